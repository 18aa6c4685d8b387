"""Driver of the six-channel grating counter box (Modbus RTU over RS-485).

Protocol (docs/protocols.md, "Grating reader"): function 23 writes the next wanted
sample sequence number to 0x0100 and reads ``5 + 20·k`` registers from 0x0100: a header
(first sequence, count, pending, boot id) and ``k ≤ 6`` samples of a 32-bit µs device
timestamp, six 32-bit counters and six status words. Reads are idempotent: a lost or
corrupted response is asked again with the same cursor, so no sample is lost.

The Modbus stack is pymodbus's sync RTU client; its port is opened through
:func:`drivers.transport.open_stream` (so ``socket://`` and pty paths work alike).

Values: ``grating1_counts`` .. ``grating6_counts`` as int64, unwrapped from the 32-bit
counters (raw = value mod 2**32); status bits per channel as the device sends them.
"""

from __future__ import annotations

import logging
import time
from typing import Any, ClassVar

import numpy as np
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException

from drivers.base import (
    BatchSchema,
    ChannelSchema,
    DeviceClock,
    Driver,
    Option,
    SampleBatch,
    seconds_left,
)
from drivers.errors import DeviceIOError, DriverConfigError
from drivers.transport import check_url, open_stream

log = logging.getLogger(__name__)

N_CHANNELS = 6
REG_INFO = 0x0000
INFO_COUNT = 16
REG_FIFO = 0x0100
FIFO_HEADER = 5
SAMPLE_REGS = 20
MAX_SAMPLES_PER_READ = 6
MAGIC = 0x4752
FC_READ_WRITE = 23
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
            f"grating{i + 1}_counts",
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


class _Client(ModbusSerialClient):
    """pymodbus's sync RTU client with the port opened by our URL opener."""

    def __init__(self, url: str, open_kwargs: dict[str, Any], **kwargs: Any) -> None:
        super().__init__(url, **kwargs)
        self._open_kwargs = open_kwargs

    def connect(self) -> bool:
        if self.socket:
            return True
        try:
            self.socket = open_stream(self.comm_params.host, **self._open_kwargs)
        except DeviceIOError as exc:
            log.debug("open failed: %s", exc)
            self.socket = None
        return self.socket is not None


