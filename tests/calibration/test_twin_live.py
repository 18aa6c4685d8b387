"""The live twin: ``twin run`` on zenoh collects a campaign, calibrates, publishes; a
subscriber in another process sees the twin's samples.

The daemon's streams come from ``daq replay`` of the small recorded campaign (the same bytes
the daemon published), first at 10x for the campaign, then looped at real speed to feed the
live twin. Everything on 127.0.0.1, peers with explicit endpoints, no scouting.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

DATA = Path(__file__).parents[1] / "data" / "campaign_small.mcap"
PY = sys.executable

pytestmark = pytest.mark.skipif(not DATA.exists(), reason="tests/data/campaign_small.mcap missing")


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


@pytest.mark.timeout(240)
def test_live_twin_is_seen_by_a_subscriber_process(tmp_path):
    twin_ep = f"tcp/127.0.0.1:{_port()}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    twin = subprocess.Popen(
        [
            PY,
            "-m",
            "calibration.cli",
            "run",
            "--robot",
            "kr500",
            "--out",
            str(tmp_path / "out"),
            "--listen",
            twin_ep,
            "--connect",
            "none",
            "--idle-s",
            "3",
            "--no-report",
            "--publish-s",
            "60",
        ],
        stdout=subprocess.PIPE,
        stderr=open(tmp_path / "twin.err", "w"),  # noqa: SIM115 - the process holds it
        text=True,
        env=env,
    )
    procs = [twin]
    try:
        time.sleep(2.0)
        feed = subprocess.run(
            [
                PY,
                "-m",
                "daq.cli",
                "replay",
                str(DATA),
                "--speed",
                "10",
                "--listen",
                "none",
                "--connect",
                twin_ep,
                "--wait-subscribers",
                "20",
            ],
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        assert feed.returncode == 0, feed.stderr
        # the twin calibrates, then announces its keys
        keys = None
        deadline = time.monotonic() + 120
        lines = []
        while time.monotonic() < deadline:
            line = twin.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith('{"twin": "live"'):
                keys = json.loads(line)["keys"]
                break
        assert keys is not None, "".join(lines) + (tmp_path / "twin.err").read_text()[-3000:]
        assert (tmp_path / "out" / "calibrated.toml").exists()
        echo = subprocess.Popen(
            [
                PY,
                "-m",
                "daq.cli",
                "echo",
                "twin/**",
                "--connect",
                twin_ep,
                "--listen",
                "none",
                "--jsonl",
                str(tmp_path / "twin.jsonl"),
                "--duration",
                "8",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        procs.append(echo)
        time.sleep(1.5)
        loop = subprocess.Popen(
            [
                PY,
                "-m",
                "daq.cli",
                "replay",
                str(DATA),
                "--speed",
                "1",
                "--loop",
                "--listen",
                "none",
                "--connect",
                twin_ep,
                "--topic",
                "cell/**/grating/**",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        procs.append(loop)
        echo.wait(60)
        rows = [json.loads(x) for x in (tmp_path / "twin.jsonl").read_text().splitlines() if x]
        state = [r for r in rows if r["key"] == keys["state"]]
        health = [r["json"] for r in rows if r["key"] == keys["health"]]
        assert state, echo.stderr.read()
        cols = state[-1]["columns"]
        tcp = cols["tcp_mm"][-1]
        assert len(tcp) == 3 and all(abs(v) < 10_000 for v in tcp)
        assert len(cols["flange_quat"][-1]) == 4 and len(cols["q_deg"][-1]) == 6
        assert "encoder_minus_grating_deg" in cols
        assert health and health[-1]["latency_ms"]["p50"] > 0
        print("twin health:", json.dumps(health[-1]))
        phases = json.loads((tmp_path / "out" / "phases.json").read_text())["phases"]
        assert phases["sweep_stops"]["1"] == {"forward": 185, "backward": 185}
        assert phases["poses"]["identify"] + phases["poses"]["validate"] >= 240
    finally:
        for p in reversed(procs):
            _stop(p)
