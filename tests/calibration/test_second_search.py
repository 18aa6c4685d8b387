"""The closed loop's second search (calibration/effects/second_search.py): a search that
ends without the gravity term a round showed is made again from that round with it first,
and the model with the lower validation error is kept.

The campaigns are bench_plan's (the emulator's truth: its own masses, counterbalance and
stiffnesses, a cyclic grating error, a tracker scale error); the twin gets the nominal
preset, and the models are judged on held-out poses against the emulator's noise-free
truth."""

from __future__ import annotations

from functools import cache
from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks.bench_plan import EFFECTS, SeedCampaigns, seed_campaigns
from calibration.effects import gravity_form
from calibration.effects.calibrate import CalibrationResult, calibrate
from calibration.effects.candidate_scoring import CandidateScore
from calibration.effects.closed_loop import LoopSettings
from calibration.effects.effect_base import EffectSpec
from calibration.effects.identification_report import build_report
from calibration.effects.model_effects import predict_tcp
from calibration.effects.report_rendering import markdown_report
from calibration.effects.second_search import SecondSearch, branch_point, has_gravity
from calibration.identify.campaign_files import Campaign
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, measure_campaign

#: The cases below were found when the loop cross-validated by the PRESS (before
#: 2026-11-28); scored by the predictive deviance the search takes other paths on these
#: campaigns (the deviance's own tests: test_candidate_cv.py). The mechanism is tested here.
PRESS = LoopSettings(loo_deviance=False)
FIRST_SEARCH_ONLY = LoopSettings(gravity_first_search=False, loo_deviance=False)
#: the first search alone, scored as the loop scores by default (the predictive deviance)
FIRST_SEARCH_BY_DEVIANCE = LoopSettings(gravity_first_search=False)
MEASURED = CampaignSettings(effects=EFFECTS)


@cache
def campaign(seed: int) -> tuple[SeedCampaigns, Campaign]:
    """bench_plan's random 50 poses of ``seed`` and the plan's 20 validation poses (from
    400 candidates; the one-pass plan's order, in which these cases were found), measured
    on the emulator's truth."""
    sc = seed_campaigns(seed, 400, 50, passes=1)
    rng = np.random.default_rng([seed, 7])
    data = measure_campaign(sc.cell, sc.random[:50], sc.q_val, rng, MEASURED)
    return sc, data.campaign


@cache
def random_50(seed: int, settings: LoopSettings = PRESS) -> tuple[CalibrationResult, float]:
    """The loop on :func:`campaign`: the result and its held-out mean error (mm)."""
    sc, measured = campaign(seed)
    return _calibrated(sc, measured, seed, MEASURED, settings)


def _calibrated(
    sc: SeedCampaigns,
    measured: Campaign,
    seed: int,
    truth: CampaignSettings,
    settings: LoopSettings | None,
) -> tuple[CalibrationResult, float]:
    """The loop on ``measured``: the result and its held-out mean error (mm) against the
    emulator's noise-free ``truth``."""
    result = calibrate(sc.nominal, measured, effects=True, loop_settings=settings, learned=False)
    held = measure_campaign(sc.cell, sc.held[:0], sc.held, np.random.default_rng([seed, 8]), truth)
    predicted = predict_tcp(result.description, held.campaign.q_rad, held.campaign.t_s)
    return result, float(np.mean(np.linalg.norm(predicted - held.true_prediction_mm, axis=1)))


#: A shoulder whose joints share compliance negatively (bench_plan's ``--effects
#: gravity_deflection,joint_coupling,grating_cyclic,tracker_scale --set
#: coupling_coefficient=-0.5``): the physical gravity form cannot be fitted on it.
NEGATIVELY_COUPLED = CampaignSettings(
    effects=UndeclaredEffects.named(
        "gravity_deflection", "joint_coupling", "grating_cyclic", "tracker_scale",
        coupling_coefficient=-0.5,
    )
)  # fmt: skip


def _without_the_coupled_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    """The physical form never fitted with the coupling beside (the loop before that fit)."""
    monkeypatch.setattr(gravity_form, "_couples", lambda ctx, blocks: False)


@cache
def planned_50(seed: int, settings: LoopSettings = PRESS) -> tuple[CalibrationResult, float]:
    """bench_plan's planned 50 poses of ``seed`` (from 5000 candidates) and its 20
    validation poses, measured on :data:`NEGATIVELY_COUPLED`: the loop's result and its
    held-out mean error (mm); the one-pass plan's order, in which these cases were found."""
    sc = seed_campaigns(seed, 5000, 50, passes=1)
    rng = np.random.default_rng([seed, 7])
    measured = measure_campaign(sc.cell, sc.q_id, sc.q_val, rng, NEGATIVELY_COUPLED).campaign
    return _calibrated(sc, measured, seed, NEGATIVELY_COUPLED, settings)


