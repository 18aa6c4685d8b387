"""Bad options of the live twin and of the recording's viewer channels: one line naming
the option or key, exit 2, no traceback, nothing started."""

from __future__ import annotations

import subprocess
import sys

import pytest

from daq.config import loads
from daq.errors import ConfigError

PY = sys.executable


@pytest.mark.parametrize(
    ("extra", "word"),
    [
        (["--mode", "client", "--listen", "tcp/127.0.0.1:7999"], "--listen"),
        (["--connect", "none"], "--connect"),
        (["--effects-radius-deg", "-1"], "--effects-radius-deg"),
        (["--effects-radius-deg", "nan"], "--effects-radius-deg"),
        (["--effects-radius-deg", "30"], "--effects-radius-deg"),
        (["--frames-hz", "inf"], "--frames-hz"),
        (["--alarm-mm", "0"], "--alarm-mm"),
        (["--alarm-mm", "nan"], "--alarm-mm"),
        (["--wait-s", "0"], "--wait-s"),
        (["--idle-s", "0"], "--idle-s"),
        (["--idle-s", "nan"], "--idle-s"),
        (["--collect-s", "-1"], "--collect-s"),
        (["--collect-s", "inf"], "--collect-s"),
        (["--publish-s", "nan"], "--publish-s"),
        (["--publish-s", "-5"], "--publish-s"),
    ],
)
def test_live_options_are_refused_in_one_line(tmp_path, extra, word):
    proc = subprocess.run(
        [PY, "-m", "calibration.cli", "run", "--from", str(tmp_path), "--out", "o", *extra],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err)
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert word in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("value", ["-1", "5000", "'30'", "nan"])
def test_viewer_rate_is_checked(value):
    with pytest.raises(ConfigError, match=r"\[recording\].*viewer_rate_hz"):
        loads(f"[recording]\nviewer_rate_hz = {value}\n", source="cell.toml")


def test_viewer_rate_and_twin_recording_defaults():
    cfg = loads("", source="cell.toml")
    assert cfg.recording.viewer_rate_hz == 30.0 and cfg.recording.twin is True
    cfg = loads("[recording]\nviewer_rate_hz = 0\ntwin = false\n", source="cell.toml")
    assert cfg.recording.viewer_rate_hz == 0.0 and cfg.recording.twin is False
