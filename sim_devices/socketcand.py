"""A minimal socketcand server on 127.0.0.1: bridges TCP clients to a python-can bus.

Speaks the subset of the socketcand protocol that python-can's ``socketcand`` interface
uses, in raw mode: the server greets ``< hi >``; the client sends ``< open CHANNEL >``
(reply ``< ok >``) and ``< rawmode >`` (reply ``< ok >``), each reply written and read
alone; then frames flow as ``< frame ID SECONDS.USEC HEXDATA >`` to the client (the data
as one contiguous hex string, which is what python-can's parser expects) and
``< send ID DLC B0 B1 ... >`` from it. No beacon is sent (no broadcast, no multicast).
Frame timestamps come from the server's :class:`~sim_devices.plant.DeviceClock` (the
CAN adapter's clock), in seconds.

Frames from a client go to the python-can bus and to the other clients, frames on the
bus go to every client, as on a real bus. With a ``sync_responder`` (the encoder nodes'
:meth:`~sim_devices.encoders.EncoderNodes.sync_frames`), a SYNC (COB-ID 0x080) from a
client is answered directly: the SYNC goes to the other clients and the nodes' TPDOs to
every client, in one write each, without a trip through the python-can bus.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable

import can

from sim_devices.plant import DeviceClock, SimClock

log = logging.getLogger(__name__)


class SocketcandServer:
    """Serves the python-can ``virtual`` channel ``channel`` to socketcand clients."""

    def __init__(
        self,
        channel: str,
        *,
        bus_name: str = "can0",
        port: int = 0,
        clock: DeviceClock | None = None,
        sim_clock: SimClock | None = None,
        sync_responder: Callable[[], list[tuple[int, bytes]]] | None = None,
    ) -> None:
        self.channel = channel
        self.sync_responder = sync_responder
        self.bus_name = bus_name
        self.clock = clock or DeviceClock()
        self.sim_clock = sim_clock or SimClock()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", port))
        self.sock.listen(4)
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.stats: Counter[str] = Counter()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._conns: list[socket.socket] = []
        self._clients: dict[socket.socket, threading.Lock] = {}  # after the handshake

    @property
    def url(self) -> str:
        return f"socketcand://127.0.0.1:{self.port}/{self.bus_name}"

    def start(self) -> SocketcandServer:
        t = threading.Thread(target=self._accept_loop, name="socketcand-accept", daemon=True)
        t.start()
        self._threads.append(t)
        return self

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conns.append(conn)
            t = threading.Thread(target=self._serve, args=(conn,), name="socketcand", daemon=True)
            t.start()
            self._threads.append(t)

    def _timestamp(self) -> float:
        return float(self.clock.device_us(self.sim_clock.wall_s())) / 1e6

    def _handshake(self, conn: socket.socket) -> bool:
        conn.sendall(b"< hi >")
        buf = b""
        for expect in (b"< open ", b"< rawmode >"):
            end = time.monotonic() + 5.0
            while b">" not in buf:
                r, _, _ = select.select([conn], [], [], 0.1)
                if r:
                    data = conn.recv(256)
                    if not data:
                        return False
                    buf += data
                if time.monotonic() > end or self._stop.is_set():
                    return False
            msg, _, buf = buf.partition(b">")
            msg = msg.strip() + b" >"
            if not msg.startswith(expect):
                conn.sendall(b"< error unexpected command >")
                return False
            if expect == b"< open ":
                name = msg[len(b"< open ") : -2].strip().decode(errors="replace")
                if name != self.bus_name:
                    conn.sendall(b"< error no such bus >")
                    return False
            conn.sendall(b"< ok >")
            time.sleep(0.05)  # one reply per client read: do not glue the next bytes to it
        return True

    def _serve(self, conn: socket.socket) -> None:
        bus = None
        try:
            if not self._handshake(conn):
                return
            bus = can.Bus(interface="virtual", channel=self.channel, receive_own_messages=False)
            self.stats["clients"] += 1
            self._clients[conn] = threading.Lock()
            writer = threading.Thread(target=self._bus_to_tcp, args=(bus, conn), daemon=True)
            writer.start()
            self._tcp_to_bus(conn, bus)
        except OSError:
            pass
        finally:
            self._clients.pop(conn, None)
            with contextlib.suppress(OSError):
                conn.close()
            if bus is not None:
                with contextlib.suppress(Exception):
                    bus.shutdown()

    def _tcp_to_bus(self, conn: socket.socket, bus: can.BusABC) -> None:
        buf = b""
        while not self._stop.is_set():
            r, _, _ = select.select([conn], [], [], 0.1)
            if not r:
                continue
            data = conn.recv(4096)
            if not data:
                return
            buf += data
            while b">" in buf:
                msg, _, buf = buf.partition(b">")
                if self.sync_responder is not None and msg.strip() == b"< send 080 0":
                    self.stats["rx_frames"] += 1
                    self._answer_sync(b"", conn)  # a SYNC without data (the usual one)
                    continue
                start = msg.find(b"<")
                if start < 0:
                    self.stats["garbage"] += 1
                    continue
                self._command(msg[start + 1 :].decode(errors="replace").split(), bus, conn)
            if len(buf) > 1024:
                buf = b""
                self.stats["garbage"] += 1

    def _command(
        self, words: list[str], bus: can.BusABC, conn: socket.socket | None = None
    ) -> None:
        if not words or words[0] != "send":
            self.stats["unknown_commands"] += 1
            return
        try:
            can_id = int(words[1], 16)
            dlc = int(words[2], 16)
            data = bytes(int(b, 16) for b in words[3 : 3 + dlc])
        except (IndexError, ValueError):
            self.stats["bad_frames"] += 1
            return
        extended = len(words[1]) > 3
        self.stats["rx_frames"] += 1
        if can_id == 0x080 and not extended and self.sync_responder is not None:
            self._answer_sync(data, conn)
            return
        bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=extended))

    def _answer_sync(self, data: bytes, sender: socket.socket | None) -> None:
        """A client's SYNC: echo it to the other clients, the TPDOs to every client."""
        assert self.sync_responder is not None
        frames = self.sync_responder()
        ts = f"{self._timestamp():.6f}"
        tpdos = "".join(f"< frame {cob:03X} {ts} {d.hex().upper()} >" for cob, d in frames)
        sync = f"< frame 080 {ts} {data.hex().upper()} >"
        for conn, lock in list(self._clients.items()):
            text = tpdos if conn is sender else sync + tpdos
            if not text:
                continue
            try:
                with lock:
                    conn.sendall(text.encode())
            except OSError:
                continue
            self.stats["tx_frames"] += len(frames) + (conn is not sender)

    def _bus_to_tcp(self, bus: can.BusABC, conn: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                msg = bus.recv(0.1)
                if msg is None:
                    continue
                out = []
                while msg is not None:
                    if msg.is_extended_id:
                        ident = f"{msg.arbitration_id:08X}"
                    else:
                        ident = f"{msg.arbitration_id:03X}"
                    ts = self._timestamp()
                    out.append(f"< frame {ident} {ts:.6f} {msg.data.hex().upper()} >")
                    msg = bus.recv(0.0)
            except can.CanError:  # the client left and its bus was shut down
                return
            lock = self._clients.get(conn)
            try:
                if lock is None:
                    conn.sendall("".join(out).encode())
                else:
                    with lock:
                        conn.sendall("".join(out).encode())
            except OSError:
                return
            self.stats["tx_frames"] += len(out)

    def stop(self) -> None:
        self._stop.set()
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.close()
        with contextlib.suppress(OSError):
            self.sock.close()
        for t in self._threads:
            t.join(timeout=1.0)
