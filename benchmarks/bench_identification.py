"""Identification speed and result: our LM vs scipy's least_squares vs pybotics.

Data: the KR500 preset, a true cell from ``sim_devices.truth`` (seed 1) with its Hayati
beta set to zero (pybotics has no beta, so both tools can represent the truth exactly),
random reachable poses, data-sheet tracker noise. Every solver starts from the nominal
geometry and the description's base guess.

Rows:

* ``identify`` at n = 100 (the source's campaign size) and, for the scaling, 1k, 10k and
  100k poses: ``ours_s`` is :func:`calibration.identify.identification.identify` end to end
  (identifiability analysis, LM, covariance), ``us_per_pose`` shows the linear scaling.
* ``scipy_lm_s``: ``scipy.optimize.least_squares(method="lm")`` (MINPACK) on the same
  residuals, analytic Jacobian, same free parameters and start; ``ours_lm_only_s`` is our
  LM alone on that problem and ``speedup_vs_scipy`` compares the two solvers;
  ``cost_ratio_vs_scipy`` is our final cost over scipy's (1.0: the same optimum).
* ``pybotics_s``: pybotics 3.1.2 (``optimize_accuracy`` through ``least_squares``, its
  documented recipe, finite-difference Jacobian, per-pose distance residuals) on the same
  data and free set. pybotics pins numpy<2, so it runs in a side venv ``.venv-ref/``
  (create it with ``python -m benchmarks.bench_identification --make-reference-venv``);
  data go there and back as ``.npz`` files, never pickles. ``val_ap_ratio_vs_pybotics`` is
  our mean validation AP over pybotics'. Without the venv the row says so and is skipped.

    python -m benchmarks.bench_identification [--quick] [--make-reference-venv]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from calibration.identify.identification import identify
from calibration.identify.levenberg_marquardt import levenberg_marquardt
from calibration.identify.position_residuals import position_residual_jacobian, position_residuals
from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel, tcp_positions
from sim_devices.pose_campaign import sample_reachable_poses
from sim_devices.truth import TrueCell

Row = dict[str, Any]

ROBOT = "kr500"
SEED = 1
REFERENCE_VENV = Path(__file__).resolve().parent.parent / ".venv-ref"
REFERENCE_REQUIREMENTS = ("pybotics==3.1.2",)  # pulls numpy<2 and scipy into the side venv

PYBOTICS_SCRIPT = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from scipy.optimize import least_squares
    from pybotics.robot import Robot
    from pybotics.tool import Tool
    from pybotics.optimization import OptimizationHandler, optimize_accuracy

    d = np.load(sys.argv[1])
    robot = Robot.from_parameters(d["mdh"])
    robot.world_frame = d["world"]
    tool = Tool()
    tool.position = d["tool"]
    robot.tool = tool
    handler = OptimizationHandler(
        robot=robot,
        kinematic_chain_mask=list(d["chain_mask"]),
        tool_mask=list(d["tool_mask"]),
        world_mask=list(d["world_mask"]),
    )
    x0 = handler.generate_optimization_vector()
    start = time.perf_counter()
    res = least_squares(
        fun=optimize_accuracy, x0=x0, args=(handler, d["q_id"], d["p_id"]), verbose=0
    )
    elapsed = time.perf_counter() - start
    handler.apply_optimization_vector(res.x)
    pred = np.array([handler.robot.fk(q)[:3, 3] for q in d["q_val"]])
    np.savez(sys.argv[2], x=res.x, elapsed_s=elapsed, nfev=res.nfev, pred_val=pred,
             residual_rms=np.sqrt(np.mean(res.fun ** 2)))
    """
)


def make_data(n_identify: int, n_validate: int, seed: int = SEED) -> dict[str, Any]:
    """Nominal model, beta-free truth, poses and noisy tracker points."""
    desc = load_robot(ROBOT)
    cell = TrueCell.create(desc, seed)
    x_true = cell.model.parameter_vector()
    x_true[4 : 5 * cell.model.n_joints : 5] = 0.0  # no Hayati beta: representable by pybotics
    truth = cell.model.with_parameters(x_true)
    rng = np.random.default_rng([seed, n_identify])
    q = sample_reachable_poses(desc, n_identify + n_validate, rng)
    tcp = tcp_positions(truth, q)
    measured, _ = cell.tracker.measure(tcp, rng)
    return {
        "nominal": KinematicModel.from_description(desc),
        "truth": truth,
        "q_id": q[:n_identify],
        "p_id": measured[:n_identify],
        "q_val": q[n_identify:],
        "p_val": measured[n_identify:],
        "tcp_val": tcp[n_identify:],
    }


def _best(fn: Any, repeat: int) -> tuple[float, Any]:
    best, out = float("inf"), None
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def _problem(data: dict[str, Any], result: Any) -> tuple[Any, tuple[Any, ...], Any]:
    free_idx = result.identifiability.free_indices
    start = result.start_model
    args = (
        start.parameter_vector(),
        free_idx,
        start,
        data["q_id"],
        data["p_id"],
        np.ones(len(data["q_id"])),
    )
    return (
        start.parameter_vector()[free_idx],
        args,
        1.0 / result.identifiability.column_scale[free_idx],
    )


def _scipy(data: dict[str, Any], result: Any) -> Any:
    x0, args, _ = _problem(data, result)
    return least_squares(
        position_residuals, x0, jac=position_residual_jacobian, args=args, method="lm"
    )


def _our_solver(data: dict[str, Any], result: Any) -> Any:
    x0, args, x_scale = _problem(data, result)
    return levenberg_marquardt(
        position_residuals, position_residual_jacobian, x0, args=args, x_scale=x_scale
    )


