"""Laser tracker: one ASCII driver over TCP (socket://) and serial (pty), in-process emulator."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from drivers.tracker_ascii import TrackerAsciiDriver
from sim_devices.config import CellConfig
from sim_devices.plant import Plant
from sim_devices.pty_link import PtyLink
from sim_devices.tracker import TrackerInstrument, TrackerServer

pytestmark = pytest.mark.timeout(60)


class Tracker:
    def __init__(self, toml: str = "") -> None:
        cfg = CellConfig.loads('[cell]\nprogram = "random"\n' + toml)
        self.plant = Plant.from_config(cfg)
        self.inst = TrackerInstrument(self.plant, cfg.tracker, cfg.effects)
        self.pty = PtyLink()
        self.server = TrackerServer(self.inst, pty=self.pty).start()

    def close(self) -> None:
        self.server.stop()
        self.pty.close()


@pytest.fixture
def tracker():
    t = Tracker()
    yield t
    t.close()


def collect(drv, seconds):
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        b = drv.read(0.05)
        if len(b):
            out.append(b)
    return out


@pytest.mark.parametrize("where", ["tcp", "serial"])
def test_stream_identify_weather_point(tracker, where):
    url = tracker.server.url if where == "tcp" else tracker.pty.path
    with TrackerAsciiDriver(url, rate_hz=500.0) as drv:
        assert drv.info["idn"].startswith("EMULATED,LT500-SIM,")
        wx = drv.weather()
        assert wx is not None and wx["temperature_c"] == pytest.approx(20.0)
        pt = drv.measure_point(5)
        assert pt is not None and pt["status"] == "OK" and np.isfinite(pt["x_mm"])
        batches = collect(drv, 1.0)
        h = drv.health()
    seq = np.concatenate([b.seq for b in batches]).astype(np.int64)
    assert len(seq) > 300 and np.all(np.diff(seq) == 1)
    t = np.concatenate([b.t_device_us for b in batches])
    assert np.all(np.diff(t) == 2000)
    values = np.concatenate([b.values for b in batches])
    # noise of ±(15 µm + 6 µm/m) at 2 σ: consecutive points of a slow arm agree to < 1 mm
    assert np.nanmax(np.abs(np.diff(values, axis=0))) < 5.0
    assert h.counters["lost_samples"] == 0


def test_scpi_style_raw_socket_session(tracker):
    with socket.create_connection(("127.0.0.1", tracker.server.port), timeout=2) as s:
        f = s.makefile("rwb")
        for cmd, prefix in [
            (b"*IDN?\n", b"EMULATED,"),
            (b"BOGUS\n", b"ERR,-113"),
            (b"STREAM:RATE 5000\n", b"ERR,-222"),
            (b"SYST:ERR?\n", b"ERR,-222"),
            (b"STATUS?\r\n", b"ST,READY,"),
        ]:
            f.write(cmd)
            f.flush()
            assert f.readline().startswith(prefix)


def test_connection_reset_mid_stream_reconnects():
    tr = Tracker("[tracker]\nreset_after_s = 0.8\n")
    try:
        with TrackerAsciiDriver(tr.server.url, reconnect_min_s=0.02) as drv:
            batches = collect(drv, 2.0)
            h = drv.health()
        assert h.counters["disconnects"] == 1 and h.counters["reconnects"] == 1
        seq = np.concatenate([b.seq for b in batches]).astype(np.int64)
        assert np.all(np.diff(seq) == 1)  # driver sequence stays increasing and unique
        t = np.concatenate([b.t_device_us for b in batches])
        assert np.all(np.diff(t) > 0) and t[-1] > 1.5e6  # streaming again after the reset
    finally:
        tr.close()


def test_beam_breaks_reported():
    tr = Tracker("[tracker]\nbeam_breaks_per_min = 120\nbeam_break_duration_s = 0.1\n")
    try:
        with TrackerAsciiDriver(tr.server.url) as drv:
            batches = collect(drv, 2.0)
            h = drv.health()
            events = list(drv.events)
        st = np.concatenate([b.status for b in batches])[:, 0]
        vals = np.concatenate([b.values for b in batches])
        broken = (st & 0x2) != 0
        assert broken.any() and h.counters["beam_breaks"] >= 1
        assert np.all(np.isnan(vals[broken]))
        assert any(e[1].startswith("BEAM_BROKEN") for e in events)
    finally:
        tr.close()


def test_serial_reopen_while_the_device_still_streams(tracker):
    """A serial tracker keeps streaming when a driver goes away without STREAM:STOP; the
    next driver's connect must not take the late reply to its STOP for *IDN?'s."""
    for _ in range(2):
        drv = TrackerAsciiDriver(tracker.pty.path, rate_hz=1000.0)
        drv.open()
        try:
            assert len(np.concatenate([b.seq for b in collect(drv, 0.3)])) > 100
            h = drv.health()
            assert h.counters["connect_failures"] == 0, h.counters
            assert drv.info["idn"].startswith("EMULATED,")
        finally:
            drv.close()  # no STREAM:STOP: the serial session keeps streaming
        time.sleep(2.0)  # the pty fills up; the session blocks in its write
