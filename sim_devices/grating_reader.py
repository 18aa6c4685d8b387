"""The six-channel grating counter box: Modbus RTU slave on RS-485 (here: a pty).

The box latches all channels at one instant at ``rate_hz`` of its own clock, with a 32-bit
µs device timestamp and a status word per channel, into a ring buffer that the master
reads with Modbus function 23 (read/write multiple registers): the write names the next
sequence number the master wants, the read returns up to six samples from there. A lost
or corrupted response is simply asked again: no sample is lost unless the buffer overruns.
The register map is in docs/protocols.md. Framing, CRC and PDU encoding are pymodbus's
(:class:`pymodbus.framer.FramerRTU`, the PDU classes), except for the hot request: a
well-formed FC23 FIFO read is answered directly (same bytes, CRC from
:mod:`drivers.modbus_rtu`), since pymodbus's pure-Python framing and CRC cost ~0.5 ms
per request. Samples are latched on the box's clock grid as they fall due; the plant is
evaluated ahead in blocks of ~0.1 s (one vectorized call instead of one per request)
and the values are released into the ring buffer only when their instant has passed.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections import Counter

import numpy as np
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    ReadWriteMultipleRegistersResponse,
    WriteMultipleRegistersRequest,
)

from drivers.modbus_rtu import crc16
from sim_devices.config import GRATING_CHANNELS, GratingSection
from sim_devices.plant import DeviceClock, Plant
from sim_devices.pty_link import PtyLink

log = logging.getLogger(__name__)

# -- the register map (mirrored in docs/protocols.md and drivers/grating_modbus.py) --------
MAGIC = 0x4752  # "GR"
PROTOCOL_VERSION = 1
N_CHANNELS = GRATING_CHANNELS
REG_INFO = 0x0000  # 16 registers, read-only
INFO_COUNT = 16
REG_LIVE = 0x0010  # 20 registers: a latch taken when read
REG_FIFO = 0x0100  # FC23: write 2 (next seq), read 5 + 20·k (k ≤ 6)
FIFO_HEADER = 5
SAMPLE_REGS = 2 + 2 * N_CHANNELS + N_CHANNELS  # t_us, counts, status = 20
MAX_SAMPLES_PER_READ = 6

# status bits per channel
ST_VALID = 0x0001
ST_SIGNAL_LOW = 0x0002
ST_HEAD_ERROR = 0x0004
ST_COUNTER_WRAPPED = 0x0008
ST_OVERRUN = 0x0010

# Modbus exception codes
EXC_ILLEGAL_FUNCTION = 1
EXC_ILLEGAL_ADDRESS = 2
EXC_ILLEGAL_VALUE = 3
EXC_DEVICE_BUSY = 6

U32 = 1 << 32
FC23_REQUEST_LEN = 17  # unit, fc, read addr/count, write addr/count, 4, 2 registers, crc
_FC23_REQ = struct.Struct(">BBHHHHBHH")


class GratingReaderDevice:
    """Register logic and sample buffer of the counter box (no I/O)."""

    def __init__(
        self,
        plant: Plant,
        config: GratingSection,
        *,
        serial_number: int = 0x00C0FFEE,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.plant = plant
        self.config = config
        self.unit_id = config.unit_id
        self.period_us = 1e6 / config.rate_hz
        self.clock = DeviceClock(ppm=config.clock_ppm, start_us=config.clock_start_us)
        self.rng = rng or np.random.default_rng(plant.cell.seed + 11)
        self.serial_number = serial_number
        offs = np.zeros(N_CHANNELS, dtype=np.int64)
        given = np.asarray(config.counter_offset_counts, dtype=np.int64)
        offs[: min(len(given), N_CHANNELS)] = given[:N_CHANNELS]
        self.counter_offset = offs
        cap = int(config.buffer_samples)
        self.cap = cap
        self.buf_t = np.zeros(cap, np.uint32)
        self.buf_counts = np.zeros((cap, N_CHANNELS), np.uint32)
        self.buf_status = np.zeros((cap, N_CHANNELS), np.uint16)
        self.lock = threading.Lock()
        self._reset_sequence()
        self.cursor = 0
        self.stats: Counter[str] = Counter()

    def _reset_sequence(self) -> None:
        self.next_seq = 0  # internal, unbounded; the wire carries it mod 2^32
        self.oldest_seq = 0
        self.next_k = 0  # sample index on this boot's clock grid
        self.prev_block: np.ndarray | None = None
        self.overrun_pending = False
        self._ahead_k0 = 0  # samples computed ahead (not yet latched): k0, k0 + 1, ...
        self._ahead_t = np.zeros(0, np.uint32)
        self._ahead_counts = np.zeros((0, N_CHANNELS), np.uint32)
        self._ahead_status = np.zeros((0, N_CHANNELS), np.uint16)

    @property
    def boot_id(self) -> int:
        return self.clock.boot_count & 0xFFFF

    def reboot(self, wall_s: float) -> None:
        with self.lock:
            self.clock.reboot(wall_s)
            self._reset_sequence()
            self.cursor = 0
            self.stats["reboots"] += 1

    # -- sampling ----------------------------------------------------------------------------
    #: seconds of samples evaluated per plant call (the values are released when due)
    LOOKAHEAD_S = 0.1

    def _compute_ahead(self, n: int) -> None:
        """Evaluate the plant for the ``n`` grid samples from ``next_k`` (not yet due)."""
        k = np.arange(self.next_k, self.next_k + n)
        t_dev = self.clock.start_us + k * self.period_us
        wall = self.clock.wall_of(t_dev)
        state = self.plant.joint_state(self.plant.clock.sim_s(wall))
        counts = self.plant.grating_counts(state.q_out_rad, self.rng, self.config.noise_counts)
        counts = counts[:, :N_CHANNELS] + self.counter_offset
        block = np.floor_divide(counts, U32)
        prev = block[:1] if self.prev_block is None else self.prev_block
        wrapped = np.diff(np.concatenate([prev, block]), axis=0) != 0
        self.prev_block = block[-1:]
        status = np.full((n, N_CHANNELS), ST_VALID, np.uint16)
        status[wrapped] |= ST_COUNTER_WRAPPED
        self._ahead_k0 = self.next_k
        self._ahead_t = np.mod(np.rint(t_dev).astype(np.int64), U32).astype(np.uint32)
        self._ahead_counts = np.mod(counts, U32).astype(np.uint32)
        self._ahead_status = status

    def produce(self, wall_s: float, max_samples: int = 20000) -> int:
        """Latch every sample due until ``wall_s`` (s since emulator start)."""
        dev_now = float(self.clock.device_us(wall_s))
        k_end = int((dev_now - self.clock.start_us) // self.period_us) + 1
        n = min(k_end - self.next_k, max_samples)
        if n <= 0:
            return 0
        block_n = max(32, int(self.config.rate_hz * self.LOOKAHEAD_S))
        done = 0
        while done < n:
            off = self.next_k - self._ahead_k0
            if not 0 <= off < self._ahead_t.shape[0]:
                self._compute_ahead(max(block_n, n - done))
                off = 0
            m = min(n - done, self._ahead_t.shape[0] - off)
            with self.lock:
                idx = np.arange(self.next_seq, self.next_seq + m) % self.cap
                self.buf_t[idx] = self._ahead_t[off : off + m]
                self.buf_counts[idx] = self._ahead_counts[off : off + m]
                self.buf_status[idx] = self._ahead_status[off : off + m]
                self.next_seq += m
                self.next_k += m
                if self.next_seq - self.oldest_seq > self.cap:
                    self.oldest_seq = self.next_seq - self.cap
                    self.overrun_pending = True
            done += m
        self.stats["samples"] += n
        return n

    def live_latch(self, wall_s: float) -> list[int]:
        t_dev = float(self.clock.device_us(wall_s))
        state = self.plant.joint_state(self.plant.clock.sim_s(np.array([wall_s])))
        counts = self.plant.grating_counts(state.q_out_rad, self.rng, self.config.noise_counts)
        counts = np.mod(counts[0, :N_CHANNELS] + self.counter_offset, U32)
        t = round(t_dev) % U32
        regs = [t >> 16, t & 0xFFFF]
        for c in counts.tolist():
            regs += [c >> 16, c & 0xFFFF]
        return regs + [ST_VALID] * N_CHANNELS

    def info_registers(self) -> list[int]:
        with self.lock:
            newest = (self.next_seq - 1) % U32
            avail = min(self.next_seq - self.cursor, 0xFFFF) if self.next_seq >= self.cursor else 0
        sn = self.serial_number
        return [
            MAGIC,
            PROTOCOL_VERSION,
            N_CHANNELS,
            round(self.config.rate_hz) & 0xFFFF,
            round(1e6 / self.plant.cell.strips[0].counts_per_mm) & 0xFFFF,  # nm/count
            self.boot_id,
            sn >> 16,
            sn & 0xFFFF,
            newest >> 16,
            newest & 0xFFFF,
            min(self.cap, 0xFFFF),
            max(0, avail),
            0,
            0,
            0,
            0,
        ]

    def fifo_block(self, want_seq_u32: int | None, k_max: int) -> list[int]:
        """The FIFO read block: header and up to ``k_max`` samples from ``want_seq_u32``."""
        block: list[int] = self.fifo_array(want_seq_u32, k_max).tolist()
        return block

    def fifo_array(self, want_seq_u32: int | None, k_max: int, pad_to: int = 0) -> np.ndarray:
        """:meth:`fifo_block` as uint16 registers, zero-padded to ``pad_to`` registers."""
        with self.lock:
            if want_seq_u32 is None:
                start = self.cursor
            else:
                span = self.next_seq - self.oldest_seq
                d = (want_seq_u32 - self.oldest_seq) % U32
                if d <= span:
                    start = self.oldest_seq + d
                else:
                    start = self.oldest_seq
                    if d > U32 // 2:
                        self.overrun_pending = True
            start = max(start, self.oldest_seq)
            self.cursor = start
            n = max(0, min(k_max, self.next_seq - start))
            pending = max(0, self.next_seq - start - n)
            out = np.zeros(max(pad_to, FIFO_HEADER + n * SAMPLE_REGS), np.uint16)
            if n:
                i0 = start % self.cap
                if i0 + n <= self.cap:
                    sl: slice | np.ndarray = slice(i0, i0 + n)
                else:
                    sl = np.arange(start, start + n) % self.cap
                t = self.buf_t[sl]
                counts = self.buf_counts[sl]
                block = out[FIFO_HEADER : FIFO_HEADER + n * SAMPLE_REGS].reshape(n, SAMPLE_REGS)
                block[:, 0] = t >> 16
                block[:, 1] = t & 0xFFFF
                block[:, 2:14:2] = counts >> 16
                block[:, 3:14:2] = counts & 0xFFFF
                block[:, 14:] = self.buf_status[sl]
                if self.overrun_pending:
                    block[0, 14:] |= ST_OVERRUN
                    self.overrun_pending = False
        seq = start % U32
        out[:FIFO_HEADER] = (seq >> 16, seq & 0xFFFF, n, min(pending, 0xFFFF), self.boot_id)
        return out

    def fifo_response(self, request: bytes | bytearray) -> bytes | None:
        """Fast path: the RTU response frame to a well-formed FC23 FIFO read frame.

        ``request`` is a complete 17-byte FC23 frame with a good CRC addressed to this
        unit. Anything else (other addresses, counts, functions) returns None and goes
        the general pymodbus way, which also produces the exception responses.
        """
        _unit, _fc, ra, rc, wa, wc, bc, hi, lo = _FC23_REQ.unpack_from(request)
        k = (rc - FIFO_HEADER) // SAMPLE_REGS
        if (
            ra != REG_FIFO
            or wa != REG_FIFO
            or wc != 2
            or bc != 4
            or rc != FIFO_HEADER + k * SAMPLE_REGS
            or not 0 <= k <= MAX_SAMPLES_PER_READ
        ):
            return None
        regs = self.fifo_array((hi << 16) | lo, k, pad_to=rc)
        body = bytes((self.unit_id, 23, 2 * rc)) + regs.astype(">u2").tobytes()
        return body + struct.pack("<H", crc16(body))

    # -- Modbus requests ------------------------------------------------------------------------
    def handle(self, request: ModbusPDU, wall_s: float) -> ModbusPDU:
        """The response PDU to a request PDU (already addressed to this unit)."""
        fc = request.function_code
        if isinstance(request, ReadWriteMultipleRegistersRequest):
            if request.write_address != REG_FIFO or request.write_count != 2:
                return self._exc(fc, EXC_ILLEGAL_ADDRESS)
            k = (request.read_count - FIFO_HEADER) // SAMPLE_REGS
            if (
                request.read_address != REG_FIFO
                or request.read_count != FIFO_HEADER + k * SAMPLE_REGS
                or not 0 <= k <= MAX_SAMPLES_PER_READ
            ):
                return self._exc(fc, EXC_ILLEGAL_VALUE)
            hi, lo = request.write_registers
            regs = self.fifo_block((hi << 16) | lo, k)
            regs += [0] * (request.read_count - len(regs))
            return ReadWriteMultipleRegistersResponse(registers=regs, dev_id=self.unit_id)
        if isinstance(request, ReadHoldingRegistersRequest):
            a, c = request.address, request.count
            if a >= REG_INFO and a + c <= INFO_COUNT:
                regs = self.info_registers()[a : a + c]
            elif a == REG_LIVE and c == SAMPLE_REGS:
                regs = self.live_latch(wall_s)
            elif a == REG_FIFO and (c - FIFO_HEADER) % SAMPLE_REGS == 0 and c >= FIFO_HEADER:
                k = min((c - FIFO_HEADER) // SAMPLE_REGS, MAX_SAMPLES_PER_READ)
                regs = self.fifo_block(None, k)
                regs += [0] * (c - len(regs))
            else:
                return self._exc(fc, EXC_ILLEGAL_ADDRESS)
            return ReadHoldingRegistersResponse(registers=regs, dev_id=self.unit_id)
        if isinstance(request, WriteMultipleRegistersRequest):
            return self._exc(fc, EXC_ILLEGAL_ADDRESS)  # nothing is writable but the cursor
        return self._exc(fc, EXC_ILLEGAL_FUNCTION)

    def _exc(self, fc: int, code: int) -> ExceptionResponse:
        self.stats[f"exception_{code}"] += 1
        return ExceptionResponse(fc, code, device_id=self.unit_id)


class ModbusRtuSlave:
    """Serves a :class:`GratingReaderDevice` on a pty with pymodbus's RTU framer.

    Fault injection (per response, from ``config.faults``): CRC error, leading garbage,
    truncation, exception 06 (busy), no response; silence windows and a reboot.
    """

    def __init__(self, device: GratingReaderDevice, link: PtyLink) -> None:
        self.device = device
        self.link = link
        self.framer = FramerRTU(DecodePDU(is_server=True))
        self.faults = device.config.faults
        self.rng = np.random.default_rng(device.plant.cell.seed + 12)
        self.stats = device.stats
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="modbus-rtu-slave", daemon=True)
        self._rebooted = False

    IDLE_S = 0.05  # wake-up period without requests

    def start(self) -> ModbusRtuSlave:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def _silent(self, wall: float) -> bool:
        f = self.faults
        return (
            f.silent_after_s >= 0 and f.silent_after_s <= wall < f.silent_after_s + f.silent_for_s
        )

    def _run(self) -> None:
        """Serve the link until stopped: latch samples, reassemble frames, answer them.
        Long because it is the per-frame hot loop: the buffer, clock and unit are locals
        it shares across the steps, and the FIFO fast path must not pay extra calls."""
        buf = b""
        last_rx = 0.0
        last_produce = -1.0
        clock = self.device.plant.clock
        unit = self.device.unit_id
        while not self._stop.is_set():
            # samples are latched lazily (at a request, or every IDLE_S): their values and
            # instants are those of the box's own clock grid either way
            data = self.link.read(0.004 if buf else self.IDLE_S)
            wall = clock.wall_s()
            f = self.faults
            if not self._rebooted and 0 <= f.restart_after_s <= wall:
                self._rebooted = True
                try:
                    self.device.produce(f.restart_after_s)  # what it latched until then
                except Exception:
                    log.exception("grating reader: sampling failed")
                self.device.reboot(f.restart_after_s)
                buf = b""
            if data or wall - last_produce >= self.IDLE_S:
                last_produce = wall
                try:
                    self.device.produce(wall)
                except Exception:  # the plant must never take the link down
                    log.exception("grating reader: sampling failed")
            if data:
                buf += data
                last_rx = time.monotonic()
            elif buf and time.monotonic() - last_rx > 0.005:
                self.stats["rx_dropped_bytes"] += len(buf)  # inter-frame silence: discard
                buf = b""
            while buf:
                if (
                    len(buf) >= FC23_REQUEST_LEN
                    and buf[0] == unit
                    and buf[1] == 23
                    and crc16(buf[: FC23_REQUEST_LEN - 2])
                    == buf[FC23_REQUEST_LEN - 2] | (buf[FC23_REQUEST_LEN - 1] << 8)
                ):
                    frame = self.device.fifo_response(buf[:FC23_REQUEST_LEN])
                    if frame is not None:
                        buf = buf[FC23_REQUEST_LEN:]
                        self.stats["requests"] += 1
                        if self._silent(wall):
                            self.stats["fault_silent"] += 1
                            continue
                        self._respond(23, frame, wall)
                        continue
                try:
                    used, pdu = self.framer.handleFrame(buf, 0, 0)
                except Exception:
                    self.stats["rx_undecodable"] += 1
                    buf = b""
                    break
                buf = buf[used:]
                if pdu is None:
                    if used:
                        continue  # skipped bytes that were no frame
                    break  # incomplete: wait for more
                if pdu.dev_id not in (unit, 0):
                    continue
                self.stats["requests"] += 1
                if self._silent(wall):
                    self.stats["fault_silent"] += 1
                    continue
                self._respond(pdu.function_code, pdu, wall)

    def _respond(self, fc: int, request: ModbusPDU | bytes, wall: float) -> None:
        """Answer ``request`` (a PDU, or the fast path's ready frame) with injected faults."""
        f = self.faults
        r = self.rng.random(5)
        if r[0] < f.silent_probability:
            self.stats["fault_no_response"] += 1
            return
        broadcast = not isinstance(request, bytes) and request.dev_id == 0
        if r[1] < f.exception_probability:
            self.stats["fault_exception"] += 1
            frame = self.framer.buildFrame(
                ExceptionResponse(fc, EXC_DEVICE_BUSY, device_id=self.device.unit_id)
            )
        elif isinstance(request, bytes):
            frame = request
        else:
            frame = self.framer.buildFrame(self.device.handle(request, wall))
        if broadcast:
            return  # no response
        if r[2] < f.crc_error_probability:
            self.stats["fault_crc"] += 1
            frame = frame[:-1] + bytes([frame[-1] ^ 0x5A])
        if r[3] < f.truncate_probability:
            self.stats["fault_truncated"] += 1
            frame = frame[: max(1, len(frame) // 2)]
        if r[4] < f.garbage_probability:
            self.stats["fault_garbage"] += 1
            frame = (
                self.rng.integers(0, 256, int(self.rng.integers(1, 9))).astype(np.uint8).tobytes()
                + frame
            )
        self.link.write(frame)
        self.stats["responses"] += 1
