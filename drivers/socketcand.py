"""A socketcand client (raw mode) as a python-can bus, with a bulk frame reader.

Same protocol as python-can's ``socketcand`` interface (docs/protocols.md §2): the
server greets ``< hi >``, the client opens the bus (``< open CHANNEL >`` → ``< ok >``)
and switches to raw mode (``< rawmode >`` → ``< ok >``); frames arrive as
``< frame ID SECONDS.USEC HEXDATA >`` and are sent as ``< send ID DLC B0 B1 ... >``.

Why not python-can's own client: it builds one :class:`can.Message` per frame and is
read one message per ``recv`` call through a :class:`can.Notifier` thread, and its SYNC
producer is another thread; at 1 kHz SYNC with six TPDOs per cycle that is ~7000
messages and ~3000 thread wake-ups a second. :meth:`SocketcandBus.poll_frames` returns
every frame that has arrived, parsed from the whole buffer at once (one regex pass), as
plain tuples, so one thread can send SYNC and read the answers once per cycle. Other
differences: the connection fails fast when nothing listens (python-can's retries for
10 s), replies glued together in one TCP read are fine, TCP_NODELAY is on.

The :class:`can.BusABC` interface (``send``, ``recv``) works as usual, so ``canopen``
can use the bus for SDO and NMT (feed it with :meth:`canopen.Network.notify`).
"""

from __future__ import annotations

import binascii
import collections
import contextlib
import re
import select
import socket
import threading
import time
from typing import Any

import can

from drivers.errors import DeviceIOError

_FRAME = re.compile(rb"<\s*frame\s+([0-9A-Fa-f]{1,8})\s+([0-9]+(?:\.[0-9]*)?)\s+([0-9A-Fa-f]*)\s*>")
MAX_PENDING = 4096  # bytes of an unfinished message kept before it is dropped as garbage

#: One received frame: (can_id, is_extended, timestamp_s, data)
Frame = tuple[int, bool, float, bytes]


def format_send(can_id: int, data: bytes | bytearray, extended: bool = False) -> bytes:
    """The ``< send ... >`` command for one frame (data bytes in hex, space separated)."""
    ident = f"{can_id & 0x1FFFFFFF:08X}" if extended else f"{can_id & 0x7FF:03X}"
    return f"< send {ident} {len(data):X} {' '.join(f'{b:X}' for b in data)} >".encode()


def split_frames(buf: bytes) -> tuple[list[tuple[bytes, bytes, bytes]], bytes, int]:
    """``(id_hex, seconds, data_hex)`` of the frames in ``buf`` (bytes as received);
    returns (frames, the unfinished rest, bytes of non-frame input)."""
    end = buf.rfind(b">")
    if end < 0:
        return [], buf, 0
    done, rest = buf[: end + 1], buf[end + 1 :]
    found = _FRAME.findall(done)
    if done.count(b"<") == len(found) and done.count(b">") == len(found):
        return found, rest, 0  # nothing but frames (the usual case)
    used = sum(m.end() - m.start() for m in _FRAME.finditer(done))
    return found, rest, len(done) - used


def parse_frames(buf: bytes) -> tuple[list[Frame], bytes, int]:
    """Frames in ``buf``; returns (frames, the unfinished rest, bytes of non-frame input)."""
    found, rest, junk = split_frames(buf)
    frames: list[Frame] = []
    for ident, ts, data in found:
        try:
            frames.append((int(ident, 16), len(ident) > 3, float(ts), binascii.unhexlify(data)))
        except (ValueError, binascii.Error):  # odd number of hex digits
            continue
    return frames, rest, junk


