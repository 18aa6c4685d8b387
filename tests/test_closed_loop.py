"""The closed loop on emulated campaigns with an effect nobody told the twin about.

For each undeclared effect (sim_devices.effects), presets KR500 and HP20D, seeds 1 and 3:
the right effect (or, for the tracker scale, "not identifiable") is named, its parameters
match the truth, and the validation mean AP after the loop is within 1.3× of the true
model's on the same data. Clean data: nothing is added. The generic search names structure
the (restricted) library cannot explain.

Seeds are fixed; the slow sweeps (many seeds) give the rates behind them. The thermal drift
is the fragile case: the validation poses are measured after the identification poses, so
the drift rate (standard error ≈ 0.015 mm/h) is extrapolated by up to 0.6 h; the slow sweep
has 2 of 30 campaigns above 1.3× (HP20D seed 2: 1.301, KR210 seed 4: 1.313; see
docs/closed-loop.md).
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from calibration.closed_loop import LoopSettings, run_closed_loop
from calibration.description import RobotDescription
from calibration.effect_library import KINDS, EffectSpec
from calibration.model_effects import predict_tcp
from sim_devices.effects import UndeclaredEffects, deflection_stiffness_nmm_per_rad
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign

PRESETS = ("kr500", "hp20d")
SEEDS = (1, 3)


@cache
def campaign(robot: str, seed: int, effect: str | None, **over):
    eff = UndeclaredEffects.named(effect, **over) if effect else UndeclaredEffects()
    return emulated_campaign(robot, seed, CampaignSettings(effects=eff))


@cache
def loop(robot: str, seed: int, effect: str | None, kinds: tuple[str, ...] | None = None):
    data = campaign(robot, seed, effect)
    return data, run_closed_loop(data.cell.nominal, data.campaign, kinds=kinds)


def validation_ratio(data, result) -> float:
    vm = data.campaign.mask("validate")
    true = np.linalg.norm(data.campaign.xyz_mm[vm] - data.true_prediction_mm[vm], axis=1)
    after = np.linalg.norm(result.final.errors_mm["validate"], axis=1)
    return float(after.mean() / true.mean())


def mean_ap(stage, set_name="validate") -> float:
    return float(np.linalg.norm(stage.errors_mm[set_name], axis=1).mean())


CASES = [(r, s) for r in PRESETS for s in SEEDS]
IDS = [f"{r}-{s}" for r, s in CASES]


@pytest.mark.parametrize(("robot", "seed"), CASES, ids=IDS)
def test_gravity_deflection_is_named_and_modelled(robot, seed):
    data, res = loop(robot, seed, "gravity_deflection")
    assert [s.kind for s in res.added] == ["gravity_compliance"]
    spec = res.added[0]
    k = deflection_stiffness_nmm_per_rad(data.effects, data.cell.truth)
    values = res.final.values_of(spec)
    se = res.final.standard_errors_of(spec)
    for j in (2, 3):  # the main axes: compliance 1/K in µrad/(kN·m)
        i = spec.joints.index(j)
        assert abs(values[i] - 1e12 / k[j - 1]) < 5 * se[i] + 0.05 * 1e12 / k[j - 1]
    assert mean_ap(res.geometric) > 3 * mean_ap(res.final)
    assert validation_ratio(data, res) <= 1.3


@pytest.mark.parametrize(("robot", "seed"), CASES, ids=IDS)
def test_cyclic_grating_error_is_named_and_modelled(robot, seed):
    data, res = loop(robot, seed, "grating_cyclic")
    assert res.added == (EffectSpec("joint_harmonic", joint=1, order=2),)
    # reading = q + A sin(2q + 30°): the twin's correction is -A sin(2q + 30°)
    a = data.effects.cyclic_amplitude_deg
    truth = -a * np.array([np.sin(np.radians(30.0)), np.cos(np.radians(30.0))])
    values = res.final.values_of(res.added[0])
    assert np.all(np.abs(values - truth) < 5 * res.final.standard_errors_of(res.added[0]))
    assert validation_ratio(data, res) <= 1.3


@pytest.mark.parametrize(("robot", "seed"), CASES, ids=IDS)
def test_thermal_drift_is_named_and_modelled(robot, seed):
    data, res = loop(robot, seed, "thermal_drift")
    assert res.added == (EffectSpec("length_drift", joint=2, parameter="a"),)
    rate = res.final.values_of(res.added[0])[0]
    se = res.final.standard_errors_of(res.added[0])[0]
    assert abs(rate - data.effects.drift_mm_per_h) < 4 * se
    assert validation_ratio(data, res) <= 1.3


@pytest.mark.parametrize(("robot", "seed"), CASES, ids=IDS)
def test_constant_tracker_scale_is_absorbed_and_said_to_be(robot, seed):
    """A distance-proportional scale about the tracker is a uniform scaling of every length
    and the base position: the geometry absorbs it exactly. The loop says the tracker
    scale is not identifiable, adds nothing, and the error stays at the true model's."""
    for ppm in (10.0, 30.0):
        data = campaign(robot, seed, "tracker_scale", tracker_scale_ppm=ppm)
        res = run_closed_loop(data.cell.nominal, data.campaign)
        assert res.added == ()
        scale = next(c for c in res.last_round if c.spec.kind == "instrument_scale")
        assert scale.n_parameters == 0 and "combination of the parameters" in scale.note
        assert validation_ratio(data, res) <= 1.3
        clean = loop(robot, seed, None)[1]
        # a3 scaled by the tracker (through the geometry alone): same residuals as clean
        assert abs(mean_ap(res.final) - mean_ap(clean.final)) < 0.02 * mean_ap(clean.final)


