"""The emulator's physical arm: own masses, counterbalance, joint torques, gears.

The torque code is checked against an independent computation (finite differences of the
potential energy, with frames from the shared forward kinematics) and, without a
counterbalance, against the twin's statics (consistency only: the emulator never uses it).
"""

from __future__ import annotations

import tomllib
from dataclasses import replace

import numpy as np
import pytest
import tomli_w

from calibration.model.description import load_robot
from calibration.model.kinematics import flange_poses
from calibration.model.statics import gravity_torques_for
from sim_devices.arm_masses import ArmMasses, generic_masses
from sim_devices.config import CellConfig
from sim_devices.counterbalance import Counterbalance
from sim_devices.effects import UndeclaredEffects, deflection_stiffness_nmm_per_rad
from sim_devices.physical_arm import PhysicalArm
from sim_devices.plant import Plant
from sim_devices.truth import GeometryDeviations, TrueCell, true_description

PRESETS = ("kr500", "kr210_r3100", "hp20d")


def potential_energy_nmm(arm: PhysicalArm, q: np.ndarray) -> np.ndarray:
    """V(q) ``(N,)`` N·mm: the weights' height energy plus the spring's elastic energy."""
    m, g = arm.masses, arm.gravity_m_s2
    v = np.zeros(len(q))
    for i in range(arm.n_joints):
        pose = flange_poses(arm.model.truncated(i + 1), q[:, : i + 1], world=False)
        z = pose[:, 2, 3] + pose[:, 2, :3] @ m.com_mm[i]
        v += m.mass_kg[i] * g * z
        if i == arm.n_joints - 1:
            v += m.payload_kg * g * (pose[:, 2, 3] + pose[:, 2, :3] @ m.payload_com_mm)
    cb = arm.counterbalance
    if cb is not None:
        j = cb.joint - 1
        v += cb.potential_nmm(q[:, j] + arm.model.theta_offset_rad[j])
    return v


@pytest.mark.parametrize("robot", PRESETS)
def test_joint_torques_are_minus_the_gradient_of_the_potential(robot):
    arm = TrueCell.create(load_robot(robot), 3).arm
    assert (arm.counterbalance is not None) == (robot != "hp20d")
    q = arm.range_poses(25)
    h = 1e-6
    tau = arm.joint_torques_nmm(q)
    for j in range(arm.n_joints):
        dq = np.zeros(arm.n_joints)
        dq[j] = h
        grad = (potential_energy_nmm(arm, q + dq) - potential_energy_nmm(arm, q - dq)) / (2 * h)
        scale = np.abs(tau).max()
        np.testing.assert_allclose(tau[:, j], -grad, atol=2e-7 * scale, err_msg=f"joint {j + 1}")


@pytest.mark.parametrize("robot", PRESETS)
def test_weights_agree_with_the_twins_statics_without_counterbalance(robot):
    desc = load_robot(robot)
    arm = PhysicalArm.of_description(desc)
    assert arm.counterbalance is None
    q = arm.range_poses(50)
    expect = gravity_torques_for(desc, q)
    np.testing.assert_allclose(arm.joint_torques_nmm(q), expect, atol=1e-9 * np.abs(expect).max())


def test_masses_are_the_emulators_own_and_leave_earlier_draws_alone():
    nominal = load_robot("kr500")
    cell = TrueCell.create(nominal, 7)
    # the geometry is the first draw of the seed's stream, as before the masses existed
    geometry = true_description(nominal, np.random.default_rng(7), GeometryDeviations())
    assert [j.a_mm for j in cell.truth.joints] == [j.a_mm for j in geometry.joints]
    assert cell.truth.base == geometry.base
    m = cell.arm.masses
    nominal_kg = np.array([j.mass_kg for j in nominal.joints])
    ratio = m.mass_kg / nominal_kg
    assert np.all(ratio >= 0.4) and np.abs(ratio - 1.0).max() > 0.05
    com_shift = m.com_mm - np.array([j.com_mm for j in nominal.joints])
    assert np.all(np.abs(com_shift) > 0) and np.abs(com_shift).max() < 6 * (0.15 * 1325 + 30)
    tool = np.array([cell.truth.tool.x_mm, cell.truth.tool.y_mm, cell.truth.tool.z_mm])
    assert 0 < np.linalg.norm(m.payload_com_mm - tool) < 6 * 40 * np.sqrt(3)
    assert abs(m.payload_kg / nominal.tool.mass_kg - 1.0) < 0.5
    # the truth description carries them; the payload's centre of mass is in the document
    assert [j.mass_kg for j in cell.truth.joints] == m.mass_kg.tolist()
    assert cell.truth.tool.mass_kg == m.payload_kg
    assert [j.mass_kg for j in cell.nominal.joints] == nominal_kg.tolist()
    doc = tomllib.loads(tomli_w.dumps(cell.truth_document()))
    assert doc["physical_arm"]["masses"]["payload_com_mm"] == m.payload_com_mm.tolist()
    assert doc["robot"]["tool"]["mass_kg"] == m.payload_kg
    # a different seed, different masses; the same seed, the same
    assert not np.allclose(TrueCell.create(nominal, 8).arm.masses.mass_kg, m.mass_kg)
    np.testing.assert_array_equal(TrueCell.create(nominal, 7).arm.masses.mass_kg, m.mass_kg)


