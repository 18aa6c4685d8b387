"""Grating reader: Modbus RTU driver against the emulated box on a pty (in-process).

Each fault of the issue is injected by the emulator and must give a counted, recoverable
condition with no valid sample lost (sequence numbers contiguous).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.grating_modbus import GratingModbusDriver
from drivers.registry import driver_class
from sim_devices.config import CellConfig
from sim_devices.grating_reader import GratingReaderDevice, ModbusRtuSlave
from sim_devices.plant import Plant
from sim_devices.pty_link import PtyLink

pytestmark = pytest.mark.timeout(60)


class Box:
    def __init__(self, toml: str = "") -> None:
        cfg = CellConfig.loads('[cell]\nprogram = "random"\n' + toml)
        self.plant = Plant.from_config(cfg)
        self.device = GratingReaderDevice(self.plant, cfg.grating)
        self.link = PtyLink()
        self.slave = ModbusRtuSlave(self.device, self.link).start()

    def close(self) -> None:
        self.slave.stop()
        self.link.close()


def collect(drv: GratingModbusDriver, seconds: float):
    batches = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        b = drv.read(0.05)
        if len(b):
            batches.append(b)
    return batches


def contiguous(batches) -> tuple[np.ndarray, np.ndarray]:
    seq = np.concatenate([b.seq for b in batches]).astype(np.int64)
    epoch = np.concatenate([b.epoch for b in batches])
    return seq, epoch


def test_reads_at_rate_with_contiguous_sequence():
    box = Box()
    try:
        with GratingModbusDriver(box.link.path) as drv:
            batches = collect(drv, 1.5)
            h = drv.health()
        seq, _ = contiguous(batches)
        assert len(seq) > 1000
        assert np.all(np.diff(seq) == 1)
        t = np.concatenate([b.t_device_us for b in batches])
        assert np.all(np.diff(t) == 1000)  # 1 kHz device clock
        assert batches[0].values.shape[1] == 6 and batches[0].values.dtype == np.int64
        assert np.all(np.concatenate([b.status for b in batches]) & 1)
        assert h.counters["lost_samples"] == 0 and h.state == "connected"
        assert drv.info["rate_hz"] == 1000
    finally:
        box.close()


def test_registry_finds_driver_lazily():
    assert driver_class("grating_modbus") is GratingModbusDriver


@pytest.mark.parametrize(
    ("fault", "counter"),
    [
        ("crc_error_probability", "crc_errors"),
        ("garbage_probability", "garbage_bytes"),
        ("truncate_probability", "truncated_frames"),
        ("exception_probability", "exception_responses"),
        ("silent_probability", "timeouts"),
    ],
)
def test_line_faults_are_counted_and_lose_nothing(fault, counter):
    box = Box(f"[grating.faults]\n{fault} = 0.1\n")
    try:
        with GratingModbusDriver(box.link.path, response_timeout_s=0.03) as drv:
            batches = collect(drv, 1.5)
            h = drv.health()
        seq, _ = contiguous(batches)
        assert len(seq) > 200  # 1 kHz nominal; the machine is shared and busy
        assert np.all(np.diff(seq) == 1), "a valid sample was lost"
        assert h.counters[counter] > 0, h.counters
        assert h.counters["lost_samples"] == 0
    finally:
        box.close()


def test_silent_device_then_recovers():
    box = Box("[grating.faults]\nsilent_after_s = 0.5\nsilent_for_s = 0.6\n")
    try:
        with GratingModbusDriver(box.link.path, response_timeout_s=0.02) as drv:
            batches = collect(drv, 2.0)
            h = drv.health()
        seq, _ = contiguous(batches)
        assert np.all(np.diff(seq) == 1)
        assert h.counters["timeouts"] > 5
        assert seq[-1] > 1500  # caught up after the silence from the device buffer
    finally:
        box.close()


def test_device_restart_clock_drift_and_wraps():
    # clock starts 0.4 s before its 32-bit wrap, drifts +50 ppm, reboots at 1.2 s;
    # channel 1's counter starts just below 2**32 (moves: wraps)
    box = Box(
        "[grating]\nclock_ppm = 50.0\nclock_start_us = 4294567296\n"
        "counter_offset_counts = [-1834700000, 0, 0, 0, 0, 0]\n"
        "[grating.faults]\nrestart_after_s = 1.2\n"
    )
    try:
        with GratingModbusDriver(box.link.path) as drv:
            batches = collect(drv, 2.0)
            h = drv.health()
        assert h.counters["clock_wraps"] == 1
        assert h.counters["device_restarts"] == 1
        seq, epoch = contiguous(batches)
        assert set(epoch.tolist()) == {0, 1}
        for e in (0, 1):
            assert np.all(np.diff(seq[epoch == e]) == 1)
        t = np.concatenate([b.t_device_us for b in batches])[epoch == 0]
        assert np.all(np.diff(t) == 1000) and t[-1] > 2**32  # unwrapped across the wrap
        host = np.concatenate([b.t_host_ns for b in batches])[epoch == 0]
        assert host.dtype == np.int64
    finally:
        box.close()


def test_counter_wrap_unwrapped():
    box = Box()
    try:
        st = box.plant.joint_state(np.array([0.5]))
        c = box.plant.grating_counts(st.q_out_rad, np.random.default_rng(0), 0.0)[0]
        # put channel 3 at 5 counts below the wrap: noise and motion cross it
        off = [0, 0, int(2**32 - (c[2] % 2**32) - 5), 0, 0, 0]
        box.close()
        box = Box("[grating]\ncounter_offset_counts = " + str(off) + "\nnoise_counts = 20.0\n")
        with GratingModbusDriver(box.link.path) as drv:
            batches = collect(drv, 1.0)
            h = drv.health()
        v = np.concatenate([b.values for b in batches])[:, 2]
        assert h.counters["counter_wraps"] > 0
        assert np.abs(np.diff(v)).max() < 1000  # continuous through the wrap
    finally:
        box.close()


def test_close_idempotent_and_bad_options():
    from drivers.errors import DriverConfigError

    with pytest.raises(DriverConfigError):
        GratingModbusDriver("/dev/null", nonsense=1)
    with pytest.raises(DriverConfigError):
        GratingModbusDriver("tcp://x:1")
    d = GratingModbusDriver("/nonexistent/tty", reconnect_max_s=0.05)
    with pytest.raises(OSError):
        d.open(timeout_s=0.2)
    d.close()
    d.close()


def test_rtu_codec_matches_pymodbus():
    """Our RTU frames are pymodbus's frames, both ways (requests, responses, exceptions)."""
    from pymodbus.framer import FramerRTU
    from pymodbus.pdu import DecodePDU, ExceptionResponse
    from pymodbus.pdu.register_message import (
        ReadHoldingRegistersRequest,
        ReadWriteMultipleRegistersRequest,
        ReadWriteMultipleRegistersResponse,
    )

    from drivers.modbus_rtu import (
        crc16,
        read_holding_request,
        readwrite_request,
        scan,
        with_crc,
    )

    client = FramerRTU(DecodePDU(is_server=False))
    server = FramerRTU(DecodePDU(is_server=True))
    req = ReadWriteMultipleRegistersRequest(
        read_address=0x100,
        read_count=125,
        write_address=0x100,
        write_registers=[7, 65535],
        dev_id=1,
    )
    assert readwrite_request(1, 0x100, 125, 0x100, [7, 65535]) == client.buildFrame(req)
    assert read_holding_request(1, 0, 16) == client.buildFrame(
        ReadHoldingRegistersRequest(address=0, count=16, dev_id=1)
    )
    used, pdu = server.handleFrame(readwrite_request(3, 0x100, 45, 0x100, [1, 2]), 0, 0)
    assert used == 17 and pdu.dev_id == 3 and pdu.write_registers == [1, 2]
    regs = list(range(0, 125 * 500, 500))
    frame = server.buildFrame(ReadWriteMultipleRegistersResponse(registers=regs, dev_id=1))
    assert len(frame) == 255
    assert scan(frame, 1, 23, 250) == ("ok", 0, 255)
    assert scan(b"\x07\x01" + frame, 1, 23, 250) == ("ok", 2, 257)
    assert scan(frame[:100], 1, 23, 250) == ("need", 0, 255)
    bad = frame[:-1] + bytes([frame[-1] ^ 1])
    assert scan(bad, 1, 23, 250)[0] == "crc"
    exc = server.buildFrame(ExceptionResponse(23, 6, device_id=1))
    assert scan(exc, 1, 23, 250) == ("ok", 0, 5) and exc[2] == 6
    assert crc16(b"") == 0xFFFF
    assert with_crc(bytes.fromhex("01030000000A")) == bytes.fromhex("01030000000AC5CD")