@pytest.mark.parametrize(("robot", "seed"), CASES, ids=IDS)
def test_clean_data_adds_nothing(robot, seed):
    data, res = loop(robot, seed, None)
    assert res.added == ()
    assert len(res.stages) == 2 and res.last_round
    assert all(not c.significant for c in res.last_round)
    assert validation_ratio(data, res) <= 1.15


@pytest.mark.parametrize("robot", PRESETS)
def test_generic_search_names_structure_outside_the_library(robot):
    """With the cyclic error (or the link drift) left out of the library, the generic search
    names the variable the structure depends on, and models it."""
    no_harmonic = tuple(k for k in KINDS if k != "joint_harmonic")
    data, res = loop(robot, 1, "grating_cyclic", no_harmonic)
    assert res.added == (EffectSpec("link_harmonic", joint=1, order=2),)
    assert res.final.label == "+ unexplained structure in q1 (harmonic 2, link 1 turning)"
    values = res.final.values_of(res.added[0])  # (x, y, z) cos, then sin: about z
    assert np.all(np.abs(values[[0, 1, 3, 4]]) < 0.2 * np.abs(values[[2, 5]]).min())
    assert validation_ratio(data, res) <= 1.3
    # translations in the tracker frame alone: what they find depends on q1 (on KR500 two
    # harmonics; on HP20D nothing is significant: the lever changes from pose to pose)
    cartesian = tuple(k for k in no_harmonic if k != "link_harmonic")
    data, res = loop(robot, 1, "grating_cyclic", cartesian)
    assert all(s.kind == "cartesian_harmonic" and s.joint == 1 for s in res.added)
    assert bool(res.added) == (robot == "kr500")
    no_drift = tuple(k for k in KINDS if k != "length_drift")
    data, res = loop(robot, 1, "thermal_drift", no_drift)
    assert res.added == (EffectSpec("cartesian_time", joint=1, order=1),)
    assert "unexplained structure in time" in res.final.label
    rate = res.final.values_of(res.added[0])
    assert abs(rate[0] - 0.15) < 0.05 and np.hypot(rate[1], rate[2]) < 0.05  # along x1: a2
    assert validation_ratio(data, res) <= 1.3


