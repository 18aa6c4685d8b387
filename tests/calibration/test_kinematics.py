"""Forward kinematics and Jacobians against independent references and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.errors import KinematicsError
from calibration.model.description import load_robot
from calibration.model.kinematics import (
    KinematicModel,
    fixed_xyz_from_rotation,
    flange_poses,
    geometric_jacobian,
    identification_jacobian,
    rotation_from_fixed_xyz,
    tcp_positions,
)

PRESETS = ("kr500", "kr210_r3100", "hp20d")
STEP = 1e-6  # central-difference step, mm or rad
# Central differences with h = 1e-6 on mm-scale positions (~3000 mm) carry ~1e-6 of
# rounding error; the analytic values are compared relative to max(|value|, 1).
FD_RTOL = 2e-6


def model_of(name: str) -> KinematicModel:
    return KinematicModel.from_description(load_robot(name))


def calibrated(name: str, seed: int = 0) -> KinematicModel:
    """A preset with every parameter disturbed, betas and base tilts included."""
    model = model_of(name)
    rng = np.random.default_rng(seed)
    x = model.parameter_vector().copy()
    per_joint = x[:30].reshape(6, 5)
    per_joint[:, [0, 2]] += rng.normal(0.0, 2.0, (6, 2))
    per_joint[:, [1, 3, 4]] += rng.normal(0.0, 0.01, (6, 3))
    x[30:33] += rng.normal(0.0, 10.0, 3)
    x[33:36] += rng.normal(0.0, 0.05, 3)
    x[36:] += rng.normal(0.0, 5.0, 3)
    return model.with_parameters(x)


def random_q(n: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-np.pi, np.pi, (n, 6))


def reference_flange(model: KinematicModel, q: np.ndarray, world: bool = True) -> np.ndarray:
    """Naive 4×4 product of the documented link transforms, one pose ``(6,)`` at a time."""

    def rx(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])

    def ry(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])

    def rz(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    def trans(x, y, z):
        t = np.eye(4)
        t[:3, 3] = x, y, z
        return t

    t = np.eye(4)
    if world:
        rxb, ryb, rzb = model.base_rad
        t = trans(*model.base_mm) @ rz(rzb) @ ry(ryb) @ rx(rxb)
    for i in range(model.n_joints):
        t = (
            t
            @ rx(model.alpha_rad[i])
            @ trans(model.a_mm[i], 0, 0)
            @ ry(model.beta_rad[i])
            @ rz(q[i] + model.theta_offset_rad[i])
            @ trans(0, 0, model.d_mm[i])
        )
    return t


def assert_fd_close(analytic: np.ndarray, numeric: np.ndarray) -> None:
    scale = np.maximum(np.abs(analytic), 1.0)
    assert np.max(np.abs(analytic - numeric) / scale) <= FD_RTOL


# -- forward kinematics -----------------------------------------------------------------
@pytest.mark.parametrize("name", PRESETS)
@pytest.mark.parametrize("world", [True, False])
def test_flange_poses_match_naive_link_product(name, world):
    model = calibrated(name)
    q = random_q(20)
    got = flange_poses(model, q, world=world)
    want = np.stack([reference_flange(model, qi, world) for qi in q])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    tool = np.append(model.tool_mm, 1.0)
    np.testing.assert_allclose(
        tcp_positions(model, q, world=world), (want @ tool)[:, :3], atol=1e-9
    )


@pytest.mark.parametrize(
    ("name", "home_mm"),
    [
        # q = 0: upper arm vertical, forearm horizontal: (a2 + d4 + d6, 0, d1 + a3 + a4)
        ("kr500", (500 + 1025 + 290, 0, 1045 + 1300 + 55)),
        ("kr210_r3100", (350 + 1400 + 215, 0, 675 + 1350 - 41)),
        ("hp20d", (150 + 795 + 100, 0, 505 + 760 + 200)),
    ],
)
def test_home_flange_position_of_presets(name, home_mm):
    pose = flange_poses(model_of(name), np.zeros(6), world=False)
    np.testing.assert_allclose(pose[:3, 3], home_mm, atol=1e-9)
    np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-15)


# -- Jacobians vs central differences ---------------------------------------------------
@pytest.mark.parametrize("name", PRESETS)
def test_identification_jacobian_matches_finite_differences(name):
    model = calibrated(name, seed=3)
    q = random_q(8, seed=4)
    tcp, jac = identification_jacobian(model, q)
    np.testing.assert_allclose(tcp, tcp_positions(model, q), atol=1e-12)
    x = model.parameter_vector()
    numeric = np.empty_like(jac)
    for k in range(x.size):
        dx = np.zeros_like(x)
        dx[k] = STEP
        plus = tcp_positions(model.with_parameters(x + dx), q)
        minus = tcp_positions(model.with_parameters(x - dx), q)
        numeric[:, :, k] = (plus - minus) / (2 * STEP)
    assert jac.shape == (8, 3, model.n_parameters)
    assert_fd_close(jac, numeric)


def _vee(m: np.ndarray) -> np.ndarray:
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )


@pytest.mark.parametrize("name", PRESETS)
@pytest.mark.parametrize(("point", "frame"), [("tcp", "world"), ("flange", "base")])
def test_geometric_jacobian_matches_finite_differences(name, point, frame):
    model = calibrated(name, seed=5)
    q = random_q(8, seed=6)
    world = frame == "world"

    def point_and_rotation(qq):
        pose = flange_poses(model, qq, world=world)
        p = tcp_positions(model, qq, world=world) if point == "tcp" else pose[:, :3, 3]
        return p, pose[:, :3, :3]

    jac = geometric_jacobian(model, q, point=point, frame=frame)
    numeric = np.empty_like(jac)
    _, rot = point_and_rotation(q)
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = STEP
        (p_plus, r_plus), (p_minus, r_minus) = (
            point_and_rotation(q + dq),
            point_and_rotation(q - dq),
        )
        numeric[:, :3, j] = (p_plus - p_minus) / (2 * STEP)
        # ω^ = dR/dq · Rᵀ
        numeric[:, 3:, j] = _vee((r_plus - r_minus) / (2 * STEP) @ np.swapaxes(rot, 1, 2))
    assert_fd_close(jac, numeric)


# -- shapes, parameters, angles, errors -------------------------------------------------
def test_single_vector_and_batch_give_the_same_numbers():
    model = calibrated("kr500")
    q = random_q(3)
    assert flange_poses(model, q[1]).shape == (4, 4)
    assert tcp_positions(model, q[1]).shape == (3,)
    assert geometric_jacobian(model, q[1]).shape == (6, 6)
    tcp1, jac1 = identification_jacobian(model, q[1])
    assert tcp1.shape == (3,) and jac1.shape == (3, model.n_parameters)
    np.testing.assert_array_equal(flange_poses(model, q[1]), flange_poses(model, q)[1])
    np.testing.assert_array_equal(tcp_positions(model, q[1]), tcp_positions(model, q)[1])
    np.testing.assert_array_equal(geometric_jacobian(model, q[1]), geometric_jacobian(model, q)[1])
    np.testing.assert_array_equal(jac1, identification_jacobian(model, q)[1][1])
    assert flange_poses(model, q[:1]).shape == (1, 4, 4)
    assert flange_poses(model, np.zeros((0, 6))).shape == (0, 4, 4)


@pytest.mark.parametrize("name", PRESETS)
def test_parameter_vector_round_trip(name):
    model = calibrated(name)
    x = model.parameter_vector()
    assert x.shape == (model.n_parameters,) == (5 * 6 + 9,)
    assert len(model.parameter_names()) == x.size
    assert model.parameter_names()[:5] == [
        "joint1.a_mm",
        "joint1.alpha_rad",
        "joint1.d_mm",
        "joint1.theta_offset_rad",
        "joint1.beta_rad",
    ]
    again = model.with_parameters(x)
    np.testing.assert_array_equal(again.parameter_vector(), x)
    # with_parameters copies: changing the vector afterwards leaves the model alone.
    x2 = x.copy()
    rebuilt = model.with_parameters(x2)
    x2[:] = 0
    np.testing.assert_array_equal(rebuilt.parameter_vector(), x)
    # Through the description (degrees) and back (radians).
    desc = model.to_description(load_robot(name))
    np.testing.assert_allclose(
        KinematicModel.from_description(desc).parameter_vector(), x, rtol=1e-14, atol=1e-12
    )


@settings(max_examples=200, deadline=None)
@given(
    rx=st.floats(-np.pi, np.pi),
    ry=st.floats(-np.pi / 2 + 1e-6, np.pi / 2 - 1e-6),
    rz=st.floats(-np.pi, np.pi),
)
def test_fixed_xyz_round_trip(rx, ry, rz):
    r = rotation_from_fixed_xyz(rx, ry, rz)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    back = fixed_xyz_from_rotation(r)
    # arcsin loses digits next to gimbal lock (~eps / cos(ry)): 1e-9 covers cos(ry) >= 1e-6.
    np.testing.assert_allclose(rotation_from_fixed_xyz(*back), r, rtol=0, atol=1e-9)
    if np.cos(ry) > 1e-3:
        np.testing.assert_allclose(back[1], ry, atol=1e-12)
        # rx and rz come back modulo 2π (±π is one angle).
        for got, want in ((back[0], rx), (back[2], rz)):
            assert abs((got - want + np.pi) % (2 * np.pi) - np.pi) <= 1e-12


@pytest.mark.parametrize(
    "q",
    [np.zeros(5), np.zeros((2, 7)), np.zeros((2, 3, 6)), np.zeros(())],
    ids=["short", "wide", "3d", "scalar"],
)
def test_bad_joint_shapes_raise(q):
    model = model_of("kr500")
    for fn in (flange_poses, tcp_positions, geometric_jacobian, identification_jacobian):
        with pytest.raises(KinematicsError, match="shape"):
            fn(model, q)


def test_bad_parameter_vector_and_template_raise():
    model = model_of("kr500")
    with pytest.raises(KinematicsError, match="shape"):
        model.with_parameters(np.zeros(model.n_parameters - 1))
    desc = load_robot("kr500")
    short = desc.with_joints(desc.joints[:5])
    with pytest.raises(KinematicsError, match="joints"):
        model.to_description(short)