def test_fast_fifo_path_equals_pymodbus_path():
    """The emulator's direct FC23 answer is byte for byte pymodbus's answer."""
    from pymodbus.framer import FramerRTU
    from pymodbus.pdu import DecodePDU

    from drivers.modbus_rtu import readwrite_request

    cfg = CellConfig.loads('[cell]\nprogram = "random"\n')
    plant = Plant.from_config(cfg)
    dev = GratingReaderDevice(plant, cfg.grating)
    dev.produce(0.5)
    server = FramerRTU(DecodePDU(is_server=True))
    for want, k in [(0, 6), (17, 6), (490, 3), (499, 6), (10**6, 6), (5, 0)]:
        req = readwrite_request(1, 0x100, 5 + 20 * k, 0x100, [want >> 16, want & 0xFFFF])
        fast = dev.fifo_response(req)
        _, pdu = server.handleFrame(req, 0, 0)
        slow = server.buildFrame(dev.handle(pdu, 0.5))
        assert fast == slow, (want, k)
    # anything unusual goes the general way (and gets its exception there)
    assert dev.fifo_response(readwrite_request(1, 0x100, 26, 0x100, [0, 0])) is None
    assert dev.fifo_response(readwrite_request(1, 0x100, 145, 0x100, [0, 0])) is None
    assert dev.fifo_response(readwrite_request(1, 0x200, 25, 0x100, [0, 0])) is None


def test_new_reader_takes_buffered_history_without_loss():
    """A driver connecting to a box whose ring has wrapped starts inside the ring's
    oldest end (margin against the overwrite) and catches up with nothing lost."""
    box = Box("[grating]\nbuffer_samples = 1024\n")
    try:
        time.sleep(1.5)  # ~1500 samples latched: the ring has overwritten its start
        with GratingModbusDriver(box.link.path) as drv:
            batches = collect(drv, 1.0)
            h = drv.health()
        seq, _ = contiguous(batches)
        assert np.all(np.diff(seq) == 1)
        assert h.counters["lost_samples"] == 0, h.counters
        assert len(seq) > 1024 - 1024 // 8  # the buffered history, then live samples
        assert seq[0] >= 1400 - 1024  # not from sequence 0 (overwritten before connecting)
    finally:
        box.close()
