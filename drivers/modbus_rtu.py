"""A lean Modbus RTU master for the functions the grating box needs (FC03, FC23).

Same bytes as any Modbus RTU stack (checked against pymodbus's framer in the tests); it
exists because the hot path of the grating driver is one FC23 transaction per 6 samples,
and pymodbus's sync serial client waits for a response by polling ``in_waiting`` with
1 ms sleeps until the byte count stops changing (at least two sleeps per transaction,
~4 ms per transaction on a loaded 2-core machine: barely 1000 samples/s, no margin to
catch up). Here a response is read event-driven (``select`` inside pyserial's ``read``)
up to its known length, and the CRC is computed two bytes per step from a 64 Ki table.

Framing (Modbus over serial line V1.02): ``unit, function, data..., CRC-16/MODBUS``
(polynomial 0xA001 reflected, initial 0xFFFF, low byte first). A normal FC03/FC23
response is ``unit, fc, byte_count, registers (big endian), crc``; an exception response
``unit, fc | 0x80, code, crc``.
"""

from __future__ import annotations

import struct
import sys
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from drivers.transport import drain, read_available, stream_fileno, write_all

if TYPE_CHECKING:  # pyserial loads with a port
    import serial

FC_READ_HOLDING = 3
FC_READ_WRITE = 23
MAX_ADU = 256  # bytes, the RTU limit
MAX_READ_REGS = 125  # FC03/FC23 read count limit (5 + 250 + ... = 255 bytes)


def _tables() -> tuple[list[int], list[int]]:
    t8 = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        t8 = np.where(t8 & 1, (t8 >> 1) ^ 0xA001, t8 >> 1)
    v = np.arange(1 << 16, dtype=np.uint32)
    c = (v >> 8) ^ t8[v & 0xFF]
    c = (c >> 8) ^ t8[c & 0xFF]
    return t8.astype(np.uint16).tolist(), c.astype(np.uint16).tolist()


