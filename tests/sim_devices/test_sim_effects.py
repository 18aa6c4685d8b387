"""The emulator's undeclared effects (sim_devices.effects): physics, generator, truth file."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from calibration.identify.campaign_files import read_campaign
from calibration.model.description import load_robot
from calibration.model.kinematics import geometric_jacobian
from sim_devices import pose_campaign
from sim_devices.effects import (
    EFFECT_NAMES,
    UndeclaredEffects,
    approach_direction,
    deflection_stiffness_nmm_per_rad,
    grating_reading_rad,
    length_changes,
    length_drift_mm,
    length_lag_mm,
    link_rotation_rad,
    tracker_reading_mm,
)
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign

SMALL = dict(n_identify=30, n_validate=20, selection=None)


@pytest.fixture(scope="module")
def clean():
    return emulated_campaign("kr500", 5, CampaignSettings(**SMALL))


def _with(*names, **over):
    return emulated_campaign(
        "kr500", 5, CampaignSettings(**SMALL, effects=UndeclaredEffects.named(*names, **over))
    )


def test_off_by_default_and_same_draws(clean):
    assert UndeclaredEffects().active == ()
    again = _with()
    np.testing.assert_array_equal(again.campaign.xyz_mm, clean.campaign.xyz_mm)
    np.testing.assert_array_equal(again.campaign.q_deg, clean.campaign.q_deg)
    np.testing.assert_array_equal(clean.true_prediction_mm, clean.tcp_true_mm)
    with pytest.raises(ValueError, match="unknown effect 'sag'"):
        UndeclaredEffects.named("sag")


def test_gravity_deflection_moves_the_tcp_not_the_gratings(clean):
    data = _with("gravity_deflection")
    np.testing.assert_array_equal(data.campaign.q_deg, clean.campaign.q_deg)
    shift = data.campaign.xyz_mm - clean.campaign.xyz_mm
    np.testing.assert_allclose(shift, data.tcp_true_mm - clean.tcp_true_mm, atol=1e-12)
    ap = np.linalg.norm(shift, axis=1)
    assert 0.1 < np.sqrt(np.mean(ap**2)) < 0.8  # tenths of a mm for a KR500
    # first order: the TCP moves by J · tau/K, tau the emulator's own (masses, counterbalance)
    arm = data.cell.arm
    k = deflection_stiffness_nmm_per_rad(data.effects, arm)
    assert np.isinf(k[0]) and np.isinf(k[5])  # vertical axis and flange carry ~no torque
    assert 1e10 < k[1] < 2e11 and 3e9 < k[2] < 1e11
    dq = arm.joint_torques_nmm(data.q_true_rad) / k
    np.testing.assert_allclose(dq, link_rotation_rad(data.effects, arm, data.q_true_rad))
    jac = geometric_jacobian(arm.model, data.q_true_rad, frame="world")
    lin = np.einsum("pij,pj->pi", jac[:, :3], dq)
    assert np.max(np.abs(lin - shift)) < 0.01 * np.max(np.abs(shift)) + 1e-9


def test_cyclic_grating_error_changes_the_readings_only(clean):
    data = _with("grating_cyclic", cyclic_joint=2, cyclic_order=3, cyclic_phase_deg=10.0)
    np.testing.assert_array_equal(data.campaign.xyz_mm, clean.campaign.xyz_mm)
    q2 = data.q_true_rad[:, 1]
    expect = 0.004 * np.sin(3 * q2 + np.radians(10.0))
    got = data.campaign.q_deg[:, 1] - clean.campaign.q_deg[:, 1]
    np.testing.assert_allclose(got, expect, atol=1e-9)
    assert np.all(
        data.campaign.q_deg[:, [0, 2, 3, 4, 5]] == clean.campaign.q_deg[:, [0, 2, 3, 4, 5]]
    )
    np.testing.assert_array_equal(
        grating_reading_rad(UndeclaredEffects(), q2[:, None]), q2[:, None]
    )


def test_thermal_drift_grows_along_the_link(clean):
    data = _with("thermal_drift")
    t = data.campaign.t_s
    growth = length_drift_mm(data.effects, t)
    np.testing.assert_allclose(growth, 0.15 * t / 3600.0)
    shift = data.tcp_true_mm - clean.tcp_true_mm
    np.testing.assert_allclose(np.linalg.norm(shift, axis=1), growth, atol=1e-9)  # a2: a length
    expo = UndeclaredEffects.named("thermal_drift", drift_time_constant_s=1800.0)
    g = length_drift_mm(expo, np.array([0.0, 1.0, 1e6]))
    np.testing.assert_allclose(g, [0.0, 0.15 / 3600.0, 0.15 / 2.0], rtol=1e-3)


def test_thermal_lag_approaches_its_final_growth(clean, tmp_path):
    data = _with("thermal_lag")
    t = data.campaign.t_s
    growth = length_lag_mm(data.effects, t)
    np.testing.assert_allclose(growth, 0.15 * (1.0 - np.exp(-t / 900.0)))
    shift = data.tcp_true_mm - clean.tcp_true_mm
    np.testing.assert_allclose(np.linalg.norm(shift, axis=1), growth, atol=1e-9)  # a2: a length
    assert 0.0 < growth[-1] < 0.15 * t[-1] / 900.0  # below its initial slope: it bends
    assert length_drift_mm(data.effects, t).max() == 0.0  # drift stays its own effect
    both = _with("thermal_lag", "thermal_drift", lag_joint=3, lag_parameter="a")
    assert len(length_changes(both.effects, t)) == 2
    truth = tmp_path / "truth.toml"
    args = ["--robot", "kr500", "--seed", "5", "--out", str(tmp_path / "c.csv")]
    args += ["--identify", "10", "--validate", "5", "--selection", "none"]
    rc = pose_campaign.main([*args, "--effect", "thermal_lag", "--truth", str(truth)])
    assert rc == 0
    eff = tomllib.loads(truth.read_text())["undeclared_effects"]
    assert eff["thermal_lag"] and not eff["thermal_drift"]
    assert (eff["lag_mm"], eff["lag_time_constant_s"], eff["lag_joint"]) == (0.15, 900.0, 2)


def test_tracker_scale_is_about_the_tracker(clean):
    data = _with("tracker_scale", tracker_scale_drift_ppm_per_h=36.0)
    t = data.campaign.t_s
    np.testing.assert_array_equal(data.tcp_true_mm, clean.tcp_true_mm)  # the robot is as it was
    ppm = 20.0 + 36.0 * t / 3600.0
    np.testing.assert_allclose(
        data.true_prediction_mm, clean.tcp_true_mm * (1 + 1e-6 * ppm)[:, None]
    )
    shift = data.campaign.xyz_mm - clean.campaign.xyz_mm
    np.testing.assert_allclose(shift, data.true_prediction_mm - clean.tcp_true_mm, atol=1e-12)
    pts = np.array([[1000.0, 0.0, 0.0]])
    assert tracker_reading_mm(UndeclaredEffects(), pts, [0.0])[0, 0] == 1000.0


def test_lost_motion_follows_the_approach_direction(clean):
    data = _with("lost_motion")
    q = data.q_true_rad
    direction = approach_direction(q)
    np.testing.assert_array_equal(direction[0], np.sign(q[0]))
    rot = link_rotation_rad(data.effects, data.cell.arm, q, direction)
    np.testing.assert_allclose(rot[:, 1], np.radians(0.003) * direction[:, 1])
    assert np.all(rot[:, 0] == 0.0)
    assert np.linalg.norm(data.tcp_true_mm - clean.tcp_true_mm, axis=1).max() > 0.05


def test_generator_command_writes_effects_into_the_truth(tmp_path):
    out, truth = tmp_path / "c.csv", tmp_path / "truth.toml"
    args = ["--robot", "hp20d", "--seed", "2", "--out", str(out), "--truth", str(truth)]
    rc = pose_campaign.main(
        [
            *args,
            "--identify",
            "20",
            "--validate",
            "5",
            "--selection",
            "none",
            "--effect",
            "gravity_deflection",
            "--effect",
            "thermal_drift",
        ]
    )
    assert rc == 0
    doc = tomllib.loads(truth.read_text())
    eff = doc["undeclared_effects"]
    assert eff["gravity_deflection"] and eff["thermal_drift"] and not eff["tracker_scale"]
    assert eff["drift_mm_per_h"] == 0.15 and len(eff["derived_stiffness_nmm_per_rad"]) == 6
    assert eff["derived_stiffness_nmm_per_rad"][0] == 0.0  # rigid
    assert set(EFFECT_NAMES) <= set(eff)
    desc = load_robot("hp20d")
    camp = read_campaign(out, 6, limits_deg=[(j.lower_deg, j.upper_deg) for j in desc.joints])
    assert len(camp) == 25


def test_live_plant_shares_the_physics():
    """The live cell's plant applies the same effects as the campaign generator."""
    from sim_devices.config import CellConfig, check_for_robot
    from sim_devices.errors import SimConfigError
    from sim_devices.plant import Plant, SimClock

    text = (
        '[cell]\nprogram = "hold"\n[effects]\ntorsion = false\nbacklash = false\n'
        "[effects.undeclared]\ngravity_deflection = true\ngrating_cyclic = true\n"
        "thermal_drift = true\nthermal_lag = true\ntracker_scale = true\n"
    )
    cfg = CellConfig.loads(text)
    assert CellConfig.loads(cfg.dumps()) == cfg
    plant = Plant.from_config(cfg, SimClock(speed=1.0, t0_monotonic=0.0))
    off = Plant.from_config(CellConfig.loads(text.split("[effects.undeclared]")[0]))
    eff = cfg.effects.undeclared
    arm = plant.cell.arm
    q = np.radians([[10.0, 20.0, -30.0, 40.0, 50.0, 60.0], [0.0, 60.0, -60.0, 0.0, 30.0, 0.0]])
    t = np.array([0.0, 1800.0])
    from sim_devices.effects import true_tcp_mm

    np.testing.assert_allclose(plant.target_mm(q, t), true_tcp_mm(eff, arm, q, t), atol=1e-9)
    moved = plant.target_mm(q, t) - off.target_mm(q, t)
    assert 0.05 < np.abs(moved).max() < 2.0
    rng = np.random.default_rng(0)
    counts = plant.grating_counts(q, rng, 0.0) - off.grating_counts(q, rng, 0.0)
    strip = plant.cell.strips[0]
    expect = strip.ideal_counts(grating_reading_rad(eff, q)[:, 0]) - strip.ideal_counts(q[:, 0])
    np.testing.assert_allclose(counts[:, 0], np.rint(expect), atol=1.0)
    assert np.all(counts[:, 1:] == 0)
    assert plant.cell.tracker.scale_error_ppm == eff.tracker_scale_ppm
    k = plant.truth_document()["plant"]["deflection_stiffness_nmm_per_rad"]
    assert k[0] == 0.0 and 1e10 < k[1] < 2e11
    for bad in (
        "lost_motion = true",
        "drift_parameter = 'b'",
        "lag_parameter = 'alpha'",
        "lag_joint = 7",
        "lag_time_constant_s = 0.0",
        "tracker_scale_drift_ppm_per_h = 1.0",
    ):
        with pytest.raises(SimConfigError, match="undeclared"):
            # joint numbers are checked against the robot once it is known
            check_for_robot(CellConfig.loads(text + bad + "\n"), 6, "<string>")
