"""Driver of the six-channel grating counter box (Modbus RTU over RS-485).

Protocol (docs/protocols.md, "Grating reader"): function 23 writes the next wanted
sample sequence number to 0x0100 and reads ``5 + 20·k`` registers from 0x0100: a header
(first sequence, count, pending, boot id) and ``k ≤ 6`` samples of a 32-bit µs device
timestamp, six 32-bit counters and six status words. Reads are idempotent: a lost or
corrupted response is asked again with the same cursor, so no sample is lost.

The Modbus RTU master is :mod:`drivers.modbus_rtu` (standard frames; responses read
event-driven up to their known length); the port is opened through
:func:`drivers.transport.open_stream` (so ``socket://`` and pty paths work alike).

A new driver starts with the history the box still buffers (up to 7/8 of its ring; the
driver catches up at ~10k samples/s); a reconnecting one resumes at its cursor.

Pacing: a read returns at most 6 samples, so at 1 kHz the box must be asked ~170 times a
second. With ``k`` or more samples pending (catching up after a stall or at connect) the
driver asks at once; otherwise it waits until the ``k``-th new sample is latched (or the
first waiting one is ``max_age_s`` old), timed on the box's own sample grid as seen from
the host, so that the newest sample of every response is fresh (~0.3 ms) and a request
fetches ~6 samples. ``idle_poll_s`` replaces this with a fixed pause.

Values: ``grating1_counts`` .. ``grating6_counts`` as int64, unwrapped from the 32-bit
counters (raw = value mod 2**32); status bits per channel as the device sends them.
"""

from __future__ import annotations

import logging
import struct
import time
from typing import Any, ClassVar

import numpy as np

from drivers.base import (
    BatchSchema,
    ChannelSchema,
    DeviceClock,
    Driver,
    Option,
    SampleBatch,
)
from drivers.errors import DeviceIOError, DriverConfigError
from drivers.modbus_rtu import (
    FC_READ_HOLDING,
    FC_READ_WRITE,
    Reply,
    RtuMaster,
    read_holding_request,
    readwrite_request,
)
from drivers.transport import check_url, open_stream
from edges.channel_names import GRATING, counts_column

log = logging.getLogger(__name__)

N_CHANNELS = 6
REG_INFO = 0x0000
INFO_COUNT = 16
REG_FIFO = 0x0100
FIFO_HEADER = 5
SAMPLE_REGS = 20
MAX_SAMPLES_PER_READ = 6
MAGIC = 0x4752
U32 = 1 << 32

STATUS_BITS = {
    0x0001: "valid",
    0x0002: "signal_low",
    0x0004: "head_error",
    0x0008: "counter_wrapped",
    0x0010: "overrun_before",
}
ST_COUNTER_WRAPPED = 0x0008
ST_OVERRUN = 0x0010

SCHEMA = BatchSchema(
    kind="grating_modbus",
    channels=tuple(
        ChannelSchema(
            counts_column(GRATING, i + 1),
            "count",
            "int64",
            f"joint {i + 1} strip counter, unwrapped from 32 bits (raw = value mod 2**32)",
        )
        for i in range(N_CHANNELS)
    ),
    status_bits=STATUS_BITS,
    device_clock="reader clock, µs, 32-bit on the wire, unwrapped per epoch",
    source="Modbus RTU FC23 at 0x0100",
)


