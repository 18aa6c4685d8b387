"""The gravity term's sweep reference per joint: each joint's own sweep configuration.

A scale map fitted on joint j's sweep absorbed the swept link's gravity deflection in that
sweep's configuration, so the closed loop's gravity term is relative to it
(``EffectData.sweep_reference``, ``(n,)`` for every joint or ``(n, n)`` one per joint).
The twin reads each sweep's configuration off the sweep stops through its maps
(``calibration.twin.sweep_configuration``); a campaign swept at Home keeps Home exactly.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from calibration.effects.closed_loop import campaign_effect_data
from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec, ModelAtPoses
from calibration.effects.effect_candidates import gravity_candidate
from calibration.effects.effect_kinds import KINDS
from calibration.identify.campaign_files import Campaign
from calibration.model.description import RobotDescription, load_robot
from calibration.model.gravity_regressor import link_rotations
from calibration.model.kinematics import KinematicModel
from calibration.scales.chain_scale import ScaleCampaignResult, calibrate_scales
from calibration.scales.sweep_inputs import JointSweep
from calibration.twin.sweep_configuration import (
    HOME_SNAP_DEG,
    stop_angles_rad,
    sweep_configurations,
)
from sim_devices.pose_campaign import sample_reachable_poses
from sim_devices.scale_campaign import CampaignOptions, ScaleCampaign, run_campaign
from sim_devices.truth import TrueCell

#: a configuration of the other joints away from KR500's Home (deg), inside its limits
AWAY_DEG = np.array([25.0, 30.0, -35.0, 45.0, -40.0, 60.0])


def _jacobian(desc: RobotDescription, spec: EffectSpec, q: np.ndarray, ref: object) -> np.ndarray:
    ctx = EffectContext(desc, EffectData(q, sweep_reference=ref))  # type: ignore[arg-type]
    kin = ModelAtPoses.of(KinematicModel.from_description(desc), q)
    d: np.ndarray = KINDS["gravity_deflection"].deflection_jacobian(spec, ctx, kin)  # type: ignore[attr-defined]
    return d


def _joint_spec(full: EffectSpec, joint: int) -> EffectSpec:
    """The linear gravity term's parameters of one joint alone."""
    names = tuple(n for n in full.names if n.startswith(f"joint{joint}."))
    return replace(full, joints=(joint,), names=names)


@pytest.mark.parametrize("joint", [2, 3, 5, 6])
def test_at_a_sweep_away_from_home_its_own_reference_leaves_nothing_to_model(joint: int) -> None:
    """Poses that are joint j's sweep with the other joints held at a configuration c away
    from Home: j's map absorbed all the deflection seen about axis j there (j's own and
    the upstream links' by ``z_i·z_j``). So with the per-joint reference (row j = c), j's
    relative deflection is exactly what the upstream rows bring back on axis j, and for
    j's parameters alone zero; with Home for every joint it is not (c changes the load on
    j, and for joints 5 and 6 the upstream axes' angles to theirs)."""
    desc = load_robot("kr500")
    home = np.radians(desc.home)
    c = np.radians(AWAY_DEG)
    lo, hi = desc.joints[joint - 1].lower_deg, desc.joints[joint - 1].upper_deg
    q = np.tile(c, (25, 1))
    q[:, joint - 1] = np.radians(np.linspace(lo + 5.0, hi - 5.0, 25))  # the sweep
    full = gravity_candidate(EffectContext(desc, EffectData(q)))
    assert full is not None
    per_joint = np.tile(home, (6, 1))
    per_joint[joint - 1] = c
    z = link_rotations(KinematicModel.from_description(desc), q)[:, :, :, 2]  # (r, n, 3)
    on_axis = np.einsum("ria,ra->ri", z[:, :joint], z[:, joint - 1])  # z_i·z_j, i ≤ j
    for spec in (_joint_spec(full, joint), full):
        plain = _jacobian(desc, spec, q, None)
        seen = np.einsum("ri,rip->rp", on_axis, plain[:, :joint])  # about axis j
        size = np.max(np.abs(seen))
        assert size > 0.1  # µrad per unit: the term loads axis j here
        own = _jacobian(desc, spec, q, per_joint)[:, joint - 1]
        at_home = _jacobian(desc, spec, q, home)[:, joint - 1]
        np.testing.assert_allclose(own + seen - plain[:, joint - 1], 0.0, atol=1e-9 * size)
        if spec is not full:  # j's own parameters: nothing left
            assert np.max(np.abs(own)) <= 1e-9 * size
        off = at_home + seen - plain[:, joint - 1]
        assert np.sqrt(np.mean(off**2)) > 0.05 * np.sqrt(np.mean(seen**2)), spec.names


