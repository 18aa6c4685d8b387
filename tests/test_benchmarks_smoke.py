"""The benchmarks keep running: quick mode on tiny sizes, and the generic runner.

No timing assertions: the numbers of a quick run mean nothing.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import sys
import threading
import types
from pathlib import Path

import numpy as np
import pytest

# `benchmarks` is not an installed package: `python -m pytest` (make test) finds it through
# the working directory, a bare `pytest` through this.
ROOT = str(Path(__file__).resolve().parents[1])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
benchmarks = importlib.import_module("benchmarks")
runner = importlib.import_module("benchmarks.__main__")
bench_kinematics = importlib.import_module("benchmarks.bench_kinematics")


def test_kinematics_benchmark_quick_rows():
    pytest.importorskip("roboticstoolbox")
    rows = bench_kinematics.run(quick=True)
    assert [r["benchmark"].split(",")[0] for r in rows] == [
        "forward kinematics",
        "identification Jacobian 3x39 (TCP",
        "geometric Jacobian 6x6 (TCP",
        "inverse kinematics",
        "inverse kinematics",
        "inverse kinematics",
    ]
    for row in rows:
        for key in ("ours_s", "loop_s", "rtb_s", "speedup_vs_loop", "speedup_vs_rtb"):
            assert math.isfinite(row[key]) and row[key] > 0, (row["benchmark"], key)
        assert row["n"] > 0 and row["loop_measured_n"] <= row["n"]
        json.dumps(row)  # JSON-ready: plain numbers and strings
    fk, _, geometric, *ik = rows
    assert fk["max_diff_vs_rtb"] < 1e-9 and geometric["max_diff_vs_rtb"] < 1e-9
    for row in ik:
        assert row["ours_found"] > 0.5 and row["ours_max_residual_mm"] <= 1e-9


def test_discovery_finds_the_kinematics_module():
    assert "benchmarks.bench_kinematics" in benchmarks.module_names()
    assert all(n.split(".")[-1].startswith("bench_") for n in benchmarks.module_names())


def test_every_benchmark_module_has_the_runners_entry_point():
    """``python -m benchmarks`` loads every ``bench_*`` module through ``run(quick)``: one
    without it is a FAILED line there (two were, until 2026-11-27)."""
    for name in benchmarks.module_names():
        assert callable(getattr(importlib.import_module(name), "run", None)), name


@pytest.fixture
def fake_modules(monkeypatch):
    """Two stand-in benchmark modules: one good, one that raises."""
    good = types.ModuleType("benchmarks.bench_fake_good")
    good.run = lambda quick: [  # type: ignore[attr-defined]
        {"benchmark": "a", "n": 3, "ours_s": 0.5, "note": "free text"},
        {"benchmark": "b", "n": 4, "extra": 1e-9},
    ]
    bad = types.ModuleType("benchmarks.bench_fake_bad")

    def broken(quick: bool) -> list[dict]:
        raise RuntimeError("boom")

    bad.run = broken  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, good.__name__, good)
    monkeypatch.setitem(sys.modules, bad.__name__, bad)
    return [good.__name__, bad.__name__]


def test_runner_keeps_going_past_a_broken_module(fake_modules):
    rows, errors = benchmarks.run_modules(fake_modules, quick=True)
    assert [r["module"] for r in rows] == ["bench_fake_good"] * 2
    assert errors == ["bench_fake_bad: RuntimeError: boom"]


def test_table_has_every_column_and_note_last():
    table = benchmarks.format_table(
        [{"benchmark": "a", "note": "x", "t": 0.5}, {"benchmark": "b", "u": 1e-9}]
    )
    header = table.splitlines()[0].split()
    assert header == ["benchmark", "t", "u", "note"]
    assert "1.000e-09" in table and "0.5" in table


def test_main_writes_json_and_reports_failures(fake_modules, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(runner, "module_names", lambda: fake_modules)
    out = tmp_path / "bench.json"
    assert runner.main(["--quick", "--json", str(out)]) == 1  # the broken module fails it
    doc = json.loads(out.read_text())
    assert doc["quick"] is True and len(doc["rows"]) == 2 and len(doc["errors"]) == 1
    assert "== bench_fake_good (quick)" in capsys.readouterr().out
    assert runner.main(["--only", "good"]) == 0
    assert runner.main(["--only", "nothing-matches"]) == 2


def test_daq_benchmark_measures_both_sides_and_loses_nothing():
    """The daemon benchmark's harness: raw and daemon rounds both deliver samples (counted
    from the payload headers), a short cell run with recording loses nothing, and the raw
    zenoh latency reference run alongside it delivers every message."""
    bench_daq = importlib.import_module("benchmarks.bench_daq")
    t = bench_daq.throughput(1.0, batch=100, rounds=1)
    assert t["raw_samples_per_s"] > 0 and t["daemon_samples_per_s"] > 0
    assert t["ratio"] == pytest.approx(t["ratio_per_round"][0])
    c = bench_daq.cell(2.0, record=True, reference=True)
    assert c["devices"] == 3 and c["samples_received"] > 3 * 1000
    lost = {k: c[k] for k in ("loss_samples", "lost_messages", "undecodable")}
    detail = {
        "per_key": {
            k: {f: v.get(f) for f in ("samples", "seq_gaps", "lost_batches", "first_seq")}
            for k, v in c["per_key"].items()
        },
        "daemon_side": c["daemon_side"],
    }
    assert lost == {"loss_samples": 0, "lost_messages": 0, "undecodable": 0}, (lost, detail)
    host = c["host_wakeup_late_ms"]
    assert 0.0 <= host["stalled_fraction_over_5ms"] <= 1.0 and host["p50"] <= host["max"]
    assert c["host_steal_cores"] >= 0.0
    split = c["windows_host_quiet"]["windows"] + c["windows_host_stalled"]["windows"]
    assert split == len(c["windows"]) >= 1  # every window is one or the other
    ref = c["raw_reference_latency_ms"]  # raw zenoh streams alongside, one per device
    assert ref["messages"] > 3 * 1000 and ref["lost"] == 0, ref
    assert 0.0 < ref["p50"] <= ref["p99"] <= ref["max"]


def test_host_wakeup_probe_is_bounded_by_count_and_time():
    bench_daq = importlib.import_module("benchmarks.bench_daq")
    probe = bench_daq._probe_host(0.2, period_s=0.01)
    late = probe.late_ms
    assert 1 <= len(late) <= 21 and len(probe.at_s) == len(late)
    assert len(bench_daq._probe_host(0.0).late_ms) == 1  # a zero window still has a figure
    assert late.min() > -1.0  # a sleep never returns early by more than clock noise
    assert np.all(np.diff(probe.at_s) >= 0) and len(probe.steal) >= 2


def test_host_probe_under_realtime_gives_the_thread_back_its_normal_scheduling():
    """``--realtime``: the probe runs at the cell's SCHED_FIFO priority (a normal loop
    would measure the cell's real-time threads) and leaves its thread as it found it."""
    bench_daq = importlib.import_module("benchmarks.bench_daq")
    got: list[object] = []

    def probe() -> None:
        try:
            got.append(len(bench_daq._probe_host(0.05, period_s=0.01, realtime=1).late_ms))
        except PermissionError as exc:  # no CAP_SYS_NICE here: refused, not ignored
            got.append(exc)
        got.append(os.sched_getscheduler(0))

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    assert got[-1] == os.SCHED_OTHER
    assert isinstance(got[0], PermissionError) or 1 <= got[0] <= 6


