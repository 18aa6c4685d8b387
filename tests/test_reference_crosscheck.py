"""Forward kinematics and geometric Jacobian against roboticstoolbox-python (test-only).

The reference is built from rtb's elementary transforms, per link
``Rx(alpha)·tx(a)·Ry(beta)·Rz(offset)·Rz(q)·tz(d)``, with the base pose in front and the
tool translation behind. Tolerances are absolute: 1e-9 mm for positions and mm/rad Jacobian
rows (values up to ~4000 mm, so ~2.5e-13 relative), 1e-9 for rotation-matrix elements and
angular rows; the observed differences are ~1e-12.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.model.description import load_robot
from calibration.model.kinematics import (
    KinematicModel,
    flange_poses,
    geometric_jacobian,
    tcp_positions,
)

rtb = pytest.importorskip("roboticstoolbox")  # slow import: once per module
ET = rtb.ET

PRESETS = ("kr500", "kr210_r3100", "hp20d")
TOL = 1e-9


def reference_ets(model: KinematicModel, *, world: bool, tcp: bool):
    """rtb ETS of the model; ``world`` puts the base pose in front, ``tcp`` the tool behind."""
    ets = ET.tx(0.0)  # neutral start so that products below are always ETS
    if world:
        (x, y, z), (rx, ry, rz) = model.base_mm, model.base_rad
        ets = ET.tx(x) * ET.ty(y) * ET.tz(z) * ET.Rz(rz) * ET.Ry(ry) * ET.Rx(rx)
    for i in range(model.n_joints):
        # Multiply one ET at a time: rtb numbers joints as they are appended, whereas a
        # parenthesized per-link ETS would give every joint index 0.
        ets = ets * ET.Rx(model.alpha_rad[i]) * ET.tx(model.a_mm[i]) * ET.Ry(model.beta_rad[i])
        ets = ets * ET.Rz(model.theta_offset_rad[i]) * ET.Rz() * ET.tz(model.d_mm[i])
    if tcp:
        ets = ets * ET.tx(model.tool_mm[0]) * ET.ty(model.tool_mm[1]) * ET.tz(model.tool_mm[2])
    assert [et.jindex for et in ets if et.isjoint] == list(range(model.n_joints))
    return ets


def with_betas(model: KinematicModel, seed: int) -> KinematicModel:
    """Nonzero beta on every joint, a tilted base and other small deviations."""
    rng = np.random.default_rng(seed)
    x = model.parameter_vector().copy()
    per_joint = x[:30].reshape(6, 5)
    per_joint[:, 4] = rng.uniform(-0.05, 0.05, 6)
    per_joint[:, [0, 2]] += rng.normal(0.0, 1.0, (6, 2))
    per_joint[:, [1, 3]] += rng.normal(0.0, 0.01, (6, 2))
    x[33:36] += rng.uniform(-0.3, 0.3, 3)
    return model.with_parameters(x)


MODELS = {
    f"{name}-{kind}": (
        KinematicModel.from_description(load_robot(name))
        if kind == "nominal"
        else with_betas(KinematicModel.from_description(load_robot(name)), seed=i)
    )
    for i, name in enumerate(PRESETS)
    for kind in ("nominal", "beta")
}


@pytest.fixture(scope="module")
def joints() -> np.ndarray:
    return np.random.default_rng(42).uniform(-np.pi, np.pi, (25, 6))


@pytest.mark.parametrize("key", sorted(MODELS))
def test_forward_kinematics_matches_rtb(key, joints):
    model = MODELS[key]
    full = np.array(reference_ets(model, world=True, tcp=True).fkine(joints).A)
    bare = np.array(reference_ets(model, world=False, tcp=False).fkine(joints).A)
    np.testing.assert_allclose(tcp_positions(model, joints), full[:, :3, 3], rtol=0, atol=TOL)
    np.testing.assert_allclose(flange_poses(model, joints)[:, :3, :3], full[:, :3, :3], atol=TOL)
    np.testing.assert_allclose(flange_poses(model, joints, world=False), bare, rtol=0, atol=TOL)


@pytest.mark.parametrize("key", sorted(MODELS))
def test_geometric_jacobian_matches_rtb(key, joints):
    model = MODELS[key]
    full = reference_ets(model, world=True, tcp=True)
    bare = reference_ets(model, world=False, tcp=False)
    want_full = np.stack([full.jacob0(q) for q in joints])
    want_bare = np.stack([bare.jacob0(q) for q in joints])
    got_full = geometric_jacobian(model, joints, point="tcp", frame="world")
    got_bare = geometric_jacobian(model, joints, point="flange", frame="base")
    np.testing.assert_allclose(got_full, want_full, rtol=0, atol=TOL)
    np.testing.assert_allclose(got_bare, want_bare, rtol=0, atol=TOL)
