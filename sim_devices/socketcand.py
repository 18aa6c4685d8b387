"""A minimal socketcand server on 127.0.0.1: bridges TCP clients to a python-can bus.

Speaks the subset of the socketcand protocol that python-can's ``socketcand`` interface
uses, in raw mode: the server greets ``< hi >``; the client sends ``< open CHANNEL >``
(reply ``< ok >``) and ``< rawmode >`` (reply ``< ok >``), each reply written and read
alone; then frames flow as ``< frame ID SECONDS.USEC HEXDATA >`` to the client (the data
as one contiguous hex string, which is what python-can's parser expects) and
``< send ID DLC B0 B1 ... >`` from it. No beacon is sent (no broadcast, no multicast).
Frame timestamps come from the server's :class:`~sim_devices.plant.DeviceClock` (the
CAN adapter's clock), in seconds.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import threading
import time
from collections import Counter

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
    ) -> None:
        self.channel = channel
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
            writer = threading.Thread(target=self._bus_to_tcp, args=(bus, conn), daemon=True)
            writer.start()
            self._tcp_to_bus(conn, bus)
        except OSError:
            pass
        finally:
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
                start = msg.find(b"<")
                if start < 0:
                    self.stats["garbage"] += 1
                    continue
                self._command(msg[start + 1 :].decode(errors="replace").split(), bus)
            if len(buf) > 1024:
                buf = b""
                self.stats["garbage"] += 1

    def _command(self, words: list[str], bus: can.BusABC) -> None:
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
        bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=len(words[1]) > 3))
        self.stats["rx_frames"] += 1

    def _bus_to_tcp(self, bus: can.BusABC, conn: socket.socket) -> None:
        while not self._stop.is_set():
            msg = bus.recv(0.1)
            if msg is None:
                continue
            out = []
            while msg is not None:
                if msg.is_extended_id:
                    ident = f"{msg.arbitration_id:08X}"
                else:
                    ident = f"{msg.arbitration_id:03X}"
                out.append(f"< frame {ident} {self._timestamp():.6f} {msg.data.hex().upper()} >")
                msg = bus.recv(0.0)
            try:
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
