"""Fuzzing every parser on both sides with hypothesis: nothing raises but the documented
errors, and garbage is counted rather than crashing."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.base import DeviceClock
from drivers.errors import ProtocolError
from drivers.grating_modbus import GratingModbusDriver
from drivers.tracker_ascii import TrackerAsciiDriver, parse_data_line
from sim_devices.config import CellConfig
from sim_devices.errors import SimConfigError

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def plant():
    from sim_devices.plant import Plant

    return Plant.from_config(CellConfig.loads('[cell]\nprogram = "hold"\n'))


@FUZZ
@given(st.text(max_size=120))
def test_tracker_data_line_parser(text):
    try:
        seq, t, _x, _y, _z, status = parse_data_line(text)
    except ProtocolError:
        return
    assert seq >= 0 and t >= 0 and status in (1, 2, 4)


@FUZZ
@given(st.lists(st.binary(max_size=80), max_size=20))
def test_tracker_driver_line_handler_counts_garbage(chunks):
    drv = TrackerAsciiDriver("socket://127.0.0.1:9")
    for c in chunks:
        drv._line(c, 0)
    assert all(isinstance(r, str) for r in drv.replies)
    assert len(drv._pending) <= len(chunks)


@FUZZ
@given(st.text(max_size=80))
def test_tracker_emulator_commands(plant, text):
    from sim_devices.tracker import TrackerInstrument, TrackerSession

    cfg = CellConfig()
    inst = TrackerInstrument(plant, cfg.tracker, cfg.effects)
    s = TrackerSession(inst, port=None, name="fuzz")  # type: ignore[arg-type]
    reply = s.command(text.strip())
    assert isinstance(reply, str)
    assert "\n" not in reply


@FUZZ
@given(st.binary(max_size=300))
def test_modbus_slave_request_decoding(plant, data):
    from pymodbus.framer import FramerRTU
    from pymodbus.pdu import DecodePDU

    from sim_devices.grating_reader import GratingReaderDevice

    dev = GratingReaderDevice(plant, CellConfig().grating)
    framer = FramerRTU(DecodePDU(is_server=True))
    try:
        _used, pdu = framer.handleFrame(data, 0, 0)
    except Exception:  # the slave loop catches and counts these (rx_undecodable)
        return
    if pdu is not None:
        resp = dev.handle(pdu, 0.1)
        frame = FramerRTU(DecodePDU(is_server=True)).buildFrame(resp)
        assert len(frame) <= 256


@FUZZ
@given(
    st.lists(st.integers(0, 0xFFFF), min_size=125, max_size=125),
    st.binary(max_size=40),
)
def test_grating_driver_block_and_failure_classification(regs, rx):
    from drivers.modbus_rtu import Reply

    drv = GratingModbusDriver("/dev/null")
    blocks, hosts, firsts = [], [], []
    drv._accept(np.asarray(regs, np.uint32), 0, blocks, hosts, firsts)
    if blocks:
        b = drv._assemble(blocks, hosts, firsts)
        assert b.values.shape == (len(b), 6)
    for kind in ("ok", "exception", "timeout", "truncated", "crc", "garbage"):
        drv._classify(Reply(kind, rx, garbage=len(rx), stale=len(rx) % 3))
    assert sum(drv.counters.values()) >= 0


@FUZZ
@given(st.binary(max_size=300), st.integers(0, 8))
def test_rtu_response_scanner(data, k):
    """Any bytes: a result that is consistent with them, never an exception."""
    from drivers.modbus_rtu import crc16, scan

    nbytes = 2 * (5 + 20 * k)
    state, start, end = scan(data, 1, 23, nbytes)
    assert state in ("ok", "need", "crc", "none")
    if state == "ok":
        frame = data[start:end]
        assert frame[0] == 1 and frame[1] in (23, 0x97)
        assert crc16(frame[:-2]) == frame[-2] | frame[-1] << 8
        assert len(frame) == (5 if frame[1] & 0x80 else nbytes + 5)
    elif state == "need":
        assert end > len(data) and data[start] == 1
    elif state == "crc":
        assert end <= len(data)


@FUZZ
@given(st.lists(st.integers(1, 5000), min_size=1, max_size=200), st.integers(0, 2**32 - 1))
def test_device_clock_unwraps_steps(steps, start):
    raw = (start + np.cumsum(steps)) % 2**32
    clock = DeviceClock(bits=32)
    half = len(raw) // 2
    a, _ = clock.unwrap(raw[:half])
    b, ep = clock.unwrap(raw[half:])
    out = np.concatenate([a, b])
    assert np.all(np.diff(out) == np.asarray(steps[1:]))
    assert clock.restarts == 0 and np.all(ep == 0)


@FUZZ
@given(st.text(max_size=200))
def test_cell_config_parser(text):
    with contextlib.suppress(SimConfigError):
        CellConfig.loads(text)


@FUZZ
@given(st.lists(st.text(max_size=12), max_size=12))
def test_socketcand_server_command_parser(words):
    import can

    from sim_devices.socketcand import SocketcandServer

    class FakeBus:
        def __init__(self) -> None:
            self.sent: list[can.Message] = []

        def send(self, msg: can.Message) -> None:
            self.sent.append(msg)

    srv = SocketcandServer.__new__(SocketcandServer)
    from collections import Counter

    srv.stats = Counter()
    srv.sync_responder = None
    srv._clients = {}
    srv._command(words, FakeBus())  # type: ignore[arg-type]


@FUZZ
@given(
    st.lists(
        st.binary(max_size=60) | st.sampled_from([b"< frame 181 12.5 0A0B0C0D >"]), max_size=20
    )
)
def test_socketcand_client_frame_parser(chunks):
    from drivers.socketcand import parse_frames

    buf = b"".join(chunks)
    frames, rest, junk = parse_frames(buf)
    assert junk >= 0 and len(rest) <= len(buf)
    for can_id, _ext, ts, data in frames:
        assert 0 <= can_id < 2**32 and ts >= 0 and len(data) * 2 <= len(buf)
    if b"< frame 181 12.5 0A0B0C0D >" in buf and buf.endswith(b">"):
        assert (0x181, False, 12.5, bytes.fromhex("0A0B0C0D")) in frames


_D_LINE = st.builds(
    lambda seq, t, x, status, tail: f"D,{seq},{t},{x},{x},{x},{status}{tail}".encode(),
    st.integers(-5, 2**64),
    st.integers(-5, 2**64),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["OK", "BROKEN_OBSTRUCTED", "BROKEN_DROPOUT", "ok", "OK ", "X"]),
    st.sampled_from(["", "\r", " \r", ",1"]),
)


@FUZZ
@given(st.lists(_D_LINE | st.binary(max_size=60), max_size=20))
def test_tracker_fast_line_path_equals_general_path(lines):
    """D lines parsed from bytes give exactly what the general line handler gives."""
    fast = TrackerAsciiDriver("socket://127.0.0.1:9")
    slow = TrackerAsciiDriver("socket://127.0.0.1:9")
    fast._lines(list(lines), 7)
    for raw in lines:
        slow._line(raw, 7)
    np.testing.assert_equal(fast._pending, slow._pending)
    assert fast._pending_host == slow._pending_host
    assert dict(fast.counters) == dict(slow.counters)
    assert list(fast.replies) == list(slow.replies)
