"""The emulator's coupled compliance of joints 2 and 3 (``joint_coupling``): a symmetric,
positive-definite cross term of the gravity deflection's compliance matrix, off by
default, declared in ``[effects.undeclared]``."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.model.description import load_robot
from sim_devices.config import CellConfig, check_for_robot
from sim_devices.effects import (
    UndeclaredEffects,
    coupling_compliance_rad_per_nmm,
    deflection_stiffness_nmm_per_rad,
    effects_document,
    link_rotation_rad,
    true_tcp_mm,
)
from sim_devices.errors import SimConfigError
from sim_devices.physical_arm import PhysicalArm
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign, sample_reachable_poses
from sim_devices.truth import TrueCell

DESC = load_robot("kr500")
Q = sample_reachable_poses(DESC, 20, np.random.default_rng(8))


def test_off_by_default_and_the_campaign_unchanged() -> None:
    """The default settings have no coupling; a campaign with the gravity deflection is
    the same to the bit whether the coupling's other settings are touched or not."""
    assert not UndeclaredEffects().joint_coupling
    assert "joint_coupling" not in UndeclaredEffects.named("gravity_deflection").active
    plain = CampaignSettings(effects=UndeclaredEffects.named("gravity_deflection"))
    touched = CampaignSettings(
        effects=UndeclaredEffects.named("gravity_deflection", coupling_coefficient=-0.7)
    )
    a = emulated_campaign("hp20d", 2, plain)
    b = emulated_campaign("hp20d", 2, touched)
    assert np.array_equal(a.campaign.xyz_mm, b.campaign.xyz_mm)


def test_cross_term_is_symmetric_and_positive_definite() -> None:
    """Joint 2 turns by c23·τ3 more, joint 3 by c23·τ2, nothing else moves; c23 =
    ρ/√(K2·K3), so the 2×2 compliance block is positive definite for |ρ| < 1."""
    arm = TrueCell.create(DESC, 3).arm
    plain = UndeclaredEffects.named("gravity_deflection")
    k_plain = deflection_stiffness_nmm_per_rad(plain, arm)
    # without the coupling the deflection is the diagonal one, to the bit
    np.testing.assert_array_equal(
        link_rotation_rad(plain, arm, Q), arm.joint_torques_nmm(Q) / k_plain
    )
    for rho in (0.5, -0.8):
        coupled = UndeclaredEffects.named("joint_coupling", coupling_coefficient=rho)
        assert coupled.gravity_deflection  # the coupling is a part of the deflection
        k = deflection_stiffness_nmm_per_rad(coupled, arm)
        c23 = coupling_compliance_rad_per_nmm(coupled, arm)
        assert c23 == pytest.approx(rho / np.sqrt(k[1] * k[2]), rel=1e-12)
        block = np.array([[1 / k[1], c23], [c23, 1 / k[2]]])
        assert np.all(np.linalg.eigvalsh(block) > 0.0)
        extra = link_rotation_rad(coupled, arm, Q) - link_rotation_rad(plain, arm, Q)
        tau = arm.joint_torques_nmm(Q)
        np.testing.assert_allclose(extra[:, 1], c23 * tau[:, 2], rtol=1e-9, atol=1e-18)
        np.testing.assert_allclose(extra[:, 2], c23 * tau[:, 1], rtol=1e-9, atol=1e-18)
        assert np.all(extra[:, [0, 3, 4, 5]] == 0.0)
        moved = true_tcp_mm(coupled, arm, Q, 0.0) - true_tcp_mm(plain, arm, Q, 0.0)
        assert 0.01 < float(np.max(np.linalg.norm(moved, axis=1))) < 1.0
    doc = effects_document(UndeclaredEffects.named("joint_coupling"), arm)
    assert doc["joint_coupling"] and doc["derived_coupling_compliance_rad_per_nmm"] > 0.0
    with pytest.raises(ValueError, match="coupling_coefficient"):
        coupling_compliance_rad_per_nmm(
            UndeclaredEffects.named("joint_coupling", coupling_coefficient=1.0), arm
        )


def test_a_rigid_joint_has_no_coupling() -> None:
    arm = PhysicalArm.of_description(DESC)
    stiff = (np.inf, 1e11, np.inf, 1e9, 1e9, np.inf)
    eff = UndeclaredEffects.named("joint_coupling", deflection_stiffness_nmm_per_rad=stiff)
    assert coupling_compliance_rad_per_nmm(eff, arm) == 0.0


def test_cell_toml_key_and_its_checks() -> None:
    """``joint_coupling = true`` in ``[effects.undeclared]`` with the gravity deflection;
    alone, with |ρ| ≥ 1 or with a joint the robot lacks it is refused naming the key."""
    head = '[cell]\nprogram = "hold"\n[effects.undeclared]\n'
    cfg = CellConfig.loads(head + "gravity_deflection = true\njoint_coupling = true\n")
    assert cfg.effects.undeclared.joint_coupling
    assert CellConfig.loads(cfg.dumps()) == cfg
    for bad, key in (
        ("joint_coupling = true", "joint_coupling"),
        (
            "gravity_deflection = true\njoint_coupling = true\ncoupling_coefficient = 1.0",
            "coupling_coefficient",
        ),
        ("coupling_joints = [2, 2]", "coupling_joints"),
        ("coupling_joints = [2, 9]", "coupling_joints"),
    ):
        with pytest.raises(SimConfigError, match=key):
            check_for_robot(CellConfig.loads(head + bad + "\n"), 6, "<string>")