def identify_row(n: int, repeat: int, with_scipy: bool) -> Row:
    data = make_data(n, 0)
    t_ours, result = _best(lambda: identify(data["nominal"], data["q_id"], data["p_id"]), repeat)
    row: Row = {
        "benchmark": "identify",
        "n": n,
        "ours_s": t_ours,
        "us_per_pose": 1e6 * t_ours / n,
        "iterations": int(result.optimize_result.nit),
    }
    if with_scipy:
        t_lm, _ = _best(lambda: _our_solver(data, result), repeat)
        t_ref, ref = _best(lambda: _scipy(data, result), repeat)
        row.update(
            {
                "ours_lm_only_s": t_lm,
                "scipy_lm_s": t_ref,
                "speedup_vs_scipy": t_ref / t_lm,
                "cost_ratio_vs_scipy": float(result.optimize_result.cost / ref.cost),
            }
        )
    row["note"] = "LM end to end (identifiability, solve, covariance)"
    return row


def reference_python() -> Path | None:
    exe = REFERENCE_VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    return exe if exe.exists() else None


def make_reference_venv() -> Path:
    """Create ``.venv-ref`` with pybotics (needs the package index)."""
    subprocess.run([sys.executable, "-m", "venv", str(REFERENCE_VENV)], check=True)
    exe = reference_python()
    assert exe is not None
    subprocess.run([str(exe), "-m", "pip", "install", "-q", *REFERENCE_REQUIREMENTS], check=True)
    return exe


def _pybotics_inputs(data: dict[str, Any], result: Any) -> dict[str, Any]:
    nominal: KinematicModel = result.start_model
    n = nominal.n_joints
    # pybotics' MDH rows are (alpha, a, theta, d); its joint q adds to theta
    mdh = np.column_stack([nominal.alpha_rad, nominal.a_mm, nominal.theta_offset_rad, nominal.d_mm])
    world = np.eye(4)
    world[:3, :3] = nominal.base_rotation()
    world[:3, 3] = nominal.base_mm
    # the same free set as ours, less the betas pybotics does not have
    free = result.free
    ours = {"alpha_rad": 1, "a_mm": 0, "theta_offset_rad": 3, "d_mm": 2}
    chain_mask = np.zeros((n, 4), dtype=bool)
    for j in range(n):
        for col, key in enumerate(("alpha_rad", "a_mm", "theta_offset_rad", "d_mm")):
            chain_mask[j, col] = free[5 * j + ours[key]]
    return {
        "mdh": mdh,
        "world": world,
        "tool": nominal.tool_mm,
        "chain_mask": chain_mask.ravel(),
        "tool_mask": np.array([True, True, True, False, False, False]),
        "world_mask": np.ones(6, dtype=bool),
        "q_id": data["q_id"],
        "p_id": data["p_id"],
        "q_val": data["q_val"],
    }


def pybotics_row(n: int, n_validate: int) -> Row:
    exe = reference_python()
    row: Row = {"benchmark": "vs pybotics", "n": n}
    if exe is None:
        row["note"] = (
            "skipped: no .venv-ref (python -m benchmarks.bench_identification "
            "--make-reference-venv)"
        )
        return row
    data = make_data(n, n_validate)
    t_ours, result = _best(lambda: identify(data["nominal"], data["q_id"], data["p_id"]), 3)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, **_pybotics_inputs(data, result))
        proc = subprocess.run(
            [str(exe), "-c", PYBOTICS_SCRIPT, str(src), str(dst)],
            capture_output=True,
            text=True,
            timeout=1800,
        )
        if proc.returncode != 0:
            row["note"] = f"pybotics failed: {proc.stderr.strip().splitlines()[-1:]}"
            return row
        out = np.load(dst, allow_pickle=False)
        t_ref = float(out["elapsed_s"])
        pred_ref = out["pred_val"]
    val_ours = np.linalg.norm(data["p_val"] - tcp_positions(result.model, data["q_val"]), axis=1)
    val_ref = np.linalg.norm(data["p_val"] - pred_ref, axis=1)
    val_true = np.linalg.norm(data["p_val"] - data["tcp_val"], axis=1)
    row.update(
        {
            "ours_s": t_ours,
            "pybotics_s": t_ref,
            "speedup_vs_pybotics": t_ref / t_ours,
            "val_ap_ours_mm": float(val_ours.mean()),
            "val_ap_pybotics_mm": float(val_ref.mean()),
            "val_ap_true_model_mm": float(val_true.mean()),
            "val_ap_ratio_vs_pybotics": float(val_ours.mean() / val_ref.mean()),
            "note": "pybotics 3.1.2 in .venv-ref, its solve only (no imports)",
        }
    )
    return row


def run(quick: bool) -> list[Row]:
    if quick:
        rows = [identify_row(100, 1, True), identify_row(1000, 1, False)]
        rows.append(pybotics_row(60, 20))
        return rows
    rows = [identify_row(100, 5, True)]
    rows += [identify_row(n, 3 if n <= 10_000 else 1, n <= 10_000) for n in (1000, 10_000)]
    rows.append(identify_row(100_000, 2, False))
    rows.append(pybotics_row(100, 150))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_identification")
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run")
    parser.add_argument(
        "--make-reference-venv", action="store_true", help="create .venv-ref with pybotics first"
    )
    args = parser.parse_args(argv)
    if args.make_reference_venv and reference_python() is None:
        make_reference_venv()
    from benchmarks import format_table

    print(format_table(run(args.quick)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
