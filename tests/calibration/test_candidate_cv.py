"""The closed loop's cross-validation by leaving one pose out: the hat-matrix PRESS is the
same as refitting without each pose in turn, for the model and for the model with a
candidate, and stays finite when a pose alone determines a direction."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.effects.candidate_scoring import LinearizedModel, pose_press, scaled


def _errors_without_each_pose(x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Each row's prediction error ``(3m,)`` by the fit without its pose."""
    out = np.zeros(len(r))
    for i in range(len(r) // 3):
        test = np.arange(3 * i, 3 * i + 3)
        train = np.setdiff1d(np.arange(len(r)), test)
        coef, *_ = np.linalg.lstsq(x[train], r[train], rcond=None)
        out[test] = r[test] - x[test] @ coef
    return out


def _refit_without_each_pose(x: np.ndarray, r: np.ndarray) -> float:
    e = _errors_without_each_pose(x, r)
    return float(e @ e)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_leave_one_pose_out_is_the_refit_without_each_pose(seed):
    rng = np.random.default_rng(seed)
    m = 25
    jac = rng.normal(size=(3 * m, 7)) * rng.uniform(0.1, 10.0, size=7)
    cand = rng.normal(size=(3 * m, 3))
    r = jac @ rng.normal(size=7) + cand @ rng.normal(size=3) + rng.normal(size=3 * m)
    lin = LinearizedModel.build(r, jac, m, 5, 0, leave_one_out=True)
    assert lin.cv0 == pytest.approx(_refit_without_each_pose(scaled(jac), r), rel=1e-10)
    both = np.hstack([scaled(jac), scaled(cand)])
    got = lin.cv_sse_with(scaled(cand))
    assert got == pytest.approx(_refit_without_each_pose(both, r), rel=1e-10)
    assert got < lin.cv0  # the candidate is in the data
    folds = LinearizedModel.build(r, jac, m, 5, 0)  # the K-fold criterion still there
    assert folds.cv0 != pytest.approx(lin.cv0, rel=1e-6)


def test_a_direction_one_pose_alone_determines_counts_nothing():
    rng = np.random.default_rng(3)
    m = 20
    jac = rng.normal(size=(3 * m, 4))
    spike = np.zeros((3 * m, 1))
    spike[5, 0] = 1.0  # seen by pose 1 alone
    r = rng.normal(size=3 * m)
    lin = LinearizedModel.build(r, jac, m, 5, 0, leave_one_out=True)
    basis, _ = np.linalg.qr(np.hstack([scaled(jac), spike]))
    press = pose_press(basis, r - basis @ (basis.T @ r))
    assert np.isfinite(press) and press == pytest.approx(lin.cv_sse_with(spike), rel=1e-9)
    # every row as refitted without its pose, but the spiked row: the fit without pose 1
    # cannot predict it (its column is all zero there), and it is not counted
    e = _errors_without_each_pose(np.hstack([scaled(jac), spike]), r)
    assert press == pytest.approx(float(e @ e) - e[5] ** 2, rel=1e-9)