class SocketcandBus(can.BusABC):
    """python-can bus on a socketcand server; see the module docstring."""

    def __init__(
        self,
        channel: str,
        host: str,
        port: int,
        *,
        connect_timeout_s: float = 2.0,
        write_timeout_s: float = 1.0,
        **kwargs: Any,
    ) -> None:
        self.host, self.port = host, port
        self.write_timeout_s = write_timeout_s
        self.garbage_bytes = 0
        self._rx = b""
        self._queue: collections.deque[Frame] = collections.deque()
        self._send_lock = threading.Lock()
        try:
            sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except OSError as exc:
            raise DeviceIOError(f"cannot connect to socketcand {host}:{port}: {exc}") from exc
        self._sock = sock
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._expect(b"< hi >", connect_timeout_s)
            sock.sendall(f"< open {channel} >".encode())
            self._expect(b"< ok >", connect_timeout_s)
            sock.sendall(b"< rawmode >")
            self._expect(b"< ok >", connect_timeout_s)
        except (OSError, DeviceIOError):
            sock.close()
            raise
        sock.setblocking(False)
        self.channel_info = f"socketcand {channel} on {host}:{port}"
        super().__init__(channel=channel, **kwargs)

    def _expect(self, reply: bytes, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while b">" not in self._rx:
            left = end - time.monotonic()
            if left <= 0:
                raise DeviceIOError(f"socketcand: no {reply.decode()!r} in {timeout_s}s")
            self._sock.settimeout(left)
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                continue
            if not data:
                raise DeviceIOError("socketcand closed the connection")
            self._rx += data
        msg, _, self._rx = self._rx.partition(b">")
        got = b" ".join((msg + b">").split())
        if got != reply:
            raise DeviceIOError(f"socketcand: expected {reply.decode()!r}, got {got.decode()!r}")

    # -- bulk reading -------------------------------------------------------------------
    def poll_raw(self, timeout_s: float = 0.0) -> list[tuple[bytes, bytes, bytes]]:
        """Frames received so far as ``(id_hex, seconds, data_hex)`` byte strings (see
        :func:`split_frames`), waiting up to ``timeout_s`` for the first bytes.

        Raises OSError when the connection is gone.
        """
        got = False
        while True:
            try:
                data = self._sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                if got or timeout_s <= 0:
                    break
                if not select.select([self._sock], [], [], timeout_s)[0]:
                    break
                timeout_s = 0.0
                continue
            if not data:
                raise OSError("socketcand server closed the connection")
            self._rx += data
            got = True
            if len(data) < 65536:
                break
        if not got:
            return []
        found, self._rx, junk = split_frames(self._rx)
        self.garbage_bytes += junk
        if len(self._rx) > MAX_PENDING:
            self.garbage_bytes += len(self._rx)
            self._rx = b""
        return found

    def poll_frames(self, timeout_s: float = 0.0) -> list[Frame]:
        """Every frame received so far, parsed (waits up to ``timeout_s`` for the first
        bytes). Raises OSError when the connection is gone."""
        frames = list(self._queue)
        self._queue.clear()
        for ident, ts, data in self.poll_raw(0.0 if frames else timeout_s):
            try:
                frames.append((int(ident, 16), len(ident) > 3, float(ts), binascii.unhexlify(data)))
            except (ValueError, binascii.Error):
                self.garbage_bytes += len(ident) + len(ts) + len(data)
        return frames

    def send_raw(self, command: bytes) -> None:
        """Send ready-made command bytes (e.g. a pre-formatted SYNC)."""
        view = memoryview(command)
        deadline = time.monotonic() + self.write_timeout_s
        with self._send_lock:
            while view:
                try:
                    view = view[self._sock.send(view) :]
                    continue
                except (BlockingIOError, InterruptedError):
                    pass
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([], [self._sock], [], left)[1]:
                    raise OSError("socketcand: write timeout")

    # -- can.BusABC --------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        try:
            self.send_raw(format_send(msg.arbitration_id, msg.data, msg.is_extended_id))
        except OSError as exc:
            raise can.CanOperationError(f"socketcand send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._queue:
            try:
                self._queue.extend(self.poll_frames(0.0 if timeout is None else timeout))
            except OSError as exc:
                raise can.CanOperationError(str(exc)) from exc
        if not self._queue:
            return None, False
        can_id, ext, ts, data = self._queue.popleft()
        msg = can.Message(
            timestamp=ts,
            arbitration_id=can_id,
            is_extended_id=ext,
            data=data,
            is_rx=True,
            channel=self.channel_info,
        )
        return msg, False

    def fileno(self) -> int:
        return self._sock.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        with contextlib.suppress(OSError):
            self._sock.close()