def test_a_description_without_masses_gets_the_generic_model():
    desc = load_robot("hp20d")
    bare = replace(
        desc,
        joints=tuple(replace(j, mass_kg=None, com_mm=None) for j in desc.joints),
        tool=replace(desc.tool, mass_kg=None),
    )
    generic = generic_masses(bare)
    s = (150 + 760 + 200 + 795) / (500 + 1300 + 55 + 1025)
    np.testing.assert_allclose(generic.mass_kg[1], 480.0 * s**3)
    np.testing.assert_allclose(generic.com_mm[1], np.array([650.0, 0.0, -250.0]) * s)
    base = ArmMasses.of_description(bare)
    np.testing.assert_array_equal(base.mass_kg, generic.mass_kg)
    cell = TrueCell.create(bare, 1)
    assert np.all(cell.arm.masses.mass_kg > 0) and cell.arm.masses.payload_kg > 0


@pytest.mark.parametrize("robot", ["kr500", "kr210_r3100"])
def test_counterbalance_takes_seventy_percent_and_is_not_a_sinusoid(robot):
    arm = TrueCell.create(load_robot(robot), 2).arm
    cb = arm.counterbalance
    assert isinstance(cb, Counterbalance) and cb.joint == 2
    q = arm.range_poses()
    weights = arm.weight_torques_nmm(q)[:, 1]
    total = arm.joint_torques_nmm(q)[:, 1]
    share = 1.0 - np.sqrt(np.mean(total**2) / np.mean(weights**2))
    assert abs(share - 0.7) < 0.01 and abs(arm.counterbalance_share - share) < 1e-12
    theta = np.linspace(arm.lower_rad[1], arm.upper_rad[1], 200) + arm.model.theta_offset_rad[1]
    # force along the spring times its moment arm; the spring stays in tension
    np.testing.assert_allclose(cb.torque_nmm(theta), -cb.force_n(theta) * cb.moment_arm_mm(theta))
    assert cb.free_length_mm > 0 and np.all(cb.length_mm(theta) > cb.free_length_mm)
    # a real free length bends the torque away from a first harmonic of θ2
    tau = cb.torque_nmm(theta)
    basis = np.column_stack([np.sin(theta), np.cos(theta)])
    fit = basis @ np.linalg.lstsq(basis, tau, rcond=None)[0]
    assert np.sqrt(np.mean((tau - fit) ** 2)) > 0.01 * np.sqrt(np.mean(tau**2))
    doc = arm.document()["counterbalance"]
    assert doc["stiffness_n_per_mm"] == cb.stiffness_n_per_mm and doc["free_length_mm"] > 0


def test_deflection_stiffness_follows_the_emulators_torques_not_the_description():
    cell = TrueCell.create(load_robot("kr500"), 4)
    eff = UndeclaredEffects.named("gravity_deflection")
    own = deflection_stiffness_nmm_per_rad(eff, cell.arm)
    q = cell.arm.range_poses()
    rms = np.sqrt(np.mean(cell.arm.joint_torques_nmm(q) ** 2, axis=0))
    np.testing.assert_allclose(own[1:5], rms[1:5] / np.radians(0.005))
    described = deflection_stiffness_nmm_per_rad(eff, cell.nominal)
    assert abs(own[1] / described[1] - 1.0) > 0.2  # the counterbalance unloads joint 2


def test_live_plant_twists_its_gears_under_the_arms_own_load():
    plant = Plant.from_config(CellConfig.loads('[cell]\nprogram = "random"\n'))
    t = np.linspace(0.0, 30.0, 40)
    q_cmd, _, direction = plant.trajectory.evaluate(t)
    corr = plant.output_correction_exact(t)
    tau = plant.cell.arm.joint_torques_nmm(q_cmd)
    eff = plant.config.effects
    w = np.clip(np.abs(tau) / eff.backlash_torque_nmm, 0.0, 1.0)
    side = w * np.sign(tau) + (1.0 - w) * direction
    expect = tau / np.array(eff.stiffness_nmm_per_rad) + 0.5 * np.radians(eff.backlash_deg) * side
    np.testing.assert_allclose(corr, expect, rtol=1e-12, atol=1e-15)
    described = gravity_torques_for(plant.cell.nominal, q_cmd)
    assert np.abs(tau[:, 1] - described[:, 1]).max() > 0.1 * np.abs(described[:, 1]).max()
