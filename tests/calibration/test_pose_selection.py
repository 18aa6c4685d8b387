"""Observability indices and pose selection."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.identify.identification import identify
from calibration.identify.pose_selection import (
    OBSERVABILITY_INDICES,
    PoseSelectionError,
    observability_indices,
    scaled_candidate_jacobian,
    select_poses,
    select_poses_for_model,
)
from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel
from sim_devices.pose_campaign import (
    plan_identification_poses,
    reachable_mask,
    sample_reachable_poses,
)
from sim_devices.truth import TrueCell


def test_indices_from_known_singular_values():
    # a block-diagonal Jacobian of 2 poses with singular values 4, 2, 1
    jac = np.zeros((2, 3, 3))
    jac[0, 0, 0], jac[0, 1, 1], jac[1, 0, 2] = 4.0, 2.0, 1.0
    idx = observability_indices(jac)
    assert idx["O1"] == pytest.approx((4 * 2 * 1) ** (1 / 3) / np.sqrt(2))
    assert idx["O2"] == pytest.approx(1 / 4)
    assert idx["O3"] == pytest.approx(1.0)
    assert idx["O4"] == pytest.approx(1 / 4)


@pytest.fixture(scope="module")
def candidates():
    desc = load_robot("kr500")
    q = sample_reachable_poses(desc, 300, np.random.default_rng(1))
    return desc, q


@pytest.mark.parametrize("index", list(OBSERVABILITY_INDICES))
def test_selection_beats_random(candidates, index):
    desc, q = candidates
    model = KinematicModel.from_description(desc)
    sel = select_poses_for_model(model, q, 40, index=index)
    assert len(set(sel.indices.tolist())) == 40
    assert sel.value > sel.random_value
    jac = scaled_candidate_jacobian(model, q)
    rng = np.random.default_rng(0)
    for _ in range(5):
        pick = rng.choice(len(q), 40, replace=False)
        assert observability_indices(jac[pick])[index] < sel.value


def test_selected_poses_give_smaller_standard_errors(candidates):
    desc, _ = candidates
    cell = TrueCell.create(desc, 4)
    nominal = KinematicModel.from_description(desc)
    rng = np.random.default_rng(4)
    n = 40
    spreads = {}
    for label, index in (("random", None), ("O1", "O1")):
        q = plan_identification_poses(desc, n, rng, index=index)
        pts, _ = cell.tracker.measure(cell.tcp_mm(q), rng)
        result = identify(nominal, q, pts)
        # geometric mean of the scaled standard errors: the D-optimality O1 improves
        scale = result.identifiability.column_scale[result.free]
        spreads[label] = np.exp(np.mean(np.log(np.sqrt(np.diag(result.covariance)) * scale)))
    assert spreads["O1"] < spreads["random"]


def test_bad_arguments(candidates):
    desc, q = candidates
    jac = scaled_candidate_jacobian(KinematicModel.from_description(desc), q[:20])
    with pytest.raises(PoseSelectionError, match="index"):
        select_poses(jac, 5, index="O9")
    with pytest.raises(PoseSelectionError, match="cannot pick"):
        select_poses(jac, 21)
    with pytest.raises(PoseSelectionError, match="shape"):
        select_poses(jac[:, :2], 5)


def test_sampled_poses_are_reachable_and_within_limits(candidates):
    desc, q = candidates
    lo = np.radians([j.lower_deg for j in desc.joints])
    hi = np.radians([j.upper_deg for j in desc.joints])
    assert q.shape == (300, 6)
    assert np.all((q >= lo) & (q <= hi))
    assert np.all(reachable_mask(desc, q))
    assert np.all(np.abs(np.degrees(q[:, 4])) >= 10.0 - 1e-9)  # away from the wrist flip
    stretched = np.zeros(6)  # Home: forearm horizontal, not a singular pose ...
    stretched[2] = np.radians(-90.0 + np.degrees(np.arctan2(55.0, 1025.0)))  # ... this is
    assert not reachable_mask(desc, stretched[None, :])[0]


@pytest.mark.parametrize("seed", [1, 2])
def test_greedy_by_rank3_updates_is_the_exact_greedy(seed):
    # 40 steps of 12 parameters: exact steps while rank-deficient, then rank-3 updates
    # with a refresh; every step must pick what the determinant recomputed from scratch picks
    rng = np.random.default_rng(seed)
    h = rng.normal(size=(300, 3, 12)) * rng.uniform(0.1, 3.0, size=(1, 1, 12))
    sel = select_poses(h, 40, exchange_passes=0)
    ridge = 1e-9 * float(np.sum(h * h)) / 12 / 300 * np.eye(12)
    info, chosen = ridge.copy(), []
    for _ in range(40):
        logdet = np.linalg.slogdet(info + np.einsum("nip,niq->npq", h, h))[1]
        logdet[chosen] = -np.inf
        best = int(np.argmax(logdet))
        chosen.append(best)
        info = info + h[best].T @ h[best]
    assert sel.indices.tolist() == chosen
