"""The daemon as a separate process with an in-process fake device (daq.testing), and a
separate subscriber process: every sample arrives in order, timestamps track the fake's
truth clock, health is published, recording → replay gives the same samples, SIGTERM
exits 0 with a finished recording, and unplug/replug loses only the time away."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from daq.bus import Receiver, open_session
from daq.daemon import Daemon
from daq.recording_reader import read_recording
from daq.testing import FakeDriver, free_port, loopback_sink, recorded_columns
from daq.testing import daq_cli as daq

pytestmark = pytest.mark.timeout(120)

KEY = "cell/t/robot/r1/fake/samples"


def write_config(tmp: Path, port: int, extra: str = "") -> Path:
    p = tmp / "cell.toml"
    p.write_text(
        f"""
[cell]
name = "t"
robot = "r1"
[zenoh]
listen = ["tcp/127.0.0.1:{port}"]
[publish]
health_period_s = 0.5
[[device]]
name = "fake"
driver = "daq.testing:FakeDriver"
url = "fake://"
rate_hz = 1000
joints = [1, 2, 3]
{extra}
"""
    )
    return p


def start_echo(port: int, out: Path) -> subprocess.Popen:
    proc = daq(
        "echo", "cell/**", "--jsonl", str(out), "--ready", "--idle", "3", "--duration", "60",
        "--connect", f"tcp/127.0.0.1:{port}",
    )  # fmt: skip
    return proc


def read_jsonl(path: Path) -> tuple[dict[str, np.ndarray], list[dict]]:
    cols: dict[str, list] = {}
    health = []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if "json" in rec:
            health.append(rec["json"])
            continue
        if rec["key"] != KEY:
            continue
        for k, v in rec["columns"].items():
            cols.setdefault(k, []).extend(v)
    return {k: np.asarray(v) for k, v in cols.items()}, health


def test_daemon_subscriber_record_replay(tmp_path):
    port = free_port()
    cfg = write_config(tmp_path, port)
    rec_path = tmp_path / "run.mcap"
    live = tmp_path / "live.jsonl"
    # the daemon first (it listens), then the subscriber connects; the daemon's first
    # samples may precede the subscription, so compare the common range
    d = daq("run", "--config", str(cfg), "--duration", "6", "--record", str(rec_path))
    first = json.loads(d.stdout.readline())
    assert first["daq"] == "running" and first["keys"] == [KEY]
    assert first["recording"] == str(rec_path)
    e = start_echo(port, live)
    assert "ready" in e.stderr.readline()
    out, err = d.communicate(timeout=60)
    assert d.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["daq"] == "stopped"
    e.communicate(timeout=30)
    got, health = read_jsonl(live)
    # every sample after the subscription started, in order, no gaps
    seq = got["seq"]
    assert len(seq) > 2000
    assert np.all(np.diff(seq) == 1)
    assert seq[-1] == summary["devices"]["fake"]["samples"] - 1
    np.testing.assert_array_equal(got["grating1_counts"], seq)
    # mapped time tracks the fake's truth (latch at t0 + seq/rate on the monotonic clock)
    rec = recorded_columns(rec_path, KEY)
    np.testing.assert_array_equal(rec["seq"], np.arange(len(rec["seq"])))
    truth_rel = rec["seq"] * 1_000_000  # ns since the first sample, 1 kHz
    mapped_rel = rec["t_mapped_ns"] - rec["t_mapped_ns"][0]
    err_ms = (mapped_rel - truth_rel) / 1e6
    settled = err_ms[len(err_ms) // 3 :]
    assert np.max(np.abs(settled - np.median(settled))) < 2.0, np.abs(settled).max()
    assert np.all(rec["t_mapped_ns"] <= rec["t_host_rx_ns"] + 2_000_000)
    # health: rates, gaps, clock-fit quality, once per period
    assert health and health[-1]["device"] == "fake"
    assert abs(health[-2]["rate_hz"] - 1000) < 300
    assert health[-1]["gaps"] == 0 and "drift_ppm" in health[-1]["clock"]
    assert abs(health[-1]["clock"]["drift_ppm"] + 30) < 20  # the fake runs 30 ppm fast
    # replay the recording to a fresh subscriber: the same samples
    port2 = free_port()
    replayed = tmp_path / "replayed.jsonl"
    e2 = start_echo(port2, replayed)
    r = daq("replay", str(rec_path), "--fast", "--listen", f"tcp/127.0.0.1:{port2}",
            "--wait-subscribers", "10")  # fmt: skip
    _, r_err = r.communicate(timeout=60)
    assert r.returncode == 0, r_err
    assert "ready" in e2.stderr.readline()
    e2.communicate(timeout=30)
    back, _ = read_jsonl(replayed)
    for k in rec:
        np.testing.assert_array_equal(back[k], rec[k], err_msg=k)


def test_sigterm_stops_cleanly_with_finished_recording(tmp_path):
    port = free_port()
    cfg = write_config(tmp_path, port)
    rec_path = tmp_path / "term.mcap"
    d = daq("run", "--config", str(cfg), "--record", str(rec_path))
    assert json.loads(d.stdout.readline())["daq"] == "running"
    time.sleep(2.0)
    d.send_signal(signal.SIGTERM)
    out, err = d.communicate(timeout=30)
    assert d.returncode == 0, err
    assert json.loads(out.strip().splitlines()[-1])["signal"] is True
    rec = read_recording(rec_path)
    n = sum(1 for _ in rec.messages_iter())
    assert rec.complete and n > 100


def test_kill_9_during_recording_leaves_readable_file(tmp_path):
    port = free_port()
    cfg = write_config(tmp_path, port)
    rec_path = tmp_path / "killed.mcap"
    d = daq("run", "--config", str(cfg), "--record", str(rec_path))
    assert json.loads(d.stdout.readline())["daq"] == "running"
    time.sleep(3.0)
    os.kill(d.pid, signal.SIGKILL)
    d.communicate(timeout=30)
    rec = recorded_columns(rec_path, KEY)
    # chunks close every second: at least the first two seconds are there, whole
    assert len(rec["seq"]) > 1000
    np.testing.assert_array_equal(rec["seq"], np.arange(len(rec["seq"])))
    r = subprocess.run(
        [sys.executable, "-m", "daq.cli", "recover", "--in-place", str(rec_path)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert read_recording(rec_path) is not None
    info = subprocess.run(
        [sys.executable, "-m", "daq.cli", "info", str(rec_path)], capture_output=True, text=True
    )
    assert info.returncode == 0 and json.loads(info.stdout)["complete"]


def test_unplug_replug_loses_only_the_time_away(tmp_path):
    """In process: the fake device is away 1.0 s mid-run; the daemon keeps going."""
    port = free_port()
    from daq.config import load

    cfg = load(write_config(tmp_path, port), environ={})
    drivers: list[FakeDriver] = []

    def factory(dev):
        drv = FakeDriver(dev.url, reconnect_min_s=0.05, reconnect_max_s=0.2)
        drv.away(1.5, 1.0)
        drivers.append(drv)
        return drv

    sink = open_session(loopback_sink(port))
    try:
        with Daemon(cfg, driver_factory=factory) as daemon:
            recv = Receiver(sink, "cell/t/**")
            time.sleep(0.5)
            t = threading.Thread(target=daemon.run, args=(4.5,))
            t.start()
            seqs = []
            while True:
                got = recv.receive(1.0)
                if got is None:
                    if not t.is_alive():
                        break
                    continue
                seqs.append(got.columns["seq"].copy())
            t.join()
            health = daemon.devices[0].health(1.0)
    finally:
        sink.close()
    seq = np.concatenate(seqs)
    assert np.all(np.diff(seq) > 0)
    jumps = np.diff(seq)[np.diff(seq) > 1]
    assert len(jumps) == 1  # one gap ...
    assert 900 <= jumps[0] - 1 <= 1300  # ... of about the second it was away (1 kHz)
    assert health["gaps"] == 1 and 900 <= health["samples_missing"] <= 1300
    assert 0.8 <= health["away_s"] <= 1.6 and health["reconnects"] >= 1


def test_a_device_that_fails_to_build_is_the_error_the_daemon_raises(tmp_path):
    """The second device names a channel its driver lacks: the daemon closes the first
    one (never started) and raises the configuration error, not another."""
    from daq.config import load
    from daq.errors import ConfigError

    second = (
        '[[device]]\nname = "bad"\ndriver = "daq.testing:FakeDriver"\nurl = "fake://"\n'
        'channels = { samples = ["nope_counts"] }\n'
    )
    cfg = load(write_config(tmp_path, free_port(), second), environ={})
    with pytest.raises(ConfigError, match=r"'bad'.*no channel 'nope_counts'"):
        Daemon(cfg, driver_factory=lambda dev: FakeDriver(dev.url))  # threads, always
