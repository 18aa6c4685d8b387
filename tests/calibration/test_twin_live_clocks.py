"""The live twin learns no tracking update from a grating and a tracker stamped by host
clocks that disagree (docs/deployment.md, "Clocks"), in real processes on loopback.

``daq replay`` feeds the live twin (``twin run --from`` the small campaign's calibration)
the campaign's pose phase from a copy of tests/data/campaign_small.mcap whose devices'
health says the tracker's host is 500 ms ahead of the grating's (as two daemons that are
clients of one router would say it; the copy is tests/calibration/test_twin_clocks.py's).
The same run with the original recording is the control: tests/calibration/
test_twin_live_tracking.py, where the dwells make ≥ 20 tracking updates.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from daq.testing import free_port
from tests.calibration.test_twin_clocks import _with_clocks
from tests.calibration.test_twin_live_tracking import _live, _stop

PY = sys.executable


@pytest.mark.slow  # ~30 s in all: `make soak`; the rule in process: test_live_clocks.py
@pytest.mark.timeout(90)
def test_clocks_apart_no_tracking_update_is_learned_and_the_health_says_why(tmp_path):
    recording = _with_clocks(tmp_path / "apart.mcap", {"tracker": 500.0, "grating": 0.2})
    rows, said = _live(tmp_path, recording=recording)
    state = [r for r in rows if r["key"].endswith("/state")]
    health = [r["json"] for r in rows if r["key"].endswith("/health")]
    assert len(state) > 10 and health, said[-3000:]  # the twin publishes from the gratings
    # said once, on one line, naming both devices and their clocks
    lines = [x for x in said.splitlines() if "host clocks" in x]
    assert len(lines) == 1, said[-3000:]
    assert "the grating (grating) and the tracker (tracker)" in lines[0], lines
    assert "499.8 ms apart" in lines[0] and "no tracking update is learned" in lines[0], lines
    # nothing learned: no tracking row, the tracker's samples counted as not used
    assert not [r for r in rows if r["key"].endswith("/tracking")], said[-2000:]
    clocks = health[-1]["clocks"]
    assert clocks["agree"] is False and clocks["apart_ms"] == 499.8, clocks
    assert clocks["devices"]["tracker"]["offset_ms"] == 500.0, clocks
    assert clocks["tracker_samples_dropped"] > 1000, clocks
    assert health[-1]["tracking"]["on"] is True and "updates" not in health[-1]["tracking"]


@pytest.mark.slow  # ~30 s in all: `make soak`; the rule in process: test_live_clocks.py
@pytest.mark.timeout(120)
def test_a_live_collection_of_clocks_apart_is_refused_as_a_replay_is(tmp_path):
    """``twin run`` collecting live (no ``--from``) reads the devices' ``host_clock`` from
    their health on the collected keys and refuses to calibrate on streams whose clocks
    disagree, as ``twin run --replay`` refuses the recording: one line, exit 2, nothing
    written."""
    recording = _with_clocks(tmp_path / "apart.mcap", {"tracker": 500.0, "grating": 0.2})
    ep = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    err = tmp_path / "twin.err"
    twin = subprocess.Popen(
        [PY, "-m", "calibration.cli", "run", "--robot", "kr500", "--out", str(tmp_path / "out"),
         "--mode", "peer", "--listen", ep, "--connect", "none", "--idle-s", "3",
         "--no-report", "--publish-s", "5"],
        stdout=subprocess.DEVNULL,
        stderr=open(err, "w"),  # noqa: SIM115 - the process holds it
        env=env,
    )  # fmt: skip
    try:
        time.sleep(1.0)
        feed = subprocess.run(
            [PY, "-m", "daq.cli", "replay", str(recording), "--speed", "10", "--listen",
             "none", "--connect", ep, "--wait-subscribers", "20"],
            capture_output=True,
            text=True,
            timeout=60,
            env=env,
        )  # fmt: skip
        assert feed.returncode == 0, feed.stderr[-2000:]
        twin.wait(40)
    finally:
        _stop(twin)
    said = err.read_text()
    assert twin.returncode == 2, said[-3000:]
    last = said.strip().splitlines()[-1]
    assert last.startswith("twin run: error: live zenoh: the grating (grating) and the "), last
    assert "tracker (tracker) were stamped by host clocks 499.8 ms apart" in last, last
    assert "Traceback" not in said and not (tmp_path / "out").exists()