class GratingModbusDriver(Driver):
    """Reads the counter box's sample FIFO; see the module docstring."""

    kind = "grating_modbus"
    OPTIONS: ClassVar[dict[str, Option]] = {
        "unit_id": Option(int, 1, "Modbus unit (slave) id of the box"),
        "baudrate": Option(int, 2_000_000, "RS-485 line speed (ignored on pty/socket)"),
        "response_timeout_s": Option(float, 0.05, "wait for one response"),
        "samples_per_read": Option(int, 6, "k samples per FC23 read (1..6)"),
        "idle_poll_s": Option(float, 0.002, "pause when the FIFO is empty"),
        "quiet_pymodbus": Option(bool, True, "raise pymodbus's logger to CRITICAL"),
    }

    def __init__(self, url: str, **options: Any) -> None:
        check_url(url)
        super().__init__(url, **options)
        k = self.options["samples_per_read"]
        if not 1 <= k <= MAX_SAMPLES_PER_READ:
            raise DriverConfigError(f"samples_per_read must be in 1..6, got {k}")
        if self.options["quiet_pymodbus"]:
            lg = logging.getLogger("pymodbus.logging")
            if lg.level == logging.NOTSET:
                lg.setLevel(logging.CRITICAL)
        self.unit = self.options["unit_id"]
        self.client: _Client | None = None
        self.next_seq: int | None = None  # wire value (u32) of the next wanted sample
        self.seq_offset = 0  # unwrapping of the wire sequence within an epoch
        self.boot_id: int | None = None
        self.clock = DeviceClock(bits=32)
        self.last_counts: np.ndarray | None = None
        self.count_offset = np.zeros(N_CHANNELS, np.int64)
        self._rx = b""
        self.counters["stale_responses"] = 0

    @property
    def schema(self) -> BatchSchema:
        return SCHEMA

    # -- link -----------------------------------------------------------------------------
    def _trace(self, sending: bool, data: bytes) -> bytes:
        if sending:
            self._rx = b""
        else:
            self._rx = data
        return data

    def _connect(self) -> None:
        timeout = self.options["response_timeout_s"]
        self.client = _Client(
            self.url,
            {"timeout_s": 0.0, "write_timeout_s": 1.0, "baudrate": self.options["baudrate"]},
            baudrate=self.options["baudrate"],
            timeout=timeout,
            retries=0,
            trace_packet=self._trace,
        )
        if not self.client.connect():
            raise DeviceIOError(f"cannot open {self.url}")
        info = None
        for _ in range(5):  # the identification must answer (a few tries: faults happen)
            info = self._transact(
                lambda c: c.read_holding_registers(REG_INFO, count=INFO_COUNT, device_id=self.unit)
            )
            if info is not None:
                break
        if info is None:
            raise DeviceIOError(f"no Modbus answer from unit {self.unit} on {self.url}")
        regs = info.registers
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
        if self.boot_id is not None and regs[5] != self.boot_id:
            self._device_restarted()
        self.boot_id = regs[5]

    def _disconnect(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            finally:
                self.client = None

    def _device_restarted(self) -> None:
        self.count("device_restarts", detail="boot id changed")
        self.clock.restart()
        self.next_seq = None
        self.seq_offset = 0

    def _transact(self, call: Any) -> Any:
        """One Modbus transaction; None (counted) on timeout, bad frame or exception."""
        assert self.client is not None
        try:
            resp = call(self.client)
        except ConnectionException as exc:
            raise DeviceIOError(str(exc)) from exc
        except ModbusException:
            self._classify_failure()
            return None
        except OSError as exc:
            raise DeviceIOError(str(exc)) from exc
        self._check_garbage()
        if resp.isError():
            self.count("exception_responses", detail=f"code {getattr(resp, 'exception_code', '?')}")
            return None
        return resp

    def _check_garbage(self) -> None:
        rx = self._rx
        if rx and rx[0] != self.unit:
            i = 1
            while i < len(rx) - 1 and not (rx[i] == self.unit and rx[i + 1] & 0x7F in (3, 23)):
                i += 1
            self.count("garbage_bytes", i)

    def _classify_failure(self) -> None:
        rx = self._rx
        if not rx:
            self.count("timeouts")
            return
        if rx[0] != self.unit or len(rx) < 2 or rx[1] & 0x7F not in (3, 23):
            self._check_garbage()
            return
        expected = 5 if rx[1] & 0x80 else (5 + rx[2] if len(rx) > 2 else 1 << 16)
        if len(rx) < expected:
            self.count("truncated_frames")
        else:
            self.count("crc_errors")

    # -- reading --------------------------------------------------------------------------
    def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
        k = self.options["samples_per_read"]
        count = FIFO_HEADER + k * SAMPLE_REGS
        blocks: list[np.ndarray] = []
        hosts: list[np.ndarray] = []
        first_seqs: list[int] = []
        while True:
            want = 0 if self.next_seq is None else self.next_seq
            resp = self._transact(
                lambda c, want=want: c.readwrite_registers(
                    read_address=REG_FIFO,
                    read_count=count,
                    write_address=REG_FIFO,
                    values=[want >> 16, want & 0xFFFF],
                    device_id=self.unit,
                )
            )
            t_host = time.monotonic_ns()
            pending = 0
            if resp is not None:
                regs = np.asarray(resp.registers, dtype=np.uint32)
                if regs.shape[0] != count:
                    self.count("protocol_errors", detail="short register block")
                else:
                    pending = self._accept(regs, t_host, blocks, hosts, first_seqs)
            if pending == 0 and blocks:
                break
            left = seconds_left(deadline_ns)
            if left <= 0:
                break
            if pending == 0 and resp is not None:
                time.sleep(min(self.options["idle_poll_s"], left))
        if not blocks:
            return None
        return self._assemble(blocks, hosts, first_seqs)

    def _accept(
        self,
        regs: np.ndarray,
        t_host: int,
        blocks: list[np.ndarray],
        hosts: list[np.ndarray],
        first_seqs: list[int],
    ) -> int:
        first = int((regs[0] << 16) | regs[1])
        n = int(regs[2])
        pending = int(regs[3])
        boot = int(regs[4])
        if n > MAX_SAMPLES_PER_READ:
            self.count("protocol_errors", detail=f"sample count {n}")
            return 0
        if self.boot_id is not None and boot != self.boot_id:
            if blocks:  # finish the old epoch's batch first; re-read after it
                return 0
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
                return 1
        block = regs[FIFO_HEADER : FIFO_HEADER + n * SAMPLE_REGS].reshape(n, SAMPLE_REGS)
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
        b = np.concatenate(blocks)
        seq = np.concatenate(
            [
                np.arange(s, s + blk.shape[0], dtype=np.uint64)
                for s, blk in zip(first_seqs, blocks, strict=True)
            ]
        )
        t_raw = (b[:, 0] << 16) | b[:, 1]
        restarts_before = self.clock.restarts
        wraps_before = self.clock.wraps
        t_us, epoch = self.clock.unwrap(t_raw)
        self.count("device_restarts", self.clock.restarts - restarts_before, "clock went back")
        self.count("clock_wraps", self.clock.wraps - wraps_before)
        raw = ((b[:, 2:14:2] << 16) | b[:, 3:14:2]).astype(np.int64)
        prev = raw[:1] if self.last_counts is None else self.last_counts
        step = np.diff(np.concatenate([prev, raw]), axis=0)
        wraps = np.where(step > U32 // 2, -1, np.where(step < -(U32 // 2), 1, 0))
        n_wraps = int(np.count_nonzero(wraps))
        values = raw + self.count_offset + np.cumsum(wraps, axis=0) * U32
        self.count_offset += wraps.sum(axis=0) * U32
        self.last_counts = raw[-1:].copy()
        if n_wraps:
            self.count("counter_wraps", n_wraps)
        status = b[:, 14:].astype(np.uint16)
        return SampleBatch(
            SCHEMA,
            seq,
            t_us,
            epoch,
            np.concatenate(hosts),
            values,
            status,
        )
