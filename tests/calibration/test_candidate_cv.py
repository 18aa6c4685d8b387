"""The closed loop's cross-validation by leaving one pose out: the hat-matrix PRESS and
predictive deviance are the same as refitting without each pose in turn, for the model and
for the model with a candidate, and stay finite when a pose alone determines a direction;
a pose at the design's edge sways the PRESS's choice between two candidates more than the
deviance's."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.effects.candidate_scoring import (
    LinearizedModel,
    pose_deviance,
    pose_press,
    scaled,
)


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


def _model_and_candidate(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """A model's columns ``(3m, 7)`` of mixed scales, a candidate's ``(3m, 3)`` and a
    residual with both in it and unit noise; ``m`` = 25 poses."""
    rng = np.random.default_rng(seed)
    m = 25
    jac = rng.normal(size=(3 * m, 7)) * rng.uniform(0.1, 10.0, size=7)
    cand = rng.normal(size=(3 * m, 3))
    r = jac @ rng.normal(size=7) + cand @ rng.normal(size=3) + rng.normal(size=3 * m)
    return jac, cand, r, m


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_leave_one_pose_out_is_the_refit_without_each_pose(seed):
    jac, cand, r, m = _model_and_candidate(seed)
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


def _deviance_without_each_pose(x: np.ndarray, r: np.ndarray, sigma2: float) -> float:
    """Σ over poses of ``dᵀC⁻¹d + σ²·ln det C``: ``d`` the pose's prediction error by the fit
    without it, ``σ²C`` its predictive covariance ``σ²(I + X_i (X₋ᵢᵀX₋ᵢ)⁻¹ X_iᵀ)``."""
    total = 0.0
    for i in range(len(r) // 3):
        test = np.arange(3 * i, 3 * i + 3)
        train = np.setdiff1d(np.arange(len(r)), test)
        coef, *_ = np.linalg.lstsq(x[train], r[train], rcond=None)
        d = r[test] - x[test] @ coef
        c = np.eye(3) + x[test] @ np.linalg.solve(x[train].T @ x[train], x[test].T)
        total += float(d @ np.linalg.solve(c, d)) + sigma2 * float(np.linalg.slogdet(c)[1])
    return total


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_predictive_deviance_is_the_refit_without_each_pose(seed):
    jac, cand, r, m = _model_and_candidate(seed)
    lin = LinearizedModel.build(r, jac, m, 5, 0, leave_one_out=True, deviance=True)
    want = _deviance_without_each_pose(scaled(jac), r, lin.sigma2)
    assert lin.cv0 == pytest.approx(want, rel=1e-9)
    both = np.hstack([scaled(jac), scaled(cand)])
    got = lin.cv_sse_with(scaled(cand))
    assert got == pytest.approx(_deviance_without_each_pose(both, r, lin.sigma2), rel=1e-9)
    assert got < lin.cv0
    # the PRESS of the same model is another number (the squared misses alone)
    assert pose_press(lin.basis, lin.fit0) != pytest.approx(lin.cv0, rel=1e-3)
    assert np.isfinite(pose_deviance(lin.basis, lin.fit0, lin.sigma2))


def _edge_pose_trial(seed: int, deviance: bool) -> bool:
    """Whether leave-one-out prefers the true candidate ``a`` to a decoy ``b`` that follows
    ``a`` loosely everywhere and differs most at pose 0, a pose at the design's edge (its
    rows 12× the others: it nearly alone determines some directions)."""
    rng = np.random.default_rng(seed)
    m = 30
    jac = rng.normal(size=(3 * m, 6))
    jac[:3] *= 12.0
    a = rng.normal(size=(3 * m, 1))
    b = a + 0.5 * rng.normal(size=(3 * m, 1))
    b[:3] = a[:3] + 4.8 * rng.normal(size=(3, 1))
    r = jac @ rng.normal(size=6) + 0.6 * a[:, 0] + rng.normal(size=3 * m)
    lin = LinearizedModel.build(r, jac, m, 5, 0, leave_one_out=True, deviance=deviance)
    return lin.cv_sse_with(scaled(a)) < lin.cv_sse_with(scaled(b))


def test_a_pose_at_the_designs_edge_sways_the_press_more_than_the_deviance():
    """Why the loop scores by the deviance: the PRESS multiplies the edge pose's residual by
    ``1/(1 − λ)²`` (λ up to 0.94 here), so its noise picks the decoy more often (22 % of
    the 400 draws against 8.5 %)."""
    press = np.mean([_edge_pose_trial(s, False) for s in range(400)])
    deviance = np.mean([_edge_pose_trial(s, True) for s in range(400)])
    assert deviance >= 0.88 and deviance - press >= 0.05, (press, deviance)
