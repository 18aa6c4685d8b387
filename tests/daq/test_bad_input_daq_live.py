"""Bad input that used to leave a ``daq`` process waiting: a device absent at start, a
subscriber or recorder connected to nobody (real processes, bounded in time).

These measure wall time (how soon the refusal comes), so they run with the ``realtime``
tests (tests/conftest.py), alone. Every process is started with a timeout and killed by
its process group if it outlives it; every refusal asserts exit 2, one stderr line with
the key words, no traceback and no file created (tests/test_bad_input_daq.refused).

| case | bound |
|---|---|
| `daq run --config` with a device path that does not exist | exit 2 within 10 s |
| the same with `wait_for_device_s = 4` | waits ≥ 4 s, one line per 10 s, exit 2 |
| `daq echo --connect` / `daq record --connect` to a port nobody listens on | exit 2 within 10 s |
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.daq.test_bad_input_daq import DAQ, free_port, refused, run

NODEV = """[cell]
name = "c1"

[zenoh]
listen = ["tcp/127.0.0.1:{port}"]

[[device]]
name = "grating"
driver = "grating_modbus"
url = "/dev/ttyNOPE-{port}"
rate_hz = 1000
{extra}
"""


@pytest.fixture
def work(tmp_path: Path) -> Path:
    return tmp_path


def _timed(work: Path, argv: list[str], words: list[str]) -> float:
    t0 = time.monotonic()
    refused(work, argv, words)
    return time.monotonic() - t0


def test_a_device_absent_at_start_is_named_within_seconds(work):
    """It was retried every second for ever, one log line per attempt."""
    port = free_port()
    (work / "cell.toml").write_text(NODEV.format(port=port, extra=""))
    took = _timed(
        work,
        [DAQ, "run", "--config", "cell.toml", "--duration", "60", "--record", "r.mcap"],
        ["cell.toml", "'grating'", f"/dev/ttyNOPE-{port}", "No such file", "wait_for_device_s"],
    )
    assert took < 10.0, took


def test_a_wait_for_an_absent_device_is_bounded_and_said_once_per_interval(work):
    port = free_port()
    (work / "cell.toml").write_text(NODEV.format(port=port, extra="wait_for_device_s = 4"))
    t0 = time.monotonic()
    proc = run([DAQ, "run", "--config", "cell.toml", "--duration", "60"], work)
    took = time.monotonic() - t0
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert 4.0 <= took < 15.0, took
    waiting = [ln for ln in lines if "waiting for device 'grating'" in ln]
    assert 1 <= len(waiting) <= 1 + 4 // 10, lines  # one per 10 s interval, not per attempt
    assert len(lines) == len(waiting) + 1 and "waited 4 s" in lines[-1], lines
    assert sorted(p.name for p in work.iterdir()) == ["cell.toml"]


@pytest.mark.parametrize("command", ["echo", "record"])
def test_a_subscriber_connected_to_nobody_says_so_within_seconds(work, command):
    """It printed (or recorded) nothing for its whole duration; twin view --connect
    already refused the same endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = ["-o", "r.mcap"] if command == "record" else ["--jsonl", "b.jsonl"]
    took = _timed(
        work,
        [DAQ, command, "cell/**", *out, "--connect", endpoint, "--duration", "60"],
        ["--connect", endpoint, "nobody answers"],
    )
    assert took < 10.0, took
