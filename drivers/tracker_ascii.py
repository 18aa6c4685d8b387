"""Driver of the laser tracker's ASCII protocol, over TCP or serial alike.

The port is opened through :func:`drivers.transport.open_stream`, so the same code talks
to ``socket://127.0.0.1:PORT`` and to a serial device path (a pty from the emulator, a
USB adapter in the cell). On connect it stops any stream, identifies the instrument
(``*IDN?``), sets the rate and starts streaming; ``D`` lines become samples, ``EV`` lines
beam events, anything else is the reply to the pending command (:meth:`command`).

Values: ``x_mm``, ``y_mm``, ``z_mm`` (float64, tracker frame; NaN when the beam is
broken), status bits per channel. Device clock: the tracker's µs since its boot.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import time
from typing import Any, ClassVar

import numpy as np
import serial

from drivers.base import BatchSchema, ChannelSchema, DeviceClock, Driver, Option, SampleBatch
from drivers.errors import DeviceIOError, ProtocolError
from drivers.transport import check_url, open_stream, read_available, stream_fileno

log = logging.getLogger(__name__)

ST_VALID = 0x0001
ST_BEAM_BROKEN = 0x0002
ST_DROPOUT = 0x0004
STATUS_BITS = {ST_VALID: "valid", ST_BEAM_BROKEN: "beam_obstructed", ST_DROPOUT: "dropout"}
STATUS_CODES = {
    "OK": ST_VALID,
    "BROKEN_OBSTRUCTED": ST_BEAM_BROKEN,
    "BROKEN_DROPOUT": ST_DROPOUT,
}
STATUS_BYTES = {k.encode(): v for k, v in STATUS_CODES.items()}
MAX_LINE = 512
I63 = 1 << 63

SCHEMA = BatchSchema(
    kind="tracker_ascii",
    channels=tuple(
        ChannelSchema(f"{a}_mm", "mm", "float64", f"target {a} in the tracker frame") for a in "xyz"
    ),
    status_bits=STATUS_BITS,
    device_clock="tracker clock, µs since boot (64-bit)",
    source="ASCII stream 'D,seq,t_us,x,y,z,status'",
)


def parse_data_line(line: str) -> tuple[int, int, float, float, float, int]:
    """Parse ``D,seq,t_us,x,y,z,STATUS``; ProtocolError if malformed."""
    parts = line.split(",")
    if len(parts) != 7 or parts[0] != "D":
        raise ProtocolError("bad_line", line[:60])
    try:
        seq = int(parts[1])
        t_us = int(parts[2])
        x, y, z = float(parts[3]), float(parts[4]), float(parts[5])
    except ValueError as exc:
        raise ProtocolError("bad_number", line[:60]) from exc
    status = STATUS_CODES.get(parts[6])
    if status is None or not (0 <= seq < I63 and 0 <= t_us < I63):
        raise ProtocolError("bad_field", line[:60])
    return seq, t_us, x, y, z, status


class TrackerAsciiDriver(Driver):
    """Streams tracker measurements; see the module docstring."""

    kind = "tracker_ascii"
    OPTIONS: ClassVar[dict[str, Option]] = {
        "rate_hz": Option(float, 1000.0, "streaming rate (0.1..1000)"),
        "baudrate": Option(int, 921600, "serial line speed (ignored on socket://)"),
        "poll_s": Option(float, 0.003, "read granularity"),
        "command_timeout_s": Option(float, 1.0, "wait for a command's reply"),
    }

    def __init__(self, url: str, **options: Any) -> None:
        check_url(url)
        super().__init__(url, **options)
        self.port: serial.SerialBase | None = None
        self.rx = b""
        self.replies: collections.deque[str] = collections.deque(maxlen=64)
        self.events: collections.deque[tuple[int, str]] = collections.deque(maxlen=1024)
        self.clock = DeviceClock(bits=63, max_gap_us=3_600_000_000)
        self.last_seq: int | None = None  # last sequence number delivered (driver's)
        self.seq_base = 0
        self.session_last: int | None = None  # last sequence number of this session
        self._pending: list[tuple[int, int, float, float, float, int]] = []
        self._pending_host: list[int] = []
        self._carry: list[SampleBatch] = []
        self._fd: int | None = None

    @property
    def schema(self) -> BatchSchema:
        return SCHEMA

    # -- link -----------------------------------------------------------------------------
    def _connect(self) -> None:
        self.port = open_stream(
            self.url, timeout_s=self.options["poll_s"], baudrate=self.options["baudrate"]
        )
        self._fd = stream_fileno(self.port)
        self.rx = b""
        self.replies.clear()
        # samples received before the link broke are kept, numbered in the old session
        # (before any command: lines of the new stream arrive with the replies)
        carry = self._finish_pending()
        if carry is not None:
            self._carry.append(carry)
        # a new session numbers its stream from 0: keep the driver's sequence increasing
        self.seq_base = 0 if self.last_seq is None else self.last_seq + 1
        self.session_last = None
        self.command("STREAM:STOP", timeout_s=0.3)  # a serial device may still be streaming
        self._quiesce()
        idn = self.command("*IDN?")
        if idn is None or idn.count(",") != 3:
            raise DeviceIOError(f"no instrument identification from {self.url}: {idn!r}")
        self.info["idn"] = idn
        rate = self.command(f"STREAM:RATE {self.options['rate_hz']:g}")
        if rate != "OK":
            raise DeviceIOError(f"tracker refused rate: {rate!r}")
        if self.command("STREAM:START") != "OK":
            raise DeviceIOError("tracker did not start streaming")

    def _disconnect(self) -> None:
        self._fd = None
        if self.port is not None:
            with contextlib.suppress(Exception):
                self.port.close()
            self.port = None

    def _write(self, line: str) -> None:
        assert self.port is not None
        try:
            self.port.write(line.encode("ascii") + b"\n")
        except (serial.SerialException, OSError) as exc:
            raise DeviceIOError(f"write to {self.url} failed: {exc}") from exc

    def _pump(self, wait_s: float | None = None) -> bool:
        """Read what is there, waiting up to ``wait_s`` (default ``poll_s``) for it; parse
        the complete lines. False if nothing came."""
        assert self.port is not None
        wait = self.options["poll_s"] if wait_s is None else wait_s
        try:
            fd = self._fd
            data = self.port.read(65536) if fd is None else read_available(fd, wait)
        except (serial.SerialException, OSError) as exc:
            if self.rx:
                self.count("truncated_frames", detail="partial line at disconnect")
                self.rx = b""
            raise DeviceIOError(f"read from {self.url} failed: {exc}") from exc
        if not data:
            return False
        host = time.monotonic_ns()
        buf = self.rx + data
        lines = buf.split(b"\n")
        self.rx = lines.pop()
        if len(self.rx) > MAX_LINE:
            self.count("garbage_bytes", len(self.rx), "overlong line")
            self.rx = b""
        self._lines(lines, host)
        return True

    def _lines(self, lines: list[bytes], host: int) -> None:
        """Handle received lines: well-formed ``D`` lines directly from the bytes (the
        stream's bulk), everything else through :meth:`_line`."""
        pending, hosts, codes = self._pending, self._pending_host, STATUS_BYTES
        for raw in lines:
            if raw[:2] == b"D,":
                p = raw.rstrip(b"\r").split(b",")
                if len(p) == 7 and (st := codes.get(p[6])) is not None:
                    try:
                        row = (int(p[1]), int(p[2]), float(p[3]), float(p[4]), float(p[5]), st)
                    except ValueError:
                        row = None
                    if row is not None and 0 <= row[0] < I63 and 0 <= row[1] < I63:
                        pending.append(row)
                        hosts.append(host)
                        continue
            self._line(raw, host)

    def _line(self, raw: bytes, host: int) -> None:
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            self.count("garbage_bytes", len(raw), "non-ASCII")
            return
        if not line:
            return
        if line.startswith("D,"):
            try:
                self._pending.append(parse_data_line(line))
                self._pending_host.append(host)
            except ProtocolError as exc:
                self.count("protocol_errors", detail=str(exc))
            return
        if line.startswith("EV,"):
            parts = line.split(",")
            try:
                self.events.append((int(parts[2]), ",".join(parts[1:2] + parts[3:])))
            except (IndexError, ValueError):
                self.count("protocol_errors", detail=line[:60])
                return
            if parts[1] == "BEAM_BROKEN":
                self.count("beam_breaks")
            return
        self.replies.append(line)

    def command(self, line: str, timeout_s: float | None = None) -> str | None:
        """Send one command and return its reply line (None on timeout)."""
        if self.port is None:
            raise DeviceIOError("not connected")
        self.replies.clear()
        self._write(line)
        end = time.monotonic() + (timeout_s or self.options["command_timeout_s"])
        while True:
            if self.replies:
                return self.replies.popleft()
            left = end - time.monotonic()
            if left <= 0:
                break
            self._pump(min(self.options["poll_s"], left))
        self.count("timeouts", detail=f"no reply to {line!r}")
        return None

    def _quiesce(self, quiet_s: float = 0.02, max_s: float = 1.0) -> None:
        """Read until the line has been quiet for ``quiet_s`` (at most ``max_s``), then
        drop stray replies: a serial device that kept streaming while nobody read answers
        STREAM:STOP late, and that "OK" must not be taken for the next command's reply."""
        end = time.monotonic() + max_s
        while time.monotonic() < end and self._pump(quiet_s):
            pass
        self.replies.clear()

    # -- convenience queries -------------------------------------------------------------
    def identify(self) -> str | None:
        return self.command("*IDN?")

    def weather(self) -> dict[str, float] | None:
        """Air temperature (°C), pressure (hPa), humidity (%) and device time (µs)."""
        r = self.command("WEATHER?")
        if not r or not r.startswith("WX,"):
            return None
        _, t, temp, p, h = r.split(",")
        return {
            "t_device_us": int(t),
            "temperature_c": float(temp),
            "pressure_hpa": float(p),
            "humidity_pct": float(h),
        }

    def measure_point(self, n_average: int = 10) -> dict[str, Any] | None:
        """One averaged point (``MEAS:POINT? n``): x/y/z mm, status, samples used."""
        r = self.command(f"MEAS:POINT? {n_average}")
        if not r or not r.startswith("PT,"):
            return None
        _, t, x, y, z, st, used = r.split(",")
        return {
            "t_device_us": int(t),
            "x_mm": float(x),
            "y_mm": float(y),
            "z_mm": float(z),
            "status": st,
            "n_used": int(used),
        }

    def status(self) -> str | None:
        return self.command("STATUS?")

    # -- reading --------------------------------------------------------------------------
    def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
        poll = self.options["poll_s"]
        while True:
            have = bool(self._pending or self._carry)
            left = (deadline_ns - time.monotonic_ns()) / 1e9
            # with samples in hand, only take what is already there; else wait for some
            got = self._pump(0.0 if have else max(0.0, min(poll, left)))
            if have and not got:
                break
            if time.monotonic_ns() >= deadline_ns:
                break
        batch = self._finish_pending()
        parts = self._carry + ([batch] if batch is not None else [])
        self._carry = []
        if not parts:
            return None
        return SampleBatch.concat(SCHEMA, parts)

    def _finish_pending(self) -> SampleBatch | None:
        if not self._pending:
            return None
        rows = self._pending
        hosts = self._pending_host
        self._pending, self._pending_host = [], []
        n = len(rows)
        first, last = rows[0][0], rows[-1][0]
        if self.session_last is not None and first > self.session_last + 1:
            self.count("lost_samples", first - self.session_last - 1)
        if last - first + 1 != n:  # not one contiguous run: count the gaps
            gaps = np.diff(np.fromiter((r[0] for r in rows), np.int64, n))
            if np.any(gaps > 1):
                self.count("lost_samples", int(np.sum(gaps[gaps > 1] - 1)))
        self.session_last = last
        arr = np.array(rows, dtype=np.float64)
        seq = np.fromiter((r[0] for r in rows), np.int64, n) + self.seq_base
        self.last_seq = last + self.seq_base
        before = self.clock.restarts
        t_us, epoch = self.clock.unwrap(np.fromiter((r[1] for r in rows), np.int64, n))
        if self.clock.restarts != before:
            self.count("device_restarts", self.clock.restarts - before, "tracker clock went back")
        st = arr[:, 5:6].astype(np.uint16)
        return SampleBatch(
            SCHEMA,
            seq.astype(np.uint64),
            t_us,
            epoch,
            np.array(hosts, dtype=np.int64),
            arr[:, 2:5].copy(),
            np.repeat(st, 3, axis=1),
        )
