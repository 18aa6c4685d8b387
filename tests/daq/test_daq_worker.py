"""Device workers (``[publish] process_per_device``): a daemon with several devices runs
each in a process of its own, and subscribers, the recording and the daemon's summary see
the same as from one process; workers never outlive the daemon; a worker that dies is
started again."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from daq.config import loads
from daq.recording_reader import read_recording
from daq.testing import child_pids, daq_cli, free_port, recorded_columns
from daq.worker import config_from_spec, worker_spec, worker_zenoh

pytestmark = pytest.mark.timeout(120)


def _config(port: int, per_device: str = '"auto"', devices: int = 2) -> str:
    out = [
        f'[cell]\nname = "w"\nrobot = "r1"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        f"[publish]\nhealth_period_s = 0.5\nprocess_per_device = {per_device}\n"
    ]
    for i in range(devices):
        out.append(
            f'[[device]]\nname = "d{i + 1}"\ndriver = "daq.testing:FakeDriver"\n'
            f'url = "fake://{i}"\nrate_hz = 1000\njoints = [1, 2, 3]\n'
            'channels = { samples = ["grating1_counts", "grating2_counts", '
            '"grating3_counts"], first = ["grating1_counts"] }\n'
        )
    return "\n".join(out)


def _key(dev: str, channel: str = "samples") -> str:
    return f"cell/w/robot/r1/{dev}/{channel}"


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_worker_spec_round_trips_the_device_and_settings():
    cfg = loads(_config(7447, "true"))
    dev = cfg.devices[1]
    zc = worker_zenoh(cfg.zenoh, "unixsock-stream//tmp/x.sock")
    assert (
        zc.mode == "client" and zc.listen == () and zc.connect == ("unixsock-stream//tmp/x.sock",)
    )
    spec = json.loads(json.dumps(worker_spec(cfg, dev, zc, 123)))  # only JSON crosses
    back, back_dev, offset = config_from_spec(spec)
    assert back_dev == dev and offset == 123
    assert back.cell == cfg.cell and back.publish == cfg.publish and back.zenoh == zc
    # a client-mode daemon's workers connect where it does
    client = loads(
        '[zenoh]\nmode = "client"\nconnect = ["tcp/127.0.0.1:7447"]\n'
        '[[device]]\nname = "a"\ndriver = "daq.testing:FakeDriver"\nurl = "fake://"\n'
    ).zenoh
    assert worker_zenoh(client, None).connect == ("tcp/127.0.0.1:7447",)


def test_bad_process_per_device_names_the_key():
    with pytest.raises(ValueError, match=r"\[publish\].*process_per_device"):
        loads(_config(7447, '"yes"'))


def test_two_devices_in_workers_reach_subscriber_and_recording_whole(tmp_path):
    port = free_port()
    cfg = tmp_path / "cell.toml"
    cfg.write_text(_config(port))
    rec = tmp_path / "w.mcap"
    d = daq_cli("run", "--config", str(cfg), "--duration", "5", "--record", str(rec))
    first = json.loads(d.stdout.readline())
    assert first["keys"] == [_key("d1"), _key("d1", "first"), _key("d2"), _key("d2", "first")]
    e = daq_cli(
        "echo", "cell/**", "--stats", "--idle", "3", "--duration", "60",
        "--connect", f"tcp/127.0.0.1:{port}",
    )  # fmt: skip
    time.sleep(2.0)
    workers = child_pids(d.pid)
    assert len(workers) == 2 and all(_alive(w) for w in workers)
    out, err = d.communicate(timeout=60)
    assert d.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    e_out, _ = e.communicate(timeout=60)
    stats = json.loads(e_out.strip().splitlines()[-1])
    assert not any(_alive(w) for w in workers)
    for dev in ("d1", "d2"):
        n = summary["devices"][dev]["samples"]
        assert n > 3000
        for ch in ("samples", "first"):
            live = stats["keys"][_key(dev, ch)]
            assert live["seq_gaps"] == 0 and live["lost_batches"] == 0 and live["seq_breaks"] == 0
            assert live["last_seq"] == n - 1  # every sample to the last, in order
            got = recorded_columns(rec, _key(dev, ch))
            np.testing.assert_array_equal(got["seq"], np.arange(n))
        assert stats["health"][f"cell/w/robot/r1/{dev}/health"]["device"] == dev
    health = [m for m in read_recording(rec).messages_iter() if m.channel.topic.endswith("health")]
    assert {json.loads(m.data)["device"] for m in health} == {"d1", "d2"}


def test_workers_leave_with_a_killed_daemon_and_a_dead_worker_is_restarted(tmp_path):
    port = free_port()
    cfg = tmp_path / "cell.toml"
    cfg.write_text(_config(port, "true", devices=1))
    rec = tmp_path / "k.mcap"
    d = daq_cli("run", "--config", str(cfg), "--record", str(rec))
    json.loads(d.stdout.readline())
    t_end = time.monotonic() + 20
    while not child_pids(d.pid) and time.monotonic() < t_end:
        time.sleep(0.1)
    (worker,) = child_pids(d.pid)
    time.sleep(1.5)
    os.kill(worker, signal.SIGKILL)  # the daemon starts it again at its next health tick
    t_end = time.monotonic() + 20
    while time.monotonic() < t_end and child_pids(d.pid) in ([], [worker]):
        time.sleep(0.1)
    (again,) = child_pids(d.pid)
    assert again != worker
    time.sleep(2.0)
    os.kill(d.pid, signal.SIGKILL)
    d.communicate(timeout=30)
    t_end = time.monotonic() + 15
    while _alive(again) and time.monotonic() < t_end:
        time.sleep(0.1)
    assert not _alive(again), "a worker outlived its daemon"
    # the restarted device's samples were recorded too (its sequence starts again)
    seq = recorded_columns(rec, _key("d1"))["seq"]
    restart = np.flatnonzero(np.diff(seq.astype(np.int64)) < 0)
    assert len(restart) == 1 and len(seq) - restart[0] > 500
