"""Gravity torques: hand-computed cases, a finite-difference energy check, vectorization."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel
from calibration.model.statics import (
    STANDARD_GRAVITY_M_S2,
    MassModel,
    gravity_torques_for,
    gravity_torques_nmm,
    torsion_rad,
)


def potential_energy_nmm(model, masses, q):
    """Σ m g z of every mass (N·mm), base frame; -dV/dq must equal the gravity torque."""
    from calibration.model.kinematics import flange_poses

    q = np.atleast_2d(q)
    energy = np.zeros(q.shape[0])
    n = model.n_joints
    for i in range(n):
        pose = flange_poses(model.truncated(i + 1), q[:, : i + 1], world=False)
        com = pose[:, :3, 3] + pose[:, :3, :3] @ masses.com_mm[i]
        energy += masses.mass_kg[i] * STANDARD_GRAVITY_M_S2 * com[:, 2]
    pose = flange_poses(model, q, world=False)
    tool = pose[:, :3, 3] + pose[:, :3, :3] @ masses.tool_mm
    energy += masses.tool_mass_kg * STANDARD_GRAVITY_M_S2 * tool[:, 2]
    return energy


def test_single_horizontal_link():
    # one joint about z... make the axis horizontal: alpha = 90° puts z_1 along -y of base
    from calibration.model.description import JointDescription, RobotDescription, ToolDescription

    joint = JointDescription(0.0, 90.0, 0.0, 0.0, -180.0, 180.0, mass_kg=10.0, com_mm=(500, 0, 0))
    desc = RobotDescription("bar", (joint,), tool=ToolDescription(0, 0, 0, None))
    tau = gravity_torques_for(desc, np.array([0.0]))
    # 10 kg at 500 mm lever: |tau| = 10 · 9.80665 · 500 N·mm
    assert abs(tau[0]) == pytest.approx(10 * STANDARD_GRAVITY_M_S2 * 500, rel=1e-12)
    # at q = 90° the mass hangs straight below/above the axis: no torque
    tau90 = gravity_torques_for(desc, np.array([np.pi / 2]))
    assert abs(tau90[0]) < 1e-6


def test_matches_energy_gradient_kr500():
    desc = load_robot("kr500")
    model = KinematicModel.from_description(desc)
    masses = MassModel.from_description(desc)
    rng = np.random.default_rng(3)
    q = rng.uniform(-1.0, 1.0, (5, 6))
    tau = gravity_torques_nmm(model, masses, q)
    h = 1e-6
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        grad = (
            potential_energy_nmm(model, masses, q + dq)
            - potential_energy_nmm(model, masses, q - dq)
        ) / (2 * h)
        np.testing.assert_allclose(tau[:, j], -grad, rtol=1e-6, atol=1e-2)


def test_vertical_axis_has_no_gravity_torque_and_shapes():
    desc = load_robot("kr500")
    q = np.zeros((4, 6))
    q[:, 1] = np.linspace(-0.5, 0.5, 4)
    tau = gravity_torques_for(desc, q)
    assert tau.shape == (4, 6)
    np.testing.assert_allclose(tau[:, 0], 0.0, atol=1e-6)  # joint 1 axis is vertical
    single = gravity_torques_for(desc, q[0])
    assert single.shape == (6,)
    np.testing.assert_allclose(single, tau[0])
    # the big joints carry most of the load
    assert abs(tau[1, 1]) > abs(tau[1, 4])


def test_torsion_and_bad_stiffness():
    t = torsion_rad(np.array([[1e7, 2e7]]), np.array([1e10, 2e10]))
    np.testing.assert_allclose(t, [[1e-3, 1e-3]])
    with pytest.raises(ValueError):
        torsion_rad([1.0], [0.0])
