"""The learned residual stage's speed: ours (numpy) against scikit-learn's GP, 1 vs 2 threads.

Data: 1000 training poses (6 joints, uniform over ±180°) whose 3-D residual is a smooth
function of the angles (a few mm-scale sines, products of joints) plus 0.02 mm noise;
10 000 poses to predict. Rows, each timed in this process, the BLAS limited to 1 thread and
then to 2 (``threadpoolctl``; on this shared 2-core host a multithreaded OpenBLAS has been
seen 10-30x slower than one thread), and once more at 2 threads with the stage's own
one-thread limit lifted (what the shipped code protects against):

* ``fit``: hyperparameters by marginal likelihood (on 400 of the poses, as the stage does)
  and the factorisation on all of them
  (:func:`calibration.effects.learned_residual.fit_learned_residual`; target ≤ 3 s for 1000 poses);
* ``predict``: mean and standard deviation of 10 000 poses (target ≤ 0.1 s);
* ``sklearn fit`` / ``sklearn predict``: ``GaussianProcessRegressor`` with an ARD RBF on
  each joint's (cos, sin) plus a white kernel (12 length scales: it has no per-joint
  periodic ARD kernel), its default L-BFGS-B without restarts on all 1000 poses (once, at
  one thread: minutes), ``return_std=True``; ``ratio_vs_ours`` is sklearn's CPU time over
  ours for the fit and its wall time over ours for the predict, same thread setting.
  Skipped (a note) when scikit-learn is not installed (a test extra of the project).

``--hyper-poses N[,M...]`` adds a row per N at 1 thread: the fit with its hyperparameters on
N poses instead of the shipped :data:`~calibration.effects.learned_residual.HYPER_POSES`,
``ratio_vs_ours`` its CPU time over the shipped fit's in the same run.

Columns: ``seconds`` wall (best of the repeats), ``cpu_s`` the process's CPU time of that
run (all threads): on a loaded shared host the wall time is mostly waiting for a core.

    OMP_NUM_THREADS=1 python -m benchmarks.bench_learned_residual [--quick] [--no-sklearn] \
        [--hyper-poses 600,1000]

(OMP_NUM_THREADS=1 only for the rest of the process: the rows set the BLAS threads
themselves.)
"""

from __future__ import annotations

import argparse
import contextlib
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from benchmarks import format_table
from calibration.effects import learned_residual
from calibration.effects.learned_residual import fit_learned_residual

Row = dict[str, Any]


