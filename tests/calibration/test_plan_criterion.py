"""The planner's criterion (:mod:`calibration.plan.plan_criterion`): its rank-3 updates
against the criterion computed from scratch, and the exchange lowering it; the model it
designs for (the gravity term in the physical form the closed loop ends with)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from calibration.effects.effect_base import EffectContext, EffectData, ModelAtPoses
from calibration.effects.effect_candidates import gravity_candidate
from calibration.effects.effect_kinds import regressor_matrix
from calibration.identify.pose_selection import select_poses
from calibration.model.cell_geometry import CellGeometrySpec, resolve
from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel, identification_jacobian
from calibration.plan.campaign_plan import (
    Observability,
    PlanSettings,
    loop_can_add,
    observability,
    parameter_sigmas,
    physical_form_columns,
)
from calibration.plan.plan_criterion import (
    DesignProblem,
    _info,
    _State,
    criterion_value,
    exchange,
)

FloatArray = NDArray[np.float64]


def _problem(seed: int, n: int = 300, r: int = 12, q: int = 5) -> DesignProblem:
    rng = np.random.default_rng(seed)
    plain = rng.normal(size=(n, 3, r)) * rng.uniform(0.2, 2.0, size=(n, 1, 1))
    left = 0.3 * rng.normal(size=(n, 3, q)) + 0.5 * plain[:, :, :q]  # partly aliased
    sigma = rng.uniform(0.5, 2.0, size=(n, 1, 1))
    w = np.einsum("nip,niq->pq", plain, plain) / n
    x = np.einsum("nip,niq->pq", plain, left) / n
    z = float(np.sum(left**2)) / n
    return DesignProblem(plain / sigma, left / sigma, w, x, z, 0.3 * np.eye(r))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_deltas_are_the_criterion_changes(seed: int) -> None:
    p = _problem(seed)
    rng = np.random.default_rng(seed + 10)
    chosen = [int(i) for i in rng.choice(len(p.h), 20, replace=False)]
    base = criterion_value(p, np.array(chosen)).total_mm2
    state = _State(p, np.arange(len(p.h)), *_info(p, chosen))
    add, remove = state.deltas(1.0), state.deltas(-1.0)
    others = [i for i in range(len(p.h)) if i not in chosen][:5]
    for i in others:
        exact = criterion_value(p, np.array([*chosen, i])).total_mm2 - base
        assert add[i] == pytest.approx(exact, rel=1e-8, abs=1e-12)
    for pos in (0, 7):
        rest = chosen[:pos] + chosen[pos + 1 :]
        exact = criterion_value(p, np.array(rest)).total_mm2 - base
        assert remove[chosen[pos]] == pytest.approx(exact, rel=1e-8, abs=1e-12)


def test_updates_match_a_fresh_state() -> None:
    p = _problem(4)
    chosen = list(range(0, 40, 2))
    state = _State(p, np.arange(len(p.h)), *_info(p, chosen))
    state.update(chosen[3], -1.0)
    state.update(101, 1.0)
    swapped = [*chosen[:3], *chosen[4:], 101]
    fresh = _State(p, np.arange(len(p.h)), *_info(p, swapped))
    for name in ("a", "d", "u", "uw", "q3", "t3", "res", "f3"):
        got, want = getattr(state, name), getattr(fresh, name)
        assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want)), name


def test_without_left_out_terms_it_is_the_bayesian_i_criterion() -> None:
    p = _problem(5, q=0)
    rows = np.arange(25)
    h = p.h[rows]
    expected = np.trace(p.w @ np.linalg.inv(p.prior + np.einsum("nip,niq->pq", h, h)))
    value = criterion_value(p, rows)
    assert value.bias_mm2 == pytest.approx(0.0, abs=1e-12)
    assert value.total_mm2 == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("seed", [6, 7])
def test_exchange_lowers_the_criterion_below_the_d_optimal_start(seed: int) -> None:
    p = _problem(seed)
    chosen = [int(i) for i in select_poses(p.h, 20, exchange_passes=0).indices]
    start = criterion_value(p, np.array(chosen))
    swaps = exchange(p, chosen, 6)
    end = criterion_value(p, np.array(chosen))
    assert swaps > 0 and len(set(chosen)) == 20
    assert end.total_mm2 < start.total_mm2 and end.bias_mm2 < start.bias_mm2
    rng = np.random.default_rng(seed)
    randoms = [criterion_value(p, rng.choice(len(p.h), 20, replace=False)) for _ in range(10)]
    assert end.total_mm2 < min(r.total_mm2 for r in randoms)


def test_loop_can_add_follows_the_penalty_and_the_degrees_of_freedom() -> None:
    # the linear gravity term (34 parameters) beside 27 geometric ones: not from 50 poses
    assert not loop_can_add(34, 50, 27) and not loop_can_add(34, 80, 27)
    assert loop_can_add(34, 90, 27) and loop_can_add(34, 150, 27)
    assert loop_can_add(2, 50, 27)  # a cyclic error's two terms
    # its physical form (18) beside them: from 46 poses on, so a 50-pose plan designs for it
    assert not loop_can_add(18, 44, 27) and loop_can_add(18, 46, 27) and loop_can_add(18, 50, 27)


def _kr500_poses(n: int, seed: int) -> tuple[RobotDescription, FloatArray]:
    robot = load_robot("kr500")
    lo = np.radians([j.lower_deg for j in robot.joints])
    hi = np.radians([j.upper_deg for j in robot.joints])
    return robot, np.random.default_rng(seed).uniform(lo, hi, size=(n, len(lo)))


def test_physical_form_columns_lie_in_the_linear_forms_span() -> None:
    # the physical form p_jk = ρ_j·w_k is the linear form constrained: its derivatives
    # (shared moments, counterbalance terms, a joint turned by its gravity torque) are
    # combinations of the linear form's columns, fewer of them
    robot, q = _kr500_poses(200, 3)
    model = KinematicModel.from_description(robot)
    tcp, jac = identification_jacobian(model, q)
    kin = ModelAtPoses(model, q, tcp, jac)
    ctx = EffectContext(robot, EffectData(q))
    linear = gravity_candidate(ctx)
    assert linear is not None
    lin = regressor_matrix([linear], ctx, slice(0, len(q)), kin).reshape(3 * len(q), -1)
    cols, names = physical_form_columns(ctx, kin, linear)
    phys = cols.reshape(3 * len(q), -1)
    assert phys.shape[1] == len(names) == 18 < lin.shape[1] == 34
    coef, *_ = np.linalg.lstsq(lin, phys, rcond=None)
    left = np.linalg.norm(phys - lin @ coef, axis=0) / np.linalg.norm(phys, axis=0)
    assert np.all(left < 1e-8)
    unit = phys / np.linalg.norm(phys, axis=0)  # the columns' units differ (µrad, N·mm)
    assert np.linalg.matrix_rank(unit, tol=1e-6) == 18


def test_plan_fits_gravity_in_the_physical_form_from_50_poses() -> None:
    robot, q = _kr500_poses(300, 4)
    geometry = resolve(CellGeometrySpec(), robot)
    obs50 = observability(robot, geometry, q, PlanSettings(n_identify=50))
    assert obs50.left_out == ()
    assert sum("compliance_rad_per_nmm" in n for n in obs50.names) == 4  # joints 3..6 against 2
    obs20 = observability(robot, geometry, q, PlanSettings(n_identify=20))
    assert obs20.left_out and "linear form" in obs20.left_out[0]  # its bias, not fitted
    assert not any("gravity" in n for n in obs20.names)


def _observability(blocks: FloatArray, sd: FloatArray, sigma: float) -> Observability:
    """A toy :class:`Observability` of scaled columns ``blocks`` ``(N, 3, p)`` with prior
    1 σ ``sd`` ``(p,)``, reduced as :func:`observability` reduces (the design's prior on
    the observed directions alone)."""
    ev, vec = np.linalg.eigh(np.einsum("nip,niq->pq", blocks, blocks))
    basis = vec[:, ev > 1e-8 * ev[-1]]
    plain = blocks @ basis
    names = tuple(f"p{i}" for i in range(len(sd)))
    return Observability(plain / sigma, plain, basis, np.ones(len(sd)), names, sd)


def test_parameter_sigmas_are_the_posterior_of_every_parameter() -> None:
    rng = np.random.default_rng(4)
    n, sigma = 40, 0.01
    own = rng.normal(size=(n, 3, 2))
    sd = np.array([0.03, 1e-5, 0.5])
    # apart: the posterior of the reduced parameters, as before
    obs = _observability(np.concatenate([own, rng.normal(size=(n, 3, 1))], axis=2), sd, sigma)
    rows = np.arange(n)
    full = np.einsum("nip,niq->pq", obs.weighted, obs.weighted) + obs.prior
    before = np.sqrt(np.diag(obs.to_scaled @ np.linalg.inv(full) @ obs.to_scaled.T))
    np.testing.assert_allclose(parameter_sigmas(obs, rows), before, rtol=1e-6)
    # the first two seen only as a sum (a cyclic error and a gravity moment turning the
    # same joint alike): the data pin the sum and the tight prior the second, so the
    # first is known as well as the sum, not as well as the tight one
    blocks = np.concatenate([own[:, :, :1], own[:, :, :1], own[:, :, 1:]], axis=2)
    obs = _observability(blocks, sd, sigma)
    s = parameter_sigmas(obs, rows)
    alone = _observability(blocks[:, :, [0, 2]], sd[[0, 2]], sigma)
    assert s[1] == pytest.approx(sd[1], rel=1e-3)
    assert s[0] == pytest.approx(parameter_sigmas(alone, rows)[0], rel=1e-2)
    assert s[0] > 10 * sd[1]
