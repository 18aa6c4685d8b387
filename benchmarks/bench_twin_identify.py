"""``twin identify`` on real data: 1000 UR10 poses, one and two OpenBLAS threads.

Issue 29's budget: ``twin identify`` on 1000 real poses (geometry, the closed loop and the
learned residual stage) under 10 s on this 2-core machine, measured with a single-threaded
and a multithreaded OpenBLAS. The campaign is the UR10 series C data
(:mod:`benchmarks.real_data`: split 0 of ``benchmarks.bench_real_data``, 1000
identification and 150 validation poses, the robot its nominal D-H) written as
``campaign.csv`` and ``ur10.toml`` into a temporary directory; the command runs as a user
runs it, a fresh ``python -m calibration.cli identify`` process (imports included), with
``OPENBLAS_NUM_THREADS`` and ``OMP_NUM_THREADS`` set to 1 and then 2.

Rows: ``seconds`` the command's wall time (best of the repeats), ``cpu_s`` its CPU time
(all threads, from the child's rusage), ``load_1min`` the host's load average when it
started (the host is shared: wall time on a loaded host is partly waiting for a core), and
``geo_fit_s`` / ``geo_fit_cpu_s``: the independent geometric fit of the same poses timed in
this process just before (BLAS on one thread), a reference for the CPU time's ratio
(``cpu_ratio_vs_geo_fit``), which moves less with the load than the wall time.

    python -m benchmarks.bench_twin_identify [--quick] [--repeat 2]

(``--quick``: 100 poses, once: a smoke run.)
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from benchmarks import Row, format_table
from benchmarks.real_data import geometric_fit, read_ur10, split
from calibration.identify.campaign_files import write_campaign

REPO = Path(__file__).resolve().parents[1]
N_IDENTIFY, N_VALIDATE, TARGET_S = 1000, 150, 10.0


def write_inputs(out: Path, n_identify: int) -> tuple[Path, Path]:
    """``ur10.toml`` and ``campaign.csv`` (split 0) in ``out``; their paths."""
    data = read_ur10()
    ident, val, _ = split(len(data), n_identify, N_VALIDATE, 0)
    robot, campaign = out / "ur10.toml", out / "campaign.csv"
    data.description.save(robot)
    write_campaign(campaign, data.campaign(ident, val))
    return robot, campaign


def geometric_reference_s(n_identify: int) -> tuple[float, float]:
    """Wall and CPU time (s) of the independent geometric fit of the same poses, in this
    process, BLAS on one thread (so the reference does not move with the thread setting)."""
    data = read_ur10()
    ident, _, _ = split(len(data), n_identify, N_VALIDATE, 0)
    started, cpu = time.perf_counter(), time.process_time()
    with threadpool_limits(limits=1, user_api="blas"):
        geometric_fit(data.description, data.q_deg[ident], data.xyz_mm[ident])
    return time.perf_counter() - started, time.process_time() - cpu


def identify_once(robot: Path, campaign: Path, out: Path, threads: int) -> tuple[float, float]:
    """Wall and CPU seconds of one ``twin identify`` process with ``threads`` BLAS threads."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    env["OPENBLAS_NUM_THREADS"] = env["OMP_NUM_THREADS"] = str(threads)
    cmd = [sys.executable, "-m", "calibration.cli", "identify", "--robot", str(robot)]
    cmd += ["--data", str(campaign), "--out", str(out / "cal.toml"), "--quiet"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"twin identify failed ({done.returncode}): {done.stderr.strip()}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def run(quick: bool = False, repeat: int = 2) -> list[Row]:
    """One row per BLAS thread setting (1, 2)."""
    n = 100 if quick else N_IDENTIFY
    repeat = 1 if quick else repeat
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="bench_twin_identify_") as tmp:
        out = Path(tmp)
        robot, campaign = write_inputs(out, n)
        for threads in (1, 2):
            ref = geometric_reference_s(n)
            load = os.getloadavg()[0]
            best = min(identify_once(robot, campaign, out, threads) for _ in range(repeat))
            rows.append(
                {"benchmark": f"twin identify, {n} UR10 poses (+{N_VALIDATE} validation)",
                 "threads": threads, "seconds": round(best[0], 2), "cpu_s": round(best[1], 2),
                 "target_s": TARGET_S if n == N_IDENTIFY else float("nan"),
                 "geo_fit_s": round(ref[0], 2), "geo_fit_cpu_s": round(ref[1], 2),
                 "cpu_ratio_vs_geo_fit": round(best[1] / ref[1], 2), "load_1min": round(load, 1)}
            )  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_twin_identify")
    parser.add_argument("--quick", action="store_true", help="100 poses, once")
    parser.add_argument("--repeat", type=int, default=2, help="runs per thread setting")
    args = parser.parse_args(argv)
    print(format_table(run(args.quick, args.repeat)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
