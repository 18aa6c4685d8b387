"""One endpoint reaches everything: a subscriber connected only to the daemon's endpoint
sees the live twin's keys; ``twin run --from DIR`` works from any working directory.

Separate real processes over loopback: ``daq run`` on the emulated cell (sim-cell, real
protocols), the live twin (``twin run --from``, a zenoh client of the daemon, started in
another working directory with a relative ``--from``) and ``daq echo 'twin/**'``
connected to the daemon's endpoint and nothing else. The twin's calibration is
``tests/data/twin_calibrated_small`` (made from ``campaign_small.mcap``, see its run.json).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from daq.testing import free_port

DATA = Path(__file__).parent / "data"
CALIBRATED = DATA / "twin_calibrated_small"
PY = sys.executable


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


def _line(p: subprocess.Popen, prefix: str, timeout_s: float) -> tuple[str | None, list[str]]:
    """The first stdout line of ``p`` starting with ``prefix``, within ``timeout_s``."""
    import selectors

    seen: list[str] = []
    sel = selectors.DefaultSelector()
    sel.register(p.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline and len(seen) < 1000:
            if not sel.select(timeout=max(0.0, min(1.0, deadline - time.monotonic()))):
                if p.poll() is not None:
                    break
                continue
            line = p.stdout.readline()
            if not line:
                break
            seen.append(line)
            if line.startswith(prefix):
                return line, seen
    finally:
        sel.close()
    return None, seen


def test_earlier_run_is_found_from_another_working_directory(tmp_path, monkeypatch):
    from calibration.cli_run import _earlier_run

    shutil.copytree(CALIBRATED, tmp_path / "runs" / "cal")
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    run = _earlier_run("../runs/cal")
    assert Path(run["calibrated"]).resolve() == (tmp_path / "runs/cal/calibrated.toml")
    assert Path(run["files"]["scale"]).is_file() and Path(run["files"]["phases"]).is_file()
    # a run.json of before (paths relative to the first run's working directory) still works
    old = json.loads((tmp_path / "runs/cal/run.json").read_text())
    old.pop("paths_relative_to")
    old["calibrated"] = "demo-out/twin/calibrated.toml"
    old["files"] = {"scale": "demo-out/twin/scale.toml", "phases": "demo-out/twin/phases.json"}
    (tmp_path / "runs/cal/run.json").write_text(json.dumps(old))
    run = _earlier_run(str(tmp_path / "runs/cal"))
    assert Path(run["files"]["scale"]) == tmp_path / "runs/cal/scale.toml"
    # a file that is gone is named, with its key
    (tmp_path / "runs/cal/scale.toml").unlink()
    from calibration.errors import DataFileError

    with pytest.raises(DataFileError, match=r"files\.scale.*not there"):
        _earlier_run(str(tmp_path / "runs/cal"))


def test_run_twin_writes_run_json_paths_beside_it():
    # the shipped run.json is what run_twin writes (trimmed): names relative to its folder
    run = json.loads((CALIBRATED / "run.json").read_text())
    from calibration.twin_run import RUN_PATHS_RELATIVE_TO

    assert run["paths_relative_to"] == RUN_PATHS_RELATIVE_TO
    assert run["calibrated"] == "calibrated.toml"


@pytest.mark.timeout(240)
def test_the_daemons_endpoint_reaches_the_live_twin(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    shutil.copytree(CALIBRATED, tmp_path / "runs" / "cal")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs: list[subprocess.Popen] = []
    try:
        daemon = subprocess.Popen(
            [PY, "-m", "daq.cli", "run", "--no-record", "--listen", ep, "--duration", "150"],
            stdout=subprocess.PIPE,
            stderr=open(tmp_path / "daq.err", "w"),  # noqa: SIM115 - the process holds it
            text=True,
            env=env,
        )
        procs.append(daemon)
        up, seen = _line(daemon, '{"daq": "running"', 90)
        assert up, "".join(seen) + (tmp_path / "daq.err").read_text()[-3000:]
        assert json.loads(up)["listen"] == [ep]
        # the twin from another working directory, --from relative to it, a client
        twin = subprocess.Popen(
            [PY, "-m", "calibration.cli", "run", "--from", "../runs/cal", "--out", "out2",
             "--connect", ep, "--publish-s", "90", "--wait-s", "60"],
            cwd=elsewhere,
            stdout=subprocess.PIPE,
            stderr=open(tmp_path / "twin.err", "w"),  # noqa: SIM115 - the process holds it
            text=True,
            env={**env, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        )  # fmt: skip
        procs.append(twin)
        live, seen = _line(twin, '{"twin": "live"', 90)
        assert live, "".join(seen) + (tmp_path / "twin.err").read_text()[-3000:]
        keys = json.loads(live)["keys"]
        assert keys["state"] == "twin/emulated/robot/robot1/state"
        # a subscriber that knows only the daemon's endpoint
        echo = subprocess.run(
            [PY, "-m", "daq.cli", "echo", "twin/**", "--connect", ep, "--listen", "none",
             "--jsonl", str(tmp_path / "twin.jsonl"), "--duration", "6"],
            capture_output=True,
            text=True,
            timeout=90,
            env=env,
        )  # fmt: skip
        assert echo.returncode == 0, echo.stderr[-3000:]
        rows = [json.loads(x) for x in (tmp_path / "twin.jsonl").read_text().splitlines() if x]
        state = [r for r in rows if r["key"] == keys["state"]]
        health = [r["json"] for r in rows if r["key"] == keys["health"]]
        assert len(state) > 10, echo.stderr[-3000:]
        cols = state[-1]["columns"]
        assert len(cols["q_deg"][-1]) == 6 and len(cols["tcp_mm"][-1]) == 3
        assert all(abs(v) < 10_000 for v in cols["tcp_mm"][-1])
        assert health and health[-1]["samples"] > 0
        assert twin.poll() is None and daemon.poll() is None
    finally:
        for p in reversed(procs):
            _stop(p)