class GratingModbusDriver(Driver):
    """Reads the counter box's sample FIFO; see the module docstring."""

    kind = "grating_modbus"
    OPTIONS: ClassVar[dict[str, Option]] = {
        "unit_id": Option(int, 1, "Modbus unit (slave) id of the box"),
        "baudrate": Option(int, 2_000_000, "RS-485 line speed (ignored on pty/socket)"),
        "response_timeout_s": Option(float, 0.05, "wait for one response"),
        "samples_per_read": Option(int, 6, "k samples per FC23 read (1..6)"),
        "idle_poll_s": Option(
            float, None, "fixed pause when the FIFO is drained (default: paced on the grid)"
        ),
        "max_age_s": Option(float, 0.01, "ask before a waiting sample gets older than this"),
        "quiet_pymodbus": Option(bool, True, "unused (kept for compatibility)"),
    }

    def __init__(self, url: str, **options: Any) -> None:
        check_url(url)
        super().__init__(url, **options)
        k = self.options["samples_per_read"]
        if not 1 <= k <= MAX_SAMPLES_PER_READ:
            raise DriverConfigError(f"samples_per_read must be in 1..6, got {k}")
        self.unit = self.options["unit_id"]
        self.k = k
        self.port: Any = None
        self.rtu: RtuMaster | None = None
        self.next_seq: int | None = None  # wire value (u32) of the next wanted sample
        self.seq_offset = 0  # unwrapping of the wire sequence within an epoch
        self.boot_id: int | None = None
        self.clock = DeviceClock(bits=32)
        self.last_counts: np.ndarray | None = None
        self.count_offset = np.zeros(N_CHANNELS, np.int64)
        self.rate_hz = 1000.0
        self._due_ns = 0  # when the next FIFO request is worth sending
        self._grid_raw: int | None = None  # device time of the last sample received ...
        self._grid_t_us = 0.0  # ... unwrapped for the pacing
        self._grid_ub: float | None = None  # bounds of host ns - device µs·1000
        self._grid_lb: float | None = None
        self._grid_host_ns = 0
        self._fifo_regs = FIFO_HEADER + k * SAMPLE_REGS
        self.counters["stale_responses"] = 0

    @property
    def schema(self) -> BatchSchema:
        return SCHEMA

    # -- link -----------------------------------------------------------------------------
    def _connect(self) -> None:
        self.port = open_stream(
            self.url,
            timeout_s=self.options["response_timeout_s"],
            write_timeout_s=1.0,
            baudrate=self.options["baudrate"],
        )
        self.rtu = RtuMaster(self.port, self.unit, self.options["response_timeout_s"])
        request = read_holding_request(self.unit, REG_INFO, INFO_COUNT)
        regs = None
        for _ in range(5):  # the identification must answer (a few tries: faults happen)
            payload = self._transact(request, FC_READ_HOLDING, INFO_COUNT)
            if payload is not None:
                regs = struct.unpack(f">{INFO_COUNT}H", payload)
                break
        if regs is None:
            raise DeviceIOError(f"no Modbus answer from unit {self.unit} on {self.url}")
        if regs[0] != MAGIC or regs[2] != N_CHANNELS:
            raise DeviceIOError(f"unit {self.unit} on {self.url} is not a 6-channel grating box")
        self.info.update(
            protocol_version=regs[1],
            rate_hz=regs[3],
            resolution_nm_per_count=regs[4],
            boot_id=regs[5],
            serial_number=(regs[6] << 16) | regs[7],
            buffer_samples=regs[10],
        )
        if regs[3] > 0:
            self.rate_hz = float(regs[3])
        if self.boot_id is not None and regs[5] != self.boot_id:
            self._device_restarted()
        self.boot_id = regs[5]
        if self.next_seq is None:
            self.next_seq = self._history_start(regs)
        self._due_ns = 0

    @staticmethod
    def _history_start(regs: tuple[int, ...]) -> int:
        """Wire sequence to start a new stream at: the samples the box holds, less a margin.

        The box keeps ``capacity`` samples; the oldest are overwritten while a new reader
        catches up, so it starts ``capacity // 8`` samples inside the oldest one (1 s at
        1 kHz of margin) instead of racing the overwrite; those older samples were taken
        before this driver connected and are not counted as lost.
        """
        newest = (regs[8] << 16) | regs[9]
        produced = (newest + 1) % U32  # 0 when the box has latched nothing yet
        capacity = regs[10]
        keep = capacity - capacity // 8
        return (newest + 1 - min(produced, keep)) % U32

    def _disconnect(self) -> None:
        port, self.port, self.rtu = self.port, None, None
        if port is not None:
            port.close()

    def _device_restarted(self) -> None:
        self.count("device_restarts", detail="boot id changed")
        self.clock.restart()
        self.next_seq = None
        self.seq_offset = 0
        self._grid_raw = None
        self._grid_ub = self._grid_lb = None

    def _transact(self, request: bytes, fc: int, n_regs: int) -> bytes | None:
        """One Modbus transaction: the register bytes, or None (counted) on a fault."""
        if self.rtu is None:
            raise DeviceIOError("not connected")
        try:
            reply = self.rtu.transact(request, fc, n_regs)
        except OSError as exc:  # pyserial's SerialException is an OSError
            raise DeviceIOError(str(exc)) from exc
        return self._classify(reply)

    def _classify(self, reply: Reply) -> bytes | None:
        if reply.stale:
            self.count("stale_responses", detail=f"{reply.stale} late bytes dropped")
        if reply.garbage and reply.kind != "timeout":
            self.count("garbage_bytes", reply.garbage)
        kind = reply.kind
        if kind == "ok":
            return reply.payload
        if kind == "exception":
            self.count("exception_responses", detail=f"code {reply.code}")
        elif kind == "timeout":
            self.count("timeouts")
        elif kind == "truncated":
            self.count("truncated_frames")
        elif kind == "crc":
            self.count("crc_errors")
        return None

    def _fifo_request(self, want: int) -> bytes:
        return readwrite_request(
            self.unit, REG_FIFO, self._fifo_regs, REG_FIFO, [want >> 16, want & 0xFFFF]
        )

    # -- reading --------------------------------------------------------------------------
    def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
        blocks: list[np.ndarray] = []
        hosts: list[np.ndarray] = []
        first_seqs: list[int] = []
        while True:
            now = time.monotonic_ns()
            if self._due_ns > now:
                if blocks:
                    break  # nothing more is due yet: deliver what came
                if self._due_ns > deadline_ns:
                    time.sleep(max(0, deadline_ns - now) / 1e9)
                    break
                time.sleep((self._due_ns - now) / 1e9)
            want = 0 if self.next_seq is None else self.next_seq
            request = self._fifo_request(want)
            t_send = time.monotonic_ns()
            payload = self._transact(request, FC_READ_WRITE, self._fifo_regs)
            t_host = time.monotonic_ns()
            if payload is None:
                self._due_ns = 0  # a fault: ask again at once (same cursor)
            else:
                regs = np.frombuffer(payload, ">u2").astype(np.uint32)
                pending = self._accept(regs, t_host, blocks, hosts, first_seqs, t_send)
                if pending < 0:  # the box restarted: deliver the old epoch first
                    self._due_ns = 0
                    break
                self._pace(pending, t_host)
            if t_host >= deadline_ns:
                break
        if not blocks:
            return None
        return self._assemble(blocks, hosts, first_seqs)

    #: the grid bounds widen by this much per second (device clock drift)
    GRID_LEAK_PER_S = 500e-6
    #: requests go out this long after the instant the sample they wait for is latched
    GRID_MARGIN_NS = 100_000

    def _track_grid(self, t_last_raw: int, pending: int, t_send: int, t_recv: int) -> None:
        """Bracket the box's latch grid in host time with one FIFO response.

        The newest sample latched when the request reached the box is the last returned
        plus ``pending``: it was latched before ``t_recv``, the one after it not before
        ``t_send``. In "host ns minus device µs·1000" these are an upper and a lower bound
        of the clock offset; both are kept (widening by ``GRID_LEAK_PER_S`` to follow
        drift) and requests aim at their middle, which converges to within a transaction
        time of the truth.
        """
        if self._grid_raw is None or (step := (t_last_raw - self._grid_raw) % U32) >= U32 // 2:
            self._grid_t_us = float(t_last_raw)  # first sample, or the clock went back
            self._grid_ub = self._grid_lb = None
        else:
            self._grid_t_us += step
        self._grid_raw = t_last_raw
        period_us = 1e6 / self.rate_hz
        latched_us = self._grid_t_us + min(pending, 0xFFFE) * period_us
        ub = t_recv - latched_us * 1e3
        lb = t_send - (latched_us + period_us) * 1e3
        if self._grid_ub is not None and self._grid_lb is not None:
            leak = self.GRID_LEAK_PER_S * (t_recv - self._grid_host_ns)
            ub = min(ub, self._grid_ub + leak)
            lb = max(lb, self._grid_lb - leak)
            if lb > ub:  # inconsistent (a clock jump): start over from this response
                ub = t_recv - latched_us * 1e3
                lb = t_send - (latched_us + period_us) * 1e3
        self._grid_ub, self._grid_lb, self._grid_host_ns = ub, lb, t_recv

    def _pace(self, pending: int, t_host: int) -> None:
        """When to send the next FIFO request, given ``pending`` samples left in the box.

        With ``k`` or more pending: at once. Otherwise when the ``k``-th sample after the
        last one received is latched, or earlier when the first of them would be older
        than ``max_age_s``; timed on the box's grid (:meth:`_track_grid`) so that the
        newest sample of each response is fresh. ``idle_poll_s`` replaces this with a
        fixed pause.
        """
        k = self.k
        fixed = self.options["idle_poll_s"]
        if pending >= k or (fixed is not None and pending > 0):
            self._due_ns = 0
            return
        if fixed is not None:
            self._due_ns = t_host + int(fixed * 1e9)
            return
        period_ns = 1e9 / self.rate_hz
        wait_ns = min(k * period_ns, period_ns + self.options["max_age_s"] * 1e9)
        plain = t_host + wait_ns - pending * period_ns
        if self._grid_ub is None or self._grid_lb is None:
            self._due_ns = int(plain)
            return
        offset = 0.5 * (self._grid_ub + self._grid_lb)
        due = offset + self._grid_t_us * 1e3 + wait_ns + self.GRID_MARGIN_NS
        # never later than a plain wait from now (a stale estimate)
        self._due_ns = int(min(due, plain + period_ns))

    def _accept(
        self,
        regs: np.ndarray,
        t_host: int,
        blocks: list[np.ndarray],
        hosts: list[np.ndarray],
        first_seqs: list[int],
        t_send: int | None = None,
    ) -> int:
        header: list[int] = regs[:FIFO_HEADER].tolist()
        first_hi, first_lo, n, pending, boot = header
        first = (first_hi << 16) | first_lo
        if n > MAX_SAMPLES_PER_READ or regs.shape[0] < FIFO_HEADER + n * SAMPLE_REGS:
            self.count("protocol_errors", detail=f"sample count {n}")
            return 0
        if self.boot_id is not None and boot != self.boot_id:
            if blocks:  # finish the old epoch's batch first; re-read after it
                return -1
            self._device_restarted()
        self.boot_id = boot
        if n == 0:
            return pending
        if self.next_seq is not None and first != self.next_seq:
            gap = (first - self.next_seq) % U32
            if gap < U32 // 2:
                self.count("lost_samples", gap, detail="device buffer overrun")
                if first < self.next_seq:
                    self.seq_offset += U32  # the wire sequence wrapped inside the gap
            else:
                # a late answer to an earlier request (RTU has no transaction id): the
                # samples were delivered already; drop it and ask again
                self.count("stale_responses", detail="sequence went back")
                return MAX_SAMPLES_PER_READ
        block = regs[FIFO_HEADER : FIFO_HEADER + n * SAMPLE_REGS].reshape(n, SAMPLE_REGS)
        if t_send is not None:
            t_hi, t_lo = block[-1, :2].tolist()
            self._track_grid((t_hi << 16) | t_lo, pending, t_send, t_host)
        blocks.append(block)
        hosts.append(np.full(n, t_host, np.int64))
        first_seqs.append(first + self.seq_offset)
        nxt = (first + n) % U32
        if nxt < first:
            self.seq_offset += U32
        self.next_seq = nxt
        return pending

    def _assemble(
        self, blocks: list[np.ndarray], hosts: list[np.ndarray], first_seqs: list[int]
    ) -> SampleBatch:
        if len(blocks) == 1:
            b = blocks[0]
            seq = np.arange(first_seqs[0], first_seqs[0] + b.shape[0], dtype=np.uint64)
            host = hosts[0]
        else:
            b = np.concatenate(blocks)
            seq = np.concatenate(
                [
                    np.arange(s, s + blk.shape[0], dtype=np.uint64)
                    for s, blk in zip(first_seqs, blocks, strict=True)
                ]
            )
            host = np.concatenate(hosts)
        t_raw = (b[:, 0] << 16) | b[:, 1]
        restarts_before = self.clock.restarts
        wraps_before = self.clock.wraps
        t_us, epoch = self.clock.unwrap(t_raw)
        if self.clock.restarts != restarts_before:
            self.count("device_restarts", self.clock.restarts - restarts_before, "clock went back")
        if self.clock.wraps != wraps_before:
            self.count("clock_wraps", self.clock.wraps - wraps_before)
        raw = ((b[:, 2:14:2] << 16) | b[:, 3:14:2]).astype(np.int64)
        prev = raw[:1] if self.last_counts is None else self.last_counts
        step = np.diff(raw, axis=0, prepend=prev)
        if np.abs(step).max() <= U32 // 2:  # no counter wrapped (the usual case)
            values = raw + self.count_offset
        else:
            wraps = np.where(step > U32 // 2, -1, np.where(step < -(U32 // 2), 1, 0))
            values = raw + self.count_offset + np.cumsum(wraps, axis=0) * U32
            self.count_offset += wraps.sum(axis=0) * U32
            self.count("counter_wraps", int(np.count_nonzero(wraps)))
        self.last_counts = raw[-1:].copy()
        status = b[:, 14:].astype(np.uint16)
        return SampleBatch(SCHEMA, seq, t_us, epoch, host, values, status)
