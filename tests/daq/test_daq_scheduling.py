"""Real-time scheduling (``[publish] realtime_priority``, ``--realtime-priority``): the
daemon, its device workers and the threads they start run under SCHED_FIFO, the MCAP
writer does not, and a refusal or a bad value is an error naming the setting."""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import pytest

from daq import scheduling
from daq.config import loads
from daq.errors import ConfigError
from daq.testing import child_pids, daq_cli, free_port

pytestmark = pytest.mark.timeout(120)

SCHED_OTHER, SCHED_FIFO = 0, 1  # /proc/<pid>/task/<tid>/stat "policy"


def _config(port: int, priority: int) -> str:
    out = [
        f'[cell]\nname = "rt"\nrobot = "r1"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        f"[publish]\nhealth_period_s = 0.5\nrealtime_priority = {priority}\n"
    ]
    for i in range(2):
        out.append(
            f'[[device]]\nname = "d{i + 1}"\ndriver = "daq.testing:FakeDriver"\n'
            f'url = "fake://{i}"\nrate_hz = 1000\n'
        )
    return "\n".join(out)


def _threads(pid: int) -> list[tuple[int, int]]:
    """(policy, rt_priority) of every thread of ``pid`` (proc(5) stat fields 41, 40)."""
    out = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            fields = Path(f"/proc/{pid}/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended meanwhile
            continue
        out.append((int(fields[38]), int(fields[37])))  # fields from "state" (field 3) on
    return out


def _realtime_allowed() -> bool:
    """Whether this machine lets us use SCHED_FIFO (tried on a thread that then ends)."""
    ok: list[bool] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            ok.append(True)
        except PermissionError:
            ok.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return ok[0]


@pytest.mark.parametrize("value", ["100", "-1", '"high"', "true", "2.5"])
def test_bad_realtime_priority_names_the_key(value):
    with pytest.raises(ConfigError, match=r"\[publish\]: key 'realtime_priority'"):
        loads(f"[publish]\nrealtime_priority = {value}\n", "cell.toml")


def test_zero_leaves_scheduling_alone_and_a_refusal_names_the_setting(monkeypatch):
    calls = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a))
    scheduling.set_realtime(0, "x")
    assert calls == []

    def refuse(*_a):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with pytest.raises(ConfigError, match=r"cell.toml: \[publish\]: key 'realtime_priority'.*"
                       r"refused.*ulimit -r"):  # fmt: skip
        scheduling.set_realtime(5, "cell.toml: [publish]: key 'realtime_priority'")


def test_echo_rejects_a_priority_out_of_range_naming_the_flag():
    p = daq_cli("echo", "--realtime-priority", "100", "--duration", "0.1")
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2
    assert "--realtime-priority" in err and "0-99" in err and "100" in err


def test_daemon_workers_and_echo_run_under_sched_fifo_but_not_the_mcap_writer(tmp_path):
    port = free_port()
    cfg = tmp_path / "cell.toml"
    cfg.write_text(_config(port, 3))
    d = daq_cli(
        "run", "--config", str(cfg), "--duration", "6", "--record", str(tmp_path / "r.mcap")
    )
    if not _realtime_allowed():  # then the daemon must say why it does not start
        _, err = d.communicate(timeout=60)
        assert d.returncode == 2
        assert "cell.toml: [publish]: key 'realtime_priority': SCHED_FIFO priority 3" in err
        return
    json.loads(d.stdout.readline())
    e = daq_cli(
        "echo", "cell/**", "--stats", "--idle", "3", "--duration", "60",
        "--realtime-priority", "3", "--connect", f"tcp/127.0.0.1:{port}",
    )  # fmt: skip
    t_end = time.monotonic() + 20
    while len(child_pids(d.pid)) < 2 and time.monotonic() < t_end:
        time.sleep(0.1)
    time.sleep(2.0)  # the workers' zenoh and device threads are up
    daemon = _threads(d.pid)
    workers = [_threads(w) for w in child_pids(d.pid)]
    echo = _threads(e.pid)
    out, err = d.communicate(timeout=60)
    assert d.returncode == 0, err
    e_out, _ = e.communicate(timeout=60)
    # one normal thread in the daemon: the MCAP writer; everything else inherited FIFO 3
    assert sorted(daemon).count((SCHED_OTHER, 0)) == 1
    assert [t for t in daemon if t != (SCHED_OTHER, 0)] == [(SCHED_FIFO, 3)] * (len(daemon) - 1)
    assert len(daemon) > 5
    assert len(workers) == 2
    for threads in workers:
        assert len(threads) > 3 and set(threads) == {(SCHED_FIFO, 3)}
    assert len(echo) > 3 and set(echo) == {(SCHED_FIFO, 3)}
    stats = json.loads(e_out.strip().splitlines()[-1])
    for dev in ("d1", "d2"):
        assert stats["health"][f"cell/rt/robot/r1/{dev}/health"]["scheduling"] == "fifo:3"
        assert json.loads(out.strip().splitlines()[-1])["devices"][dev]["samples"] > 3000