def test_a_search_that_ends_without_gravity_is_made_again_with_gravity_first() -> None:
    """Seed 3: the search by score adds a generic structure in q3 and ends without the
    gravity term (physical form, 18 parameters, penalized below it though its
    cross-validated gain was larger) that the first round's F-test showed; searched
    again with it first, the loop adds it and joint 1's cyclic error (the emulator's
    truth), and the emulator says the kept model is better by far (0.0192 against 0.0642
    mm when written)."""
    second, err_second = random_50(3)
    first, err_first = random_50(3, FIRST_SEARCH_ONLY)
    assert first.loop is not None and second.loop is not None
    assert first.loop.second_search is None
    assert not has_gravity(first.loop.final.specs)
    found = second.loop.second_search
    assert found is not None and found.kept and found.second_has_gravity
    assert has_gravity(second.loop.final.specs)
    assert found.second_mean_ap_mm < found.first_mean_ap_mm
    assert err_second < 0.5 * err_first
    sc, measured = campaign(3)
    doc, _ = build_report(
        second.result, sc.nominal, measured, robot_source="kr500", closed_loop=second.loop
    )
    assert doc["closed_loop"]["second_search"]["kept"] == "second"
    assert doc["closed_loop"]["added"][0].startswith("gravity deflection")
    assert "Searched again with gravity first: the first round showed gravity" in markdown_report(
        doc
    )


def test_a_later_round_that_showed_gravity_is_where_the_second_search_begins() -> None:
    """Seed 6: the search by score begins with joint 1's cyclic error (the truth, its gain
    above gravity's), then adds joint 2's harmonic 3 in round 2 though that round showed
    the gravity term with a larger cross-validated gain, and ends without it. Searched
    again from round 2 with gravity first, joint 1's harmonic kept, the loop ends on the
    truth, and the emulator says the kept model is better (0.0145 against 0.0275 mm when
    written)."""
    second, err_second = random_50(6)
    first, err_first = random_50(6, FIRST_SEARCH_ONLY)
    assert first.loop is not None and second.loop is not None
    assert not has_gravity(first.loop.final.specs)
    found = second.loop.second_search
    assert found is not None and found.round == 2 and found.kept, found
    assert second.loop.final.specs[0] == first.loop.final.specs[0]  # round 1 kept as it was
    assert second.loop.final.specs[1].kind == "gravity_deflection"
    assert err_second < 0.7 * err_first
    assert found.text.startswith("round 2 showed gravity deflection")
    assert found.as_dict()["round"] == 2


