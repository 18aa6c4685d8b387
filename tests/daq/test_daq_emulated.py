"""End to end on the emulated cell: ``daq run`` (spawning ``sim-cell serve``) and a
separate ``daq echo`` subscriber process on loopback.

* every sample the daemon published after the subscription arrives, in order, and equals
  what was recorded;
* every settled grating and tracker sample's mapped timestamp is within ±3 ms of the
  emulator's truth clock (the box's clock runs 40 ppm fast; the origin is the
  ``emulator_t0_monotonic_ns`` the daemon prints; ``t_mapped_ok`` marks settled: the
  first seconds are a backlog catch-up, the box buffered since its start), and the
  fitted drift is plausible;
* the grating box goes silent for 1 s (its FIFO keeps sampling): nothing is lost; the
  tracker's connection is reset (unplug/replug): it reconnects and the device time lost
  matches the time it was away.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from daq.columnar import StreamSchema, decode
from daq.recording_reader import read_recording
from daq.testing import free_port

pytestmark = pytest.mark.timeout(180)

SIM = """
[cell]
program = "random"
[grating]
rate_hz = 200.0
clock_ppm = 40.0
[grating.faults]
silent_after_s = 5.0
silent_for_s = 1.0
[tracker]
serial = false
reset_after_s = 6.0
[encoders]
enabled = false
"""
PPM = 40.0
RATE = 200.0
DURATION = 12.0


def recorded(path: Path) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, list[dict]]]:
    data: dict[str, dict[str, list]] = {}
    health: dict[str, list[dict]] = {}
    rec = read_recording(path)
    for m in rec.messages_iter():
        if m.channel.message_encoding == "json":
            if m.topic.endswith("/health"):
                health.setdefault(m.topic, []).append(json.loads(m.data))
            continue
        _, cols = decode(StreamSchema.loads(m.schema.data), m.data)
        d = data.setdefault(m.topic, {})
        for k, v in cols.items():
            d.setdefault(k, []).append(v)
    assert rec.complete
    return {t: {k: np.concatenate(v) for k, v in d.items()} for t, d in data.items()}, health


def test_emulated_cell_end_to_end(tmp_path):
    (tmp_path / "sim.toml").write_text(SIM)
    port = free_port()
    rec_path = tmp_path / "cell.mcap"
    live = tmp_path / "live.jsonl"
    t_spawn = time.monotonic_ns()
    d = subprocess.Popen(
        [sys.executable, "-m", "daq.cli", "run", "--sim-config", str(tmp_path / "sim.toml"),
         "--rate", str(RATE), "--duration", str(DURATION), "--record", str(rec_path),
         "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    first = json.loads(d.stdout.readline())
    t_first_line = time.monotonic_ns()
    assert first["daq"] == "running" and len(first["keys"]) == 2
    e = subprocess.Popen(
        [sys.executable, "-m", "daq.cli", "echo", "cell/**", "--jsonl", str(live), "--ready",
         "--idle", "4", "--duration", "90", "--connect", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert "ready" in e.stderr.readline()
    _, err = d.communicate(timeout=120)
    assert d.returncode == 0, err[-3000:]
    e.communicate(timeout=60)
    data, health = recorded(rec_path)
    assert "cell/emulated/robot/robot1/grating/samples" in data, (list(data), err[-3000:])
    grating = data["cell/emulated/robot/robot1/grating/samples"]
    tracker = data["cell/emulated/robot/robot1/tracker/samples"]

    # every sample published after the subscription arrived, in order, equal to the record
    got: dict[str, dict[str, list]] = {}
    for line in live.read_text().splitlines():
        rec = json.loads(line)
        if "columns" in rec:
            g = got.setdefault(rec["key"], {})
            for k, v in rec["columns"].items():
                g.setdefault(k, []).extend(v)
    for key, cols in data.items():
        seq = np.asarray(got[key]["seq"])
        assert np.all(np.diff(seq) > 0), key  # device-side losses would show as gaps
        i0 = int(np.searchsorted(cols["seq"], seq[0]))
        for name in ("seq", "t_device_us", "t_mapped_ns", "status"):
            np.testing.assert_array_equal(
                np.asarray(got[key][name]), cols[name][i0:], err_msg=f"{key} {name}"
            )

    # the grating box: no sample lost although it was silent for a second
    assert np.all(np.diff(grating["seq"]) == 1)
    hg = health["cell/emulated/robot/robot1/grating/health"][-1]
    assert hg["samples_missing"] == 0 and hg["lost_samples"] == 0 and hg["time_gaps"] == 0
    assert len(grating["seq"]) >= RATE * (DURATION - 3)

    # mapped timestamps vs the truth clock: latch = t0 + t_dev / (1 + ppm·1e-6) on the
    # emulator's monotonic clock, t0 the origin it printed (inside our spawn ... first line)
    t0 = int(first["emulator_t0_monotonic_ns"])
    assert t_spawn <= t0 <= t_first_line
    off = _offset(rec_path)
    truth = t0 + grating["t_device_us"] * 1e3 / (1 + PPM * 1e-6)
    err_ms = (grating["t_mapped_ns"] - off - truth) / 1e6
    ok = grating["t_mapped_ok"] == 1
    assert ok.mean() > 0.25  # settles after a few seconds
    # stated tolerance: every settled sample within ±3 ms of the truth, on a busy 2-core
    # host (typically ±0.3 ms: the fit's lower envelope sits on the least-delayed reads)
    print(
        "grating mapped - truth, settled (ms): p0 p1 p50 p99 p100",
        np.percentile(err_ms[ok], [0, 1, 50, 99, 100]),
    )
    assert np.abs(err_ms[ok]).max() <= 3.0, np.percentile(err_ms[ok], [0, 1, 50, 99, 100])
    # the tracker (its clock at 0 ppm here; a connection reset is not a reboot)
    t_err_ms = (tracker["t_mapped_ns"] - off - (t0 + tracker["t_device_us"] * 1e3)) / 1e6
    t_ok = tracker["t_mapped_ok"] == 1
    assert t_ok.mean() > 0.25
    print(
        "tracker mapped - truth, settled (ms): p0 p1 p50 p99 p100",
        np.percentile(t_err_ms[t_ok], [0, 1, 50, 99, 100]),
    )
    assert np.abs(t_err_ms[t_ok]).max() <= 3.0, np.percentile(t_err_ms[t_ok], [0, 1, 50, 99, 100])
    # ~10 s of a 0.3 ms envelope pins the drift to tens of ppm only (longer runs do better)
    assert abs(hg["clock"]["drift_ppm"] + PPM) < 100, hg["clock"]
    late_ms = (grating["t_mapped_ns"][ok] - grating["t_host_rx_ns"][ok]) / 1e6
    assert late_ms.max() <= 3.0, (late_ms.max(), np.flatnonzero(late_ms > 3.0)[:5], ok.mean())

    # the tracker was reset (unplugged) once: it came back, and lost only the time away
    ht = health["cell/emulated/robot/robot1/tracker/health"][-1]
    assert ht["reconnects"] >= 1 and ht["disconnects"] >= 1
    assert ht["time_gaps"] >= 1
    assert abs(ht["time_missing_s"] - ht["away_s"]) < 0.5, ht
    t_rel = (tracker["t_mapped_ns"] - tracker["t_mapped_ns"][0]) / 1e9
    assert t_rel[-1] > 8.0  # samples after the reset at 6 s
    # tracker points went to a Foxglove channel too
    topics = {ch.topic for ch in _channels(rec_path)}
    assert "cell/emulated/robot/robot1/tracker/samples/points" in topics


def _offset(path: Path) -> int:
    rec = read_recording(path)
    for _ in rec.messages_iter():
        break
    return int(rec.metadata["daq"]["host_utc_minus_monotonic_ns"])


def _channels(path: Path):
    rec = read_recording(path)
    for _ in rec.messages_iter():
        pass
    return rec.channels.values()


def test_daq_run_without_config_records_the_emulated_cell(tmp_path):
    port = free_port()
    r = subprocess.run(
        [sys.executable, "-m", "daq.cli", "run", "--duration", "3",
         "--listen", f"tcp/127.0.0.1:{port}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    path = tmp_path / lines[0]["recording"]
    assert lines[0]["cell"] == "emulated" and path.name.startswith("daq-emulated-")
    assert f"recorded to {lines[0]['recording']}" in r.stderr
    assert {d["name"] for d in lines[0]["emulated"]} == {"grating", "tracker", "encoders"}
    recording, counts = _scan(path)
    assert recording.complete
    for dev in ("grating", "tracker", "encoders"):
        assert counts.get(f"cell/emulated/robot/robot1/{dev}/samples", 0) > 0, counts


def _scan(path: Path):
    from daq.recording_reader import scan

    return scan(path)