def test_host_probe_windows_and_the_latency_beside_them():
    """Stalls and steal are assigned to the UTC-aligned window they happened in, and each
    latency window is classed by its host window."""
    bench_daq = importlib.import_module("benchmarks.bench_daq")
    t = 1_763_860_000.0  # a multiple of 10 s
    at = t + np.arange(0.0, 20.0, 0.001)  # two windows of wake-ups every ms
    late = np.full(len(at), 0.1)
    late[15_000] = 50.0  # one 50 ms stall in the second window
    late[16_000] = 4.9  # late, but not a stall beyond 5 ms
    steal = np.array([[t, 100.0], [t + 10.0, 101.0], [t + 20.0, 106.0]])
    probe = bench_daq.HostProbe(late, at, steal)
    w = probe.windows(10)
    assert list(w) == [int(t), int(t) + 10]
    assert w[int(t)]["stalled_fraction_over_5ms"] == 0.0
    assert w[int(t) + 10]["stalled_fraction_over_5ms"] == pytest.approx(0.05 / 9.999, rel=1e-3)
    assert w[int(t)]["steal_cores"] == pytest.approx(0.1)
    assert w[int(t) + 10]["steal_cores"] == pytest.approx(0.5)

    def key(p99s):
        return {"latency_mapped_ms_windows": [
            {"t_s": int(t) + 10 * i, "n": 10, "p50": 1.0, "p99": p, "max": 2 * p}
            for i, p in enumerate(p99s)]}  # fmt: skip

    res = bench_daq._windows_by_host_state({"a": key([3.0, 40.0]), "b": key([4.0, 20.0])}, probe)
    assert [r["latency_p99_ms"] for r in res["windows"]] == [4.0, 40.0]  # worst device
    assert res["windows_host_quiet"] == {"windows": 1, "p99_under_5ms": 1,
        "latency_p99_ms_median": 4.0, "latency_p99_ms_max": 4.0}  # fmt: skip
    assert res["windows_host_stalled"]["windows"] == 1
    assert res["windows_host_stalled"]["latency_p99_ms_max"] == 40.0
    assert res["windows_host_stalled"]["p99_under_5ms"] == 0
    steal = res["windows_by_steal_cores"]  # 0.1 and 0.5 cores
    assert [steal[k]["windows"] for k in steal] == [0, 0, 1, 1]
    assert steal["0.05-0.2"]["latency_p99_ms_max"] == 4.0


def test_real_data_benchmark_refuses_sizes_and_robots_it_cannot_run(capsys):
    """A size that leaves no pose held out, or a robot it has no data of: one line, exit 2,
    before any split runs."""
    bench = importlib.import_module("benchmarks.bench_real_data")
    assert bench.main(["--sizes", "100,1000", "--robots", "ur5", "--splits", "1"]) == 2
    assert "--sizes 1000: ur5 has 1000 poses" in capsys.readouterr().err
    assert bench.main(["--robots", "ur7"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--robots ur7: not one of ur10, ur5" in err
