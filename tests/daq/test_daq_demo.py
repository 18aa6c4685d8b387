"""The demo's recording step shows progress while ``daq run`` records (not only at its end)."""

from __future__ import annotations

import subprocess
import sys

from daq import demo
from daq.testing import free_port

FAKE_DAEMON = (
    "import json, time\n"
    "print(json.dumps({'daq': 'running', 'keys': []}), flush=True)\n"
    "time.sleep(2.6)\n"
    "print(json.dumps({'daq': 'stopped', 'devices': {}}), flush=True)\n"
)


def test_the_recording_step_prints_progress_while_it_runs(tmp_path, capsys):
    mcap = tmp_path / "campaign.mcap"
    mcap.write_bytes(b"x" * 1_500_000)
    proc = subprocess.Popen([sys.executable, "-c", FAKE_DAEMON], stdout=subprocess.PIPE, text=True)
    lines = demo._follow(proc, 2.0, 200.0, mcap, free_port(), 0.5)
    out = capsys.readouterr().out.splitlines()
    assert proc.returncode == 0 and lines[-1].startswith('{"daq": "stopped"')
    shown = [x for x in out if x.startswith("demo: recording")]
    # a line every 0.5 s while it ran (not a timing assertion: at least two of ~5)
    assert len(shown) >= 2, out
    assert "/ 2 s" in shown[0] and "robot time" in shown[0] and "campaign.mcap 1.5 MB" in shown[0]


def test_no_progress_when_asked_for_none(tmp_path, capsys):
    proc = subprocess.Popen([sys.executable, "-c", FAKE_DAEMON], stdout=subprocess.PIPE, text=True)
    demo._follow(proc, 2.0, 200.0, tmp_path / "c.mcap", free_port(), 0.0)
    assert not [x for x in capsys.readouterr().out.splitlines() if x.startswith("demo:")]