_T8, _T16 = _tables()
_LITTLE = sys.byteorder == "little"


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS of ``data`` (send it low byte first)."""
    crc = 0xFFFF
    n = len(data)
    even = n & ~1
    if _LITTLE and even:
        t16 = _T16
        for w in memoryview(data)[:even].cast("B").cast("H"):
            crc = t16[crc ^ w]
    else:
        t8 = _T8
        for b in bytes(data[:even]):
            crc = (crc >> 8) ^ t8[(crc ^ b) & 0xFF]
    if n & 1:
        crc = (crc >> 8) ^ _T8[(crc ^ data[n - 1]) & 0xFF]
    return crc


def with_crc(body: bytes | bytearray) -> bytes:
    """``body`` (unit id, function code, data) with its CRC appended (low byte first)."""
    return bytes(body) + struct.pack("<H", crc16(body))


def read_holding_request(unit: int, address: int, count: int) -> bytes:
    """FC03 request frame."""
    return with_crc(struct.pack(">BBHH", unit, FC_READ_HOLDING, address, count))


def readwrite_request(
    unit: int, read_address: int, read_count: int, write_address: int, values: list[int]
) -> bytes:
    """FC23 (read/write multiple registers) request frame."""
    n = len(values)
    head = struct.pack(
        ">BBHHHHB", unit, FC_READ_WRITE, read_address, read_count, write_address, n, 2 * n
    )
    return with_crc(head + struct.pack(f">{n}H", *values))


def scan(buf: bytes | bytearray, unit: int, fc: int, byte_count: int) -> tuple[str, int, int]:
    """Find the response to function ``fc`` of ``unit`` in received bytes ``buf``.

    Returns ``(state, start, end)``:

    * ``("ok", start, end)``: a complete frame with a good CRC is ``buf[start:end]``;
      bytes before ``start`` are garbage;
    * ``("need", start, end)``: a frame starts at ``start`` and needs ``end`` bytes;
    * ``("crc", start, end)``: a complete frame at ``start`` has a bad CRC (and no later
      candidate in ``buf`` is a good frame);
    * ``("none", 0, 0)``: no frame start in ``buf`` (all garbage, or nothing yet).
    """
    n = len(buf)
    first_bad: tuple[int, int] | None = None
    i = buf.find(bytes((unit,)))
    while 0 <= i < n:
        if i + 1 >= n:
            return ("need", i, i + 5) if first_bad is None else ("crc", *first_bad)
        f = buf[i + 1]
        if f == fc | 0x80:
            end = i + 5
        elif f == fc:
            if i + 2 >= n:
                return ("need", i, i + 5 + byte_count) if first_bad is None else ("crc", *first_bad)
            end = i + 5 + byte_count if buf[i + 2] == byte_count else -1
        else:
            end = -1
        if end > 0:
            if end > n:
                if first_bad is None:
                    return ("need", i, end)
            else:
                body = buf[i : end - 2]
                if crc16(body) == buf[end - 2] | (buf[end - 1] << 8):
                    return ("ok", i, end)
                if first_bad is None:
                    first_bad = (i, end)
        i = buf.find(bytes((unit,)), i + 1)
    if first_bad is not None:
        return ("crc", *first_bad)
    return ("none", 0, 0)


@dataclass
class Reply:
    """Outcome of one transaction.

    ``kind``: ``ok`` (``payload`` holds the register bytes), ``exception`` (``code``),
    ``timeout`` (nothing came), ``truncated`` (a frame started but did not complete),
    ``crc`` (complete frame, bad CRC), ``garbage`` (bytes, but no frame). ``garbage`` is
    the number of bytes skipped before the frame; ``stale`` the bytes of an earlier,
    late answer discarded before sending.
    """

    kind: str
    payload: bytes = b""
    code: int = 0
    garbage: int = 0
    stale: int = 0
    raw: bytes = b""


class RtuMaster:
    """Request/response on a pyserial port object (``read``/``write``/``in_waiting``).

    Ports with a file descriptor (a serial device, a pty, ``socket://``; pyserial opens
    them non-blocking) are driven directly: one ``select`` and one ``read`` per arrival
    instead of pyserial's per-call bookkeeping. Others use pyserial's ``read``/``write``.
    ``timeout_s`` bounds a transaction.
    """

    def __init__(self, port: serial.SerialBase, unit: int, timeout_s: float) -> None:
        self.port = port
        self.unit = unit
        self.timeout_s = timeout_s
        self.fd = stream_fileno(port)

    # -- raw I/O -------------------------------------------------------------------------
    def _drain(self) -> int:
        """Discard what is waiting (a late answer to a request that timed out)."""
        if self.fd is None:
            n: int = self.port.in_waiting
            if n:
                self.port.read(n)
            return n
        return drain(self.fd)

    def _write(self, data: bytes, deadline: float) -> None:
        if self.fd is None:
            self.port.write(data)
        else:
            write_all(self.fd, data, max(0.0, deadline - time.monotonic()))

    def _read(self, want: int, deadline: float) -> bytes:
        """What arrives until ``deadline`` (at least one byte unless it passes)."""
        if self.fd is None:
            data: bytes = self.port.read(want)
            return data
        return read_available(self.fd, max(0.0, deadline - time.monotonic()), 4096)

    def transact(self, request: bytes, fc: int, n_regs: int) -> Reply:
        stale = self._drain()
        deadline = time.monotonic() + self.timeout_s
        self._write(request, deadline + 1.0)
        byte_count = 2 * n_regs
        buf = b""
        want = 5
        state, start, end = "none", 0, 0
        while True:
            chunk = self._read(max(1, want - len(buf)), deadline)
            if chunk:
                buf += chunk
                state, start, end = scan(buf, self.unit, fc, byte_count)
                if state == "ok":
                    frame = buf[start:end]
                    if frame[1] & 0x80:
                        return Reply("exception", code=frame[2], garbage=start, stale=stale)
                    return Reply("ok", frame[3:-2], garbage=start, stale=stale)
                if state == "crc":
                    return Reply("crc", garbage=start, stale=stale, raw=buf)
                if state == "need":
                    want = end
                else:
                    want = len(buf) + 5
                    if len(buf) > 2 * MAX_ADU:
                        return Reply("garbage", garbage=len(buf), stale=stale, raw=buf)
            if time.monotonic() >= deadline:
                break
        if not buf:
            return Reply("timeout", stale=stale)
        if state == "need":
            return Reply("truncated", garbage=start, stale=stale, raw=buf)
        return Reply("garbage", garbage=len(buf), stale=stale, raw=buf)