@pytest.mark.slow  # a plan from 5000 candidates and two loops: ~10 s of make test's margin
def test_a_search_without_gravity_takes_its_shown_linear_form_when_the_physical_fails(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A negatively coupled shoulder, planned seed 5, the physical form never fitted with
    the coupling beside (as before that fit was made): the physical form cannot be fitted
    in any round and the search by score ends on joint 1's cyclic error and a generic q3
    structure, though its third round showed the linear gravity form (corrected p 5e-7).
    Searched again from there, the linear form is taken for being shown (the search had
    no gravity term), the validation error falls, and the emulator says the kept model is
    better (0.0179 against 0.0323 mm when written)."""
    _without_the_coupled_fit(monkeypatch)
    second, err_second = planned_50.__wrapped__(5)
    first, err_first = planned_50.__wrapped__(5, FIRST_SEARCH_ONLY)
    assert first.loop is not None and second.loop is not None
    assert not has_gravity(first.loop.final.specs)
    found = second.loop.second_search
    assert found is not None and found.kept and found.round > 1, found
    forms = [s.parameter for s in second.loop.final.specs if s.kind == "gravity_deflection"]
    assert forms == ["linear"], second.loop.final.specs
    assert err_second < 0.7 * err_first


@pytest.mark.slow  # a plan from 5000 candidates and two loops: ~10 s of make test's margin
def test_a_coupled_shoulder_gets_its_physical_form_fitted_with_the_coupling_beside(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The same shoulder, planned seed 4: the one-ratio physical form does not converge,
    so it is fitted with the coupling beside; the gravity term goes in in that form and
    the coupling after it (the truth's two terms), the report says how the ratios were
    fitted, and the emulator says the model is better than the loop's without that fit
    (0.0165 against 0.0231 mm when written; 0.0195 since a search that ended without
    gravity searches again from a round that showed half the added effect's gain)."""
    coupled, err = planned_50(4)
    with monkeypatch.context() as before:
        _without_the_coupled_fit(before)
        uncoupled, err_uncoupled = planned_50.__wrapped__(4)
    assert coupled.loop is not None and uncoupled.loop is not None
    assert not any(s.kind == "joint_coupling" for s in uncoupled.loop.final.specs)
    specs = coupled.loop.final.specs
    kinds = [s.kind for s in specs]
    assert "joint_coupling" in kinds and "gravity_deflection" in kinds, specs
    assert kinds.index("gravity_deflection") < kinds.index("joint_coupling")
    gravity = next(s for s in specs if s.kind == "gravity_deflection")
    assert gravity.parameter == "physical"
    forms = [st.shape["gravity_form"] for st in coupled.loop.stages if "gravity_form" in st.shape]
    assert any(f.get("fitted_with_coupling_ratio") is not None for f in forms), forms
    assert any("coupled compliance beside" in f["reason"] for f in forms)
    assert err < 0.9 * err_uncoupled, (err, err_uncoupled)


#: Lost motion in joints 2 and 3 beside the default effects (bench_plan's ``--effects
#: gravity_deflection,grating_cyclic,tracker_scale,lost_motion``).
WITH_LOST_MOTION = CampaignSettings(
    effects=UndeclaredEffects.named(
        "gravity_deflection", "grating_cyclic", "tracker_scale", "lost_motion"
    )
)


def test_the_second_searchs_gravity_step_is_judged_by_the_search_s_end() -> None:
    """Seed 2's planned 50 poses (from 400 candidates) on a truth with lost motion: the
    first search ends on joint 2's lost motion and joint 1's cyclic error without the
    gravity term its first round showed. Searched again, the gravity step alone raises the
    validation error (0.0913 -> 0.1015 mm: joint 2's lost motion, the larger effect, is
    still unmodelled), which the validation guard undid until 2026-11-28, ending the
    second search without gravity. Judged by where the second search ends (0.0278 against
    0.0504 mm), on the same validation poses, it is kept, and the emulator says the kept
    model is better by far (0.0147 against 0.0608 mm held out when written)."""
    sc = seed_campaigns(2, 400, 50)
    rng = np.random.default_rng([2, 7])
    measured = measure_campaign(sc.cell, sc.q_id, sc.q_val, rng, WITH_LOST_MOTION).campaign
    second, err_second = _calibrated(sc, measured, 2, WITH_LOST_MOTION, None)
    first, err_first = _calibrated(sc, measured, 2, WITH_LOST_MOTION, FIRST_SEARCH_BY_DEVIANCE)
    assert second.loop is not None and first.loop is not None
    found = second.loop.second_search
    assert found is not None and found.kept and not found.gravity_undone
    stages = second.loop.stages
    k = next(i for i, stage in enumerate(stages) if has_gravity(stage.specs))
    assert stages[k].mean_ap("validate") > stages[k - 1].mean_ap("validate")
    assert not has_gravity(first.loop.final.specs)
    assert err_second < 0.5 * err_first, (err_second, err_first)


def test_a_search_that_began_with_gravity_is_not_made_again() -> None:
    """Seed 10: the search by score begins with the gravity term; nothing is searched
    again and the model is the first search's."""
    result, err = random_50(10)
    first, err_first = random_50(10, FIRST_SEARCH_ONLY)
    assert result.loop is not None and first.loop is not None
    assert result.loop.second_search is None
    assert has_gravity(result.loop.final.specs[:1])
    assert err == err_first


def test_a_second_search_no_better_leaves_the_first_model() -> None:
    """Seed 29: the search by score begins with a cyclic error and ends on cyclic errors
    without the gravity term; the second search adds it but its validation error is
    higher, so it is not kept: the model is the first search's, to the digit, and the
    report says why."""
    result, err = random_50(29)
    first, err_first = random_50(29, FIRST_SEARCH_ONLY)
    assert result.loop is not None and first.loop is not None
    found = result.loop.second_search
    assert found is not None and not found.kept
    assert found.second_has_gravity and found.second_mean_ap_mm >= found.first_mean_ap_mm
    assert err == err_first
    assert result.loop.added == first.loop.added
    assert found.text.endswith("the first kept: the second's validation mean AP is not lower")


def test_the_second_search_says_what_each_search_found() -> None:
    """The report's sentence names both searches' effects and errors and which was kept,
    and why the first was kept when it was."""
    shown = "gravity deflection (physical form) (corrected p 1e-10, CV gain 80.0 σ²)"
    kept = SecondSearch(shown, ("harmonic",), ("gravity", "harmonic"), 0.04, 0.02, True, True)
    said = "by score began with harmonic and ended with harmonic (validation mean AP 0.0400"
    assert said in kept.text
    assert kept.text.endswith("gravity first: gravity, harmonic (0.0200 mm); the second kept")
    assert kept.as_dict()["kept"] == "second"
    lost = SecondSearch(shown, (), ("harmonic",), 0.04, 0.05, False, False)
    assert "the search by score added nothing" in lost.text
    later = SecondSearch(shown, ("h1", "h2"), ("h1", "gravity"), 0.04, 0.02, True, True, 2)
    assert later.text.startswith("round 2 showed gravity")
    assert "the search by score added h2 there and ended with h1, h2" in later.text
    stopped = SecondSearch(shown, ("h1",), ("h1", "gravity"), 0.04, 0.02, True, True, 2)
    assert "the search by score stopped there with h1 (validation" in stopped.text
    assert lost.text.endswith("the first kept: the second ended without gravity")
    undone = SecondSearch(shown, ("h1",), ("h1",), 0.04, 0.04, False, False, 2, "it failed")
    assert undone.text.endswith("ended without gravity (its gravity step was set aside: it failed)")
    worse = SecondSearch(shown, ("harmonic",), ("gravity",), 0.04, 0.05, True, False)
    assert worse.text.endswith("the first kept: the second's validation mean AP is not lower")


def _score(kind: str, cv_gain: float, p: float = 1e-9) -> CandidateScore:
    spec = EffectSpec(kind, joint=1, parameter="physical" if kind == "gravity_deflection" else "")
    return CandidateScore(spec, 18, cv_gain, cv_gain - 90.0, 9.0, p, p, cv_gain > 90.0)


def _stages(*rounds: tuple[CandidateScore, list[CandidateScore]]) -> list[SimpleNamespace]:
    """Nominal and geometric, then one stage per round: what it added and its scores."""
    out = [SimpleNamespace(specs=(), round_scores=(), added=None)] * 2
    for added, scores in rounds:
        specs = (*out[-1].specs, added.spec)
        out.append(SimpleNamespace(specs=specs, round_scores=tuple(scores), added=added))
    return out


def test_where_the_second_search_begins() -> None:
    """The first round, before gravity is in, that showed it with the larger gain than
    what it added (half of it when the search stopped without gravity, short of the
    maximum); or the round that stopped with it shown; never once gravity is in."""
    gravity, weak = _score("gravity_deflection", 80.0), _score("gravity_deflection", 30.0)
    h1, h2 = _score("joint_harmonic", 60.0), _score("cyclic_error", 40.0)
    later = _stages((h1, [h1, weak]), (h2, [h2, gravity]))  # round 1: gravity's gain lower
    assert branch_point(later, [], 0.01, 6) == (3, gravity)  # round 2: two stages kept + 1
    first = _stages((h1, [h1, gravity]), (h2, [h2, gravity]))
    assert branch_point(first, [], 0.01, 6) == (2, gravity)
    # gravity added in round 1: no round after it is looked at
    assert branch_point(_stages((gravity, [gravity]), (h1, [h1, gravity])), [], 0.01, 6) is None
    # stopped with gravity shown but not significant by its penalized score
    ended = _stages((h1, [h1, weak]))
    assert branch_point(ended, [weak, h2], 0.01, 6) == (3, weak)
    assert branch_point(ended, [weak, h2], 0.01, 1) is None  # the maximum is in
    assert branch_point(ended, [_score("gravity_deflection", 30.0, p=0.5)], 0.01, 6) is None
    assert branch_point(ended, [_score("gravity_deflection", -1.0)], 0.01, 6) is None
    # a search that ended without gravity: half the added effect's gain is enough
    half = _score("gravity_deflection", 31.0)
    assert branch_point(_stages((h1, [h1, half]), (h2, [h2])), [], 0.01, 6) == (2, half)
    assert branch_point(_stages((h1, [h1, weak]), (h2, [h2])), [], 0.01, 6) is None  # 30 = 60/2
    # one that added gravity later keeps the strict rule: a larger gain than the added's
    ended_with = _stages((h1, [h1, half]), (gravity, [gravity]))
    assert branch_point(ended_with, [], 0.01, 6) is None
    full = _stages((h1, [h1, half]), (h2, [h2]))  # so does one that filled the model
    assert branch_point(full, [], 0.01, 2) is None