def dataset(n_train: int, n_predict: int, seed: int = 0) -> tuple[Any, Any, Any, Any]:
    """Training angles ``(n, 6)`` rad and residuals ``(n, 3)`` mm; angles to predict and
    their noise-free residuals."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n_train + n_predict, 6))
    y = np.column_stack(
        [
            0.1 * np.sin(q[:, 1]) * np.cos(q[:, 2]),
            0.08 * np.sin(q[:, 0] + q[:, 3]),
            0.05 * np.cos(2 * q[:, 1]) + 0.03 * np.sin(q[:, 4]),
        ]
    )
    noisy = y[:n_train] + rng.normal(0, 0.02, (n_train, 3))
    return q[:n_train], noisy, q[n_train:], y[n_train:]


@contextlib.contextmanager
def blas_threads(n: int) -> Iterator[None]:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # without it: whatever the environment set
        yield
        return
    with threadpool_limits(limits=n, user_api="blas"):
        yield


def timed(fn: Callable[[], Any], repeat: int) -> tuple[float, Any, float]:
    """Best of ``repeat`` wall times (s), the last result, and the CPU time (s, all
    threads) of the best run: on a loaded host the wall time is mostly waiting."""
    best, out, cpu = float("inf"), None, float("nan")
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall = time.perf_counter() - t
        if wall < best:
            best, cpu = wall, time.process_time() - c
    return best, out, cpu


def _sklearn_rows(q: Any, y: Any, qx: Any, yx: Any, ours: dict[int, dict[str, float]]) -> list[Row]:
    """scikit-learn fitted once (one thread: minutes), then predicting with 1 and 2."""
    try:
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
    except ImportError:
        return [{"benchmark": "sklearn", "note": "scikit-learn not installed"}]

    def features(a: Any) -> Any:
        return np.concatenate([np.cos(a), np.sin(a)], axis=1)

    kernel = ConstantKernel(0.01) * RBF(length_scale=np.ones(12)) + WhiteKernel(1e-3)
    gp = GaussianProcessRegressor(kernel=kernel, normalize_y=False)
    with blas_threads(1):
        fit_s, _, fit_cpu = timed(lambda: gp.fit(features(q), y), 1)
    rows: list[Row] = [
        {"benchmark": f"sklearn fit {len(q)} (all poses)", "threads": 1,
         "seconds": round(fit_s, 3), "cpu_s": round(fit_cpu, 3),
         "ratio_vs_ours": round(fit_cpu / ours[1]["fit_cpu"], 2)}
    ]  # fmt: skip
    for threads in (1, 2):
        with blas_threads(threads):
            pred_s, (mean, _), pred_cpu = timed(
                lambda: gp.predict(features(qx), return_std=True), 2
            )
        rows.append(
            {"benchmark": f"sklearn predict {len(qx)} (+std)", "threads": threads,
             "seconds": round(pred_s, 4), "cpu_s": round(pred_cpu, 4),
             "ratio_vs_ours": round(pred_cpu / ours[threads]["predict_cpu"], 2),
             "rms_error_mm": round(float(np.sqrt(np.mean((mean - yx) ** 2))), 4)}
        )  # fmt: skip
    return rows


def _ours(q: Any, y: Any, qx: Any, yx: Any, threads: int, quick: bool, note: str) -> list[Row]:
    with blas_threads(threads):
        fit_s, model, fit_cpu = timed(lambda: fit_learned_residual(q, y), 1 if quick else 2)
        pred_s, pred, pred_cpu = timed(lambda: model.predict(qx), 3)
    return [
        {"benchmark": f"fit {len(q)} (hyperparameters + factor)", "threads": threads,
         "seconds": round(fit_s, 3), "cpu_s": round(fit_cpu, 3), "target_s": 3.0, "note": note},
        {"benchmark": f"predict {len(qx)} (mean + sd)", "threads": threads,
         "seconds": round(pred_s, 4), "cpu_s": round(pred_cpu, 4), "target_s": 0.1,
         "rms_error_mm": round(float(np.sqrt(np.mean((pred.mean_mm - yx) ** 2))), 4),
         "note": f"{note}; {len(model._pivots)} variance pivots"},
    ]  # fmt: skip


def _hyper_rows(
    q: Any, y: Any, qx: Any, yx: Any, sizes: tuple[int, ...], shipped_cpu: float
) -> list[Row]:
    """The fit at 1 thread with the hyperparameters on each of ``sizes`` poses."""
    rows: list[Row] = []
    shipped = learned_residual.HYPER_POSES
    for n in sizes:
        learned_residual.HYPER_POSES = n
        try:
            row = _ours(q, y, qx, yx, 1, False, f"hyperparameters on {n} poses")[0]
        finally:
            learned_residual.HYPER_POSES = shipped
        rows.append({**row, "ratio_vs_ours": round(row["cpu_s"] / shipped_cpu, 2)})
    return rows


def run(quick: bool = False, sklearn: bool = True, hyper_poses: tuple[int, ...] = ()) -> list[Row]:
    """Our rows at 1 and 2 BLAS threads, the limit lifted, the fit with its hyperparameters
    on other numbers of poses (``hyper_poses``), then scikit-learn's (not with ``quick`` or
    without ``sklearn``)."""
    n_train, n_predict = (200, 1000) if quick else (1000, 10_000)
    q, y, qx, yx = dataset(n_train, n_predict)
    rows: list[Row] = []
    for threads in (1, 2):
        rows += _ours(q, y, qx, yx, threads, quick, "as shipped (BLAS held at 1 thread)")
    # the same with the stage's own one-thread limit lifted: what it protects against
    shipped = learned_residual.one_blas_thread
    learned_residual.one_blas_thread = contextlib.nullcontext  # type: ignore[assignment]
    try:
        rows += _ours(q, y, qx, yx, 2, quick, "limit lifted")
    finally:
        learned_residual.one_blas_thread = shipped  # type: ignore[assignment]
    rows += _hyper_rows(q, y, qx, yx, hyper_poses, rows[0]["cpu_s"])
    if not quick and sklearn:
        cpu = {
            t: {"fit_cpu": rows[2 * i]["cpu_s"], "predict_cpu": rows[2 * i + 1]["cpu_s"]}
            for i, t in enumerate((1, 2))
        }
        rows += _sklearn_rows(q, y, qx, yx, cpu)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_learned_residual")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--no-sklearn", action="store_true", help="ours only (scikit-learn's fit takes minutes)"
    )
    parser.add_argument(
        "--hyper-poses", default="", help="comma-separated N: the fit with hyperparameters on N"
    )
    args = parser.parse_args(argv)
    sizes = tuple(int(v) for v in args.hyper_poses.split(",") if v.strip())
    print(format_table(run(args.quick, sklearn=not args.no_sklearn, hyper_poses=sizes)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
