"""Inverse kinematics: FK round trips on the presets, selection rule, singularities, limits."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.errors import KinematicsError
from calibration.model.description import load_robot
from calibration.model.ik_results import JointLimits, SingularityMargins
from calibration.model.inverse_kinematics import select_solution, singularity_flags, solve_ik
from calibration.model.kinematics import KinematicModel, flange_poses, tcp_positions
from calibration.model.pieper_closed_form import (
    BRANCHES,
    N_BRANCHES,
    is_spherical_wrist,
    nearest_equivalent,
    spherical_approximation,
)

PRESETS = ("kr500", "kr210_r3100", "hp20d")
POS_TOL_MM = 1e-9
ROT_TOL = 1e-9  # rotation-matrix elements, i.e. rad for small errors
# The original q must come back when the pose is at least this far from every singularity.
CLEAR = SingularityMargins(shoulder_mm=1.0, elbow_rad=1e-3, wrist_rad=1e-3)

_ROBOTS = {name: load_robot(name) for name in PRESETS}


def robot(name: str) -> tuple[KinematicModel, JointLimits]:
    desc = _ROBOTS[name]
    return KinematicModel.from_description(desc), JointLimits.from_description(desc)


def wrapped(delta: np.ndarray) -> np.ndarray:
    return (delta + np.pi) % (2 * np.pi) - np.pi


def assert_reproduces(model: KinematicModel, q: np.ndarray, poses: np.ndarray, ok: np.ndarray):
    """Every solution ``q[ok]`` ``(N, B, 6)`` gives back its target pose (base frame)."""
    targets = np.broadcast_to(poses[:, None], (*ok.shape, 4, 4))[ok]
    got = flange_poses(model, q[ok], world=False)
    assert np.abs(got[:, :3, 3] - targets[:, :3, 3]).max(initial=0) <= POS_TOL_MM
    assert np.abs(got[:, :3, :3] - targets[:, :3, :3]).max(initial=0) <= ROT_TOL


def branch_of(q_true: np.ndarray, solutions: np.ndarray) -> int:
    """Index of the branch nearest ``q_true`` ``(6,)`` among ``solutions`` ``(B, 6)``."""
    dist = np.abs(wrapped(solutions - q_true)).max(axis=-1)
    return int(np.argmin(np.where(np.isnan(dist), np.inf, dist)))


def recovery_error(q_true: np.ndarray, solutions: np.ndarray) -> np.ndarray:
    """Per pose, the smallest max-joint distance (mod 2π) from ``q_true`` to a solution."""
    dist = np.abs(wrapped(solutions - q_true[:, None, :])).max(axis=-1)
    return np.nanmin(np.where(np.isnan(dist), np.inf, dist), axis=1)


def clear_of_singularities(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    return ~np.any(singularity_flags(model, q, CLEAR), axis=0)


def joint_vectors(name: str) -> st.SearchStrategy[np.ndarray]:
    _, limits = robot(name)
    joints = [
        st.floats(lo, hi, allow_nan=False, allow_infinity=False)
        for lo, hi in zip(limits.lower_rad, limits.upper_rad, strict=True)
    ]
    return st.tuples(*joints).map(np.array)


# -- round trips ------------------------------------------------------------------------
@pytest.mark.parametrize("name", PRESETS)
def test_presets_are_pieper_geometries(name):
    model, _ = robot(name)
    assert is_spherical_wrist(model)
    assert len(BRANCHES) == N_BRANCHES == 8


@pytest.mark.parametrize("name", PRESETS)
@settings(max_examples=120, deadline=None)
@given(data=st.data())
def test_round_trip_property(name, data):
    model, limits = robot(name)
    q = data.draw(joint_vectors(name))[None]
    pose = flange_poses(model, q, world=False)
    res = solve_ik(model, pose, limits=limits)

    assert res.solutions_rad.shape == (1, 8, 6)
    assert res.reachable.any()
    assert_reproduces(model, res.solutions_rad, pose, res.reachable)
    assert np.all(res.residual_mm[res.reachable] <= POS_TOL_MM)
    assert np.all(limits.contains(res.solutions_rad[res.valid]))
    assert np.all(np.isnan(res.solutions_rad[~res.reachable]))
    if not clear_of_singularities(model, q)[0]:
        return  # near a singularity q is ill-determined by the pose; checked elsewhere
    assert recovery_error(q, res.solutions_rad)[0] <= 1e-9
    branch = branch_of(q[0], res.solutions_rad[0])
    assert res.valid[0, branch]  # q is within limits, so is its branch
    # Pure shortest travel from q itself selects q (the default rule may prefer a
    # non-singular branch when q is within the default margins of a singularity).
    again = solve_ik(model, pose, limits=limits, q_current_rad=q[0], singular_penalty=0.0)
    np.testing.assert_allclose(again.chosen_rad, q, atol=1e-9)


@pytest.mark.parametrize("name", PRESETS)
def test_vectorized_batch_matches_single_poses(name):
    model, limits = robot(name)
    rng = np.random.default_rng(7)
    q = rng.uniform(limits.lower_rad, limits.upper_rad, (2000, 6))
    poses = flange_poses(model, q, world=False)
    res = solve_ik(model, poses, limits=limits)
    assert res.solutions_rad.shape == (2000, 8, 6)
    assert res.valid.shape == res.wrist_singular.shape == (2000, 8)
    assert_reproduces(model, res.solutions_rad, poses, res.reachable)
    clear = clear_of_singularities(model, q)
    assert clear.mean() > 0.9
    assert recovery_error(q[clear], res.solutions_rad[clear]).max() <= 1e-9
    for i in (0, 17, 1999):
        one = solve_ik(model, poses[i], limits=limits)
        np.testing.assert_array_equal(one.reachable[0], res.reachable[i])
        np.testing.assert_allclose(one.solutions_rad[0], res.solutions_rad[i], atol=1e-12)


@pytest.mark.parametrize("name", PRESETS)
def test_world_frame_and_tcp_targets(name):
    model, limits = robot(name)
    rng = np.random.default_rng(3)
    q = rng.uniform(limits.lower_rad, limits.upper_rad, (200, 6))
    base = solve_ik(model, flange_poses(model, q, world=False), limits=limits)
    world = solve_ik(model, flange_poses(model, q), frame="world", limits=limits)
    tcp = flange_poses(model, q)
    tcp[:, :3, 3] = tcp_positions(model, q)
    tool = solve_ik(model, tcp, frame="world", target="tcp", limits=limits)
    for other in (world, tool):
        np.testing.assert_array_equal(other.reachable, base.reachable)
        ok = base.reachable & ~base.singular
        np.testing.assert_allclose(other.solutions_rad[ok], base.solutions_rad[ok], atol=1e-9)
        assert np.nanmax(other.residual_mm) <= POS_TOL_MM


def perturbed(model: KinematicModel, seed: int) -> KinematicModel:
    """A 'calibrated' model: ~1 mm and ~0.1° deviations, betas included."""
    rng = np.random.default_rng(seed)
    x = model.parameter_vector().copy()
    per_joint = x[:30].reshape(6, 5)
    per_joint[:, [0, 2]] += rng.normal(0.0, 1.0, (6, 2))
    per_joint[:, [1, 3, 4]] += rng.normal(0.0, np.radians(0.1), (6, 3))
    x[30:36] += rng.normal(0.0, 1.0, 6) * np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
    return model.with_parameters(x)


@pytest.mark.parametrize("name", PRESETS)
def test_numeric_refinement_on_calibrated_model(name):
    nominal, limits = robot(name)
    model = perturbed(nominal, seed=11)
    assert not is_spherical_wrist(model)
    rng = np.random.default_rng(5)
    q = rng.uniform(limits.lower_rad, limits.upper_rad, (300, 6))
    poses = flange_poses(model, q)
    res = solve_ik(model, poses, frame="world", limits=limits)
    base_poses = flange_poses(model, q, world=False)
    assert_reproduces(model, res.solutions_rad, base_poses, res.reachable)
    assert np.all(res.residual_mm[res.reachable] <= 1e-9)
    assert np.all(res.residual_rad[res.reachable] <= 1e-11)
    assert np.median(res.iterations[res.reachable]) <= 4
    # Away from singularities (of the nominal geometry, with a margin for the deviations)
    # every original is found again.
    margins = SingularityMargins(shoulder_mm=20.0, elbow_rad=0.05, wrist_rad=0.05)
    clear = ~np.any(singularity_flags(nominal, q, margins), axis=0)
    assert clear.mean() > 0.8
    assert recovery_error(q[clear], res.solutions_rad[clear]).max() <= 1e-8
    # An explicit nominal gives the same answer as the automatic approximation.
    explicit = solve_ik(model, poses[:20], frame="world", limits=limits, nominal=nominal)
    ok = explicit.reachable & res.reachable[:20]
    np.testing.assert_allclose(explicit.solutions_rad[ok], res.solutions_rad[:20][ok], atol=1e-8)


def test_chosen_branch_only_refinement_matches_the_full_solve():
    nominal, limits = robot("kr210_r3100")
    model = perturbed(nominal, seed=4)
    rng = np.random.default_rng(8)
    q = rng.uniform(limits.lower_rad, limits.upper_rad, (300, 6))
    q_now = q + rng.normal(0.0, 0.05, q.shape)
    poses = flange_poses(model, q)
    args = {"frame": "world", "limits": limits, "q_current_rad": q_now}
    full = solve_ik(model, poses, **args)
    chosen = solve_ik(model, poses, branches="chosen", **args)
    assert chosen.iterations.sum() < full.iterations.sum() / 2
    assert np.all(chosen.residual_mm[chosen.reachable] <= 1e-9)
    # At most three candidates solved per pose, more only where all of them failed.
    assert np.mean(chosen.reachable.sum(axis=1) <= 3) > 0.95
    # Away from singularities both pick the same solution.
    margins = SingularityMargins(shoulder_mm=20.0, elbow_rad=0.05, wrist_rad=0.05)
    clear = ~np.any(singularity_flags(nominal, q, margins), axis=0)
    assert clear.mean() > 0.8
    np.testing.assert_allclose(chosen.chosen_rad[clear], full.chosen_rad[clear], atol=1e-9)


def test_spherical_approximation_restores_the_nominal_structure():
    nominal, _ = robot("kr500")
    approx = spherical_approximation(perturbed(nominal, seed=2))
    assert is_spherical_wrist(approx)
    np.testing.assert_array_equal(approx.beta_rad, 0.0)
    np.testing.assert_allclose(approx.alpha_rad, nominal.alpha_rad, atol=1e-15)
    x = nominal.parameter_vector().copy()
    x[2 * 5 + 1] = 1.2  # alpha3: joints 2 and 3 no longer parallel
    with pytest.raises(KinematicsError, match="alpha3"):
        spherical_approximation(nominal.with_parameters(x))


# -- singularities and reach ------------------------------------------------------------
def test_wrist_singularity_flagged_and_resolved_with_current_q4():
    model, _ = robot("kr500")  # no limits here: the other elbow exists (q3 < -120°)
    q = np.array([0.3, 0.2, -0.4, 1.1, 0.0, -0.7])
    pose = flange_poses(model, q, world=False)
    res = solve_ik(model, pose, q_current_rad=q)
    assert_reproduces(model, res.solutions_rad, pose[None], res.reachable)
    branch = branch_of(q, res.solutions_rad[0])
    flip = branch ^ 1  # index 4·shoulder + 2·elbow + wrist
    assert res.wrist_singular[0, [branch, flip]].all()
    assert not res.wrist_singular[~res.reachable].any()
    # Only q4 + q6 is determined; with the current q4 known the original comes back.
    np.testing.assert_allclose(res.solutions_rad[0, branch], q, atol=1e-9)
    # The method's order avoids the singular branches while others exist ...
    assert res.selection.index[0] not in (branch, flip) and not res.selection.singular[0]
    # ... and without a singularity penalty the shortest travel (none) wins.
    soft = solve_ik(model, pose, q_current_rad=q, singular_penalty=0.0)
    np.testing.assert_allclose(soft.chosen_rad[0], q, atol=1e-9)
    assert soft.selection.singular[0]


def test_elbow_singularity_when_arm_stretched():
    model, _ = robot("kr210_r3100")
    # psi = q3 + offset3 + atan2(-sin(alpha4)·d4, a4) = 0: forearm in line with upper arm.
    phi = np.arctan2(-np.sin(model.alpha_rad[3]) * model.d_mm[3], model.a_mm[3])
    q = np.array([0.2, 0.1, -phi - model.theta_offset_rad[2], 0.5, 0.6, 0.1])
    pose = flange_poses(model, q, world=False)
    res = solve_ik(model, pose)
    assert_reproduces(model, res.solutions_rad, pose[None], res.reachable)
    branch = branch_of(q, res.solutions_rad[0])
    twin = branch ^ 2  # the other elbow: on the workspace boundary both elbows meet
    assert res.reachable[0, [branch, twin]].all()
    assert res.elbow_singular[0, [branch, twin]].all()
    up, down = res.solutions_rad[0, branch], res.solutions_rad[0, twin]
    np.testing.assert_allclose(up, down, atol=1e-6)  # rounding near acos(±1)
    beyond = pose.copy()
    beyond[:3, 3] *= 1.001
    assert not solve_ik(model, beyond).reachable.any()


def test_shoulder_singularity_wrist_centre_on_axis_1():
    model, limits = robot("hp20d")
    rot = flange_poses(model, np.array([0.0, 0.4, 0.3, 0.2, 0.8, 0.1]), world=False)[:3, :3]
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = np.array([0.0, 0.0, 1600.0]) + model.d_mm[5] * rot[:, 2]
    q_now = np.array([0.7, 0.0, 0.0, 0.0, 0.5, 0.0])
    res = solve_ik(model, pose, limits=limits, q_current_rad=q_now)
    assert res.reachable[0].any()
    assert np.all(res.shoulder_singular[0][res.reachable[0]])
    assert_reproduces(model, res.solutions_rad, pose[None], res.reachable)
    # q1 is free there: the solver keeps the current one.
    np.testing.assert_allclose(res.solutions_rad[0][res.reachable[0]][:, 0], 0.7, atol=1e-12)


def test_unreachable_pose_is_flagged_not_raised():
    model, limits = robot("kr500")
    pose = np.eye(4)
    pose[:3, 3] = [10_000.0, 0.0, 0.0]
    res = solve_ik(model, np.stack([pose, pose]), limits=limits)
    assert res.n_poses == 2
    assert not res.reachable.any() and not res.valid.any()
    assert np.isnan(res.solutions_rad).all() and np.isnan(res.residual_mm).all()
    assert not res.selection.found.any()
    np.testing.assert_array_equal(res.selection.index, -1)
    assert np.isnan(res.chosen_rad).all()


def test_reachable_but_outside_joint_limits():
    model, limits = robot("kr500")
    q = np.array([0.1, np.radians(120.0), -0.3, 0.2, 0.5, 0.1])  # q2 above its 110° limit
    res = solve_ik(model, flange_poses(model, q, world=False), limits=limits)
    branch = branch_of(q, res.solutions_rad[0])
    assert res.reachable[0, branch] and not res.within_limits[0, branch]
    assert not res.valid[0, branch]


# -- ±360° equivalents and the selection rule -------------------------------------------
def test_nearest_equivalent_uses_wide_joint_ranges():
    limits = JointLimits(np.radians([-185.0, -350.0]), np.radians([185.0, 350.0]))
    q, inside = nearest_equivalent([[3.0, -3.0]], [[0.0, 3.0]], limits)
    np.testing.assert_allclose(q, [[3.0, 2 * np.pi - 3.0]])
    assert inside[0]
    narrow = JointLimits(np.radians([-90.0]), np.radians([90.0]))
    _, inside = nearest_equivalent([[3.0]], [[0.0]], narrow)
    assert not inside[0]


def test_selection_prefers_moving_the_wrist():
    current = np.zeros(6)
    big_axis = [0.5, 0, 0, 0, 0, 0]  # plain distance 0.5, weighted 1.5
    wrist = [0, 0, 0, 0.6, 0, 0.6]  # plain distance 1.2, weighted 1.2
    sel = select_solution(np.array([[big_axis, wrist]]), current)
    assert sel.index[0] == 1 and sel.found[0]
    np.testing.assert_allclose(sel.travel, [1.2])
    flat = select_solution(np.array([[big_axis, wrist]]), current, weights=np.ones(6))
    assert flat.index[0] == 0


def test_selection_avoids_singular_and_out_of_limit_solutions():
    limits = JointLimits(np.full(6, -2.0), np.full(6, 2.0))
    sols = np.array([[[0.1] * 6, [0.3] * 6, [2.5] + [0.0] * 5, [1.0] * 6]])
    singular = np.array([[True, False, False, False]])
    sel = select_solution(sols, np.zeros(6), singular=singular, limits=limits)
    assert sel.index[0] == 1 and not sel.singular[0]
    # Only singular candidates left: the nearest singular one, and it says so.
    sel = select_solution(sols[:, :1], np.zeros(6), singular=singular[:, :1], limits=limits)
    assert sel.index[0] == 0 and sel.singular[0]
    # A finite penalty lets a near-singular solution win against a long way round.
    soft = select_solution(sols, np.zeros(6), singular=singular, singular_penalty=0.5)
    assert soft.index[0] == 0
    # Invalid candidates never win, and nothing valid means found=False.
    none = select_solution(sols, np.zeros(6), valid=np.zeros((1, 4), bool))
    assert not none.found[0] and none.index[0] == -1 and np.isnan(none.q_rad).all()


def test_selection_takes_the_2pi_equivalent_nearest_current():
    limits = JointLimits(
        np.radians([-185, -40, -120, -350, -120, -350.0]),
        np.radians([185, 110, 65, 350, 120, 350.0]),
    )
    sols = np.array([[[0.0, 0.0, 0.0, -3.0, 0.0, 3.0]]])
    sel = select_solution(sols, [0.0, 0.0, 0.0, 3.0, 0.0, -3.0], limits=limits)
    np.testing.assert_allclose(sel.q_rad[0], [0, 0, 0, 2 * np.pi - 3.0, 0, 3.0 - 2 * np.pi])


def test_selection_with_current_vector_keeps_the_branch():
    model, limits = robot("kr500")
    rng = np.random.default_rng(9)
    q = rng.uniform(limits.lower_rad, limits.upper_rad, (500, 6))
    res = solve_ik(model, flange_poses(model, q, world=False), limits=limits, q_current_rad=q)
    clear = clear_of_singularities(model, q)
    clear &= ~np.any(singularity_flags(model, q), axis=0)  # default margins: 1°, 10 mm
    assert res.selection.found[clear].all()
    np.testing.assert_allclose(res.chosen_rad[clear], q[clear], atol=1e-9)
    assert res.selection.travel[clear].max() <= 1e-8


# -- argument errors --------------------------------------------------------------------
def test_bad_arguments_raise():
    model, _ = robot("kr500")
    with pytest.raises(KinematicsError, match="shape"):
        solve_ik(model, np.eye(3))
    with pytest.raises(KinematicsError, match="q_current"):
        solve_ik(model, np.eye(4), q_current_rad=np.zeros(5))
    with pytest.raises(KinematicsError, match="frame"):
        solve_ik(model, np.eye(4), frame="tracker")  # type: ignore[arg-type]
    with pytest.raises(KinematicsError, match="branches"):
        solve_ik(model, np.eye(4), branches="some")  # type: ignore[arg-type]
    with pytest.raises(KinematicsError, match="weights"):
        select_solution(np.zeros((1, 8, 6)), np.zeros(6), weights=np.ones(5))
    with pytest.raises(KinematicsError, match="shape"):
        select_solution(np.zeros((8, 6)), np.zeros(6))
    five = KinematicModel.from_description(
        _ROBOTS["kr500"].with_joints(_ROBOTS["kr500"].joints[:5])
    )
    with pytest.raises(KinematicsError, match="6 joints"):
        solve_ik(five, np.eye(4))