def test_home_in_every_row_is_the_single_home_reference_exactly() -> None:
    """``(n, n)`` with every row Home gives the ``(n,)`` Home result bit for bit, and a
    row away from Home changes only its own joint's row."""
    desc = load_robot("kr500")
    q = sample_reachable_poses(desc, 30, np.random.default_rng(4))
    spec = gravity_candidate(EffectContext(desc, EffectData(q)))
    assert spec is not None
    home = np.radians(desc.home)
    single = _jacobian(desc, spec, q, home)
    np.testing.assert_array_equal(_jacobian(desc, spec, q, np.tile(home, (6, 1))), single)
    rows = np.tile(home, (6, 1))
    rows[2] = np.radians(AWAY_DEG)
    moved = _jacobian(desc, spec, q, rows)
    np.testing.assert_array_equal(np.delete(moved, 2, axis=1), np.delete(single, 2, axis=1))
    assert np.max(np.abs(moved[:, 2] - single[:, 2])) > 1e-3 * np.max(np.abs(single[:, 2]))


def test_the_loop_data_carry_the_configurations_only_when_sweep_referenced() -> None:
    desc = load_robot("kr500")
    q_deg = np.array([[0.0, 10, -20, 0, 30, 0], [5, 20, -10, 10, 20, 5]])
    camp = Campaign("test", ("p1", "p2"), ("identify", "validate"), np.array([0.0, 1.0]),
                    q_deg, np.zeros((2, 3)))  # fmt: skip
    configs = np.tile(np.radians(AWAY_DEG), (6, 1))
    plain = campaign_effect_data(desc, camp, sweep_configurations=configs)
    assert plain.sweep_reference is None
    at_home = campaign_effect_data(desc, camp, sweep_referenced=True)
    np.testing.assert_array_equal(at_home.sweep_reference, np.radians(desc.home))
    per_joint = campaign_effect_data(
        desc, camp, sweep_referenced=True, sweep_configurations=configs
    )
    np.testing.assert_array_equal(per_joint.sweep_reference, configs)
    with pytest.raises(ValueError, match="sweep_configurations"):
        campaign_effect_data(desc, camp, sweep_referenced=True, sweep_configurations=configs[:3])


@cache
def _scale_campaign() -> tuple[ScaleCampaign, ScaleCampaignResult]:
    """An emulated KR500 scale campaign (every sweep at Home; gear torsion and backlash
    turn the held joints by up to ~30″) and the twin's maps from it."""
    desc = load_robot("kr500")
    camp = run_campaign(
        TrueCell.create(desc, 1, eccentricity_mm=0.002),
        CampaignOptions(torsion=True, backlash=True),
    )
    limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
    scales = calibrate_scales(
        camp.joint_sweeps(), camp.home_readings(), home_deg=desc.home, limits_deg=limits
    )
    return camp, scales


def test_sweeps_at_home_give_home_exactly() -> None:
    """The joints held at Home read off it by tens of arc-seconds (the load on their
    gears), within :data:`HOME_SNAP_DEG`: every row is Home, bit for bit."""
    desc = load_robot("kr500")
    camp, scales = _scale_campaign()
    home = np.radians(desc.home)
    off = [
        np.delete(np.median(stop_angles_rad(desc, scales, s), axis=0) - home, j - 1)
        for j, s in camp.joint_sweeps().items()
    ]
    worst_deg = float(np.degrees(np.max(np.abs(off))))
    assert 10.0 / 3600 < worst_deg < HOME_SNAP_DEG  # 26″ (seed 1)
    configs = sweep_configurations(desc, camp.joint_sweeps(), scales)
    np.testing.assert_array_equal(configs, np.tile(home, (6, 1)))


def test_sweeps_held_away_from_home_give_their_configuration() -> None:
    """Every sweep's other joints held at :data:`AWAY_DEG` (joint 5 only 0.02° off Home,
    within :data:`HOME_SNAP_DEG`): their readings the emulator's strips at those angles
    with the campaign's stop jitter, read through the twin's maps. Each row is the held
    configuration within 0.01°, joint 5 exactly Home; the swept joint's own entry Home."""
    desc = load_robot("kr500")
    camp, scales = _scale_campaign()
    held = AWAY_DEG.copy()
    held[4] = 0.02
    assert held[4] < HOME_SNAP_DEG
    rng = np.random.default_rng(7)
    sweeps: dict[int, JointSweep] = {}
    for j, sweep in camp.joint_sweeps().items():
        assert sweep.chain_counts is not None
        counts = sweep.chain_counts.copy()
        for i in range(6):
            if i != j - 1:
                angle = held[i] + rng.normal(0.0, 0.005, len(counts))
                counts[:, i] = np.round(camp.truth(i + 1).counts_at(angle)).astype(counts.dtype)
        sweeps[j] = replace(sweep, chain_counts=counts)
    configs = np.degrees(sweep_configurations(desc, sweeps, scales))
    for j in range(6):
        expected = np.where(np.isin(np.arange(6), (j, 4)), 0.0, held)
        np.testing.assert_allclose(configs[j], expected, atol=0.01, rtol=0.0)
        assert configs[j, 4] == 0.0 and configs[j, j] == 0.0