def test_stages_evidence_and_predict_round_trip(tmp_path):
    data, res = loop("kr500", 1, "grating_cyclic")
    names = [s.name for s in res.stages]
    assert names == ["nominal", "geometric", "effect"]
    aps = [mean_ap(s) for s in res.stages]
    assert aps[0] > 10 * aps[1] and aps[1] > 2 * aps[2]
    stage = res.final
    assert stage.added is not None and stage.added.significant
    assert stage.round_scores[0] is stage.added
    ev = stage.evidence
    assert ev is not None and "joint 1" in ev.x_label
    # the residual in the effect's coordinate follows the model before, not after
    ok = np.isfinite(ev.before)
    assert np.corrcoef(ev.before[ok], ev.model[ok])[0, 1] > 0.8
    assert np.corrcoef(ev.partial[ok], ev.model[ok])[0, 1] > 0.8
    assert np.std(ev.after[ok]) < 0.5 * np.std(ev.before[ok])
    # the calibrated description predicts what the loop evaluated
    desc = res.calibrated_description(data.cell.nominal)
    path = tmp_path / "calibrated.toml"
    desc.save(path)
    back = RobotDescription.load(path)
    assert [e.kind for e in back.effects] == ["joint_harmonic"]
    vm = data.campaign.mask("validate")
    pred = predict_tcp(back, data.campaign.q_rad[vm], data.campaign.t_s[vm])
    np.testing.assert_allclose(
        data.campaign.xyz_mm[vm] - pred, stage.errors_mm["validate"], atol=1e-9
    )


def test_settings_are_checked_and_max_effects_stops():
    with pytest.raises(ValueError, match="folds"):
        LoopSettings(folds=1)
    with pytest.raises(ValueError, match="unknown effect kind"):
        LoopSettings(kinds=("sag",))
    data = campaign("kr500", 1, "lost_motion")
    res = run_closed_loop(data.cell.nominal, data.campaign, settings=LoopSettings(max_effects=1))
    assert len(res.added) == 1 and res.added[0].kind == "lost_motion"
    full = run_closed_loop(data.cell.nominal, data.campaign)
    assert {(s.kind, s.joint) for s in full.added} == {("lost_motion", 2), ("lost_motion", 3)}
    assert validation_ratio(data, full) <= 1.3


# -- slow sweeps -----------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("robot", PRESETS)
def test_clean_data_many_seeds(robot):
    """False-positive rate of the loop on clean data (no undeclared effect)."""
    added = []
    smallest = []
    for seed in range(100, 140):
        data = campaign.__wrapped__(robot, seed, None)
        res = run_closed_loop(data.cell.nominal, data.campaign)
        if res.added:
            added.append((seed, [s.label for s in res.added]))
        smallest.append(min(c.p_adjusted for c in res.last_round))
    print(
        f"\n{robot}: effects added on {len(added)} of 40 clean campaigns {added}; "
        f"smallest corrected p per campaign: min {min(smallest):.3g}, "
        f"median {np.median(smallest):.3g}"
    )
    assert len(added) == 0


@pytest.mark.slow
@pytest.mark.parametrize("robot", [*PRESETS, "kr210_r3100"])
@pytest.mark.parametrize(
    ("effect", "kind"),
    [
        ("gravity_deflection", "gravity_compliance"),
        ("grating_cyclic", "joint_harmonic"),
        ("thermal_drift", "length_drift"),
        ("tracker_scale", None),
    ],
)
def test_effects_many_seeds(robot, effect, kind):
    rows = []
    for seed in range(1, 11):
        data = campaign.__wrapped__(robot, seed, effect)
        res = run_closed_loop(data.cell.nominal, data.campaign)
        rows.append(
            (
                seed,
                [s.kind for s in res.added],
                mean_ap(res.stages[0]),
                mean_ap(res.geometric),
                mean_ap(res.final),
                validation_ratio(data, res),
            )
        )
    ratios = np.array([r[-1] for r in rows])
    named = sum(r[1] == ([kind] if kind else []) for r in rows)
    nominal, geometric, final = (np.mean([r[i] for r in rows]) for i in (2, 3, 4))
    above = int(np.sum(ratios > 1.3))
    print(
        f"\n{robot} {effect}: named {named}/10, validation mean AP nominal {nominal:.4f} "
        f"-> geometric {geometric:.4f} -> final {final:.4f} mm; after/true mean "
        f"{ratios.mean():.3f} max {ratios.max():.3f}, above 1.3: {above}"
    )
    for r in rows:
        print(f"  seed {r[0]}: {r[1]} {r[2]:.4f} {r[3]:.4f} {r[4]:.4f} ratio {r[5]:.3f}")
    assert named == 10
    assert (ratios > 1.3).sum() <= 1 and ratios.max() < 1.5
