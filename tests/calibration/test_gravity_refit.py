"""The physical gravity form's compliance ratios are refitted once a later effect is in,
the shoulder's coupling included.

The ratios are a shape the LM holds, profiled when the term is added; an effect the loop
adds after it (here the emulator's cyclic grating error of joint 1) was part of the
residual they were profiled on. On noise-free points (the emulator's own gravity
deflection and cyclic error, nothing else) the model the loop ends with is exact, so what
is left on the validation poses is what the held ratios cost.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from benchmarks.bench_attribution import twin_description
from benchmarks.bench_candidates import truth_errors_mm
from benchmarks.bench_plan import (
    ADMITTED,  # the gravity term and the cyclic errors, two
    seed_campaigns,
)
from calibration.effects.closed_loop import ClosedLoopResult, LoopSettings, run_closed_loop
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign, measure_campaign
from sim_devices.truth import TrueCell


@cache
def noise_free_loop(seed: int, refit: bool) -> ClosedLoopResult:
    effects = UndeclaredEffects.named("gravity_deflection", "grating_cyclic")
    settings = CampaignSettings(effects=effects, n_identify=50, n_validate=100)
    data = emulated_campaign("kr500", seed, replace(settings, grating_noise_deg=0.0))
    exact = data.expected_mm if data.expected_mm is not None else data.tcp_true_mm
    campaign = replace(data.campaign, xyz_mm=exact)
    desc = twin_description(data.cell.nominal, "none")
    return run_closed_loop(desc, campaign, settings=replace(ADMITTED, refit_gravity_form=refit))


@pytest.mark.parametrize("seed", [1, 2])
def test_a_later_effect_refits_the_compliance_ratios(seed):
    res = noise_free_loop(seed, refit=True)
    kinds = [(s.kind, s.parameter, s.joint) for s in res.added]
    assert kinds == [("gravity_deflection", "physical", 0), ("joint_harmonic", "", 1)], kinds
    final = res.final
    assert "refitted beside cyclic error of joint 1" in final.shape["gravity_form"]["reason"]
    held = noise_free_loop(seed, refit=False).final.mean_ap("validate")
    # measured: 0.0007 mm refitted against 0.006 and 0.034 mm held (seeds 1, 2)
    assert final.mean_ap("validate") < 0.002
    assert held > 3 * final.mean_ap("validate")


@cache
def noisy_gravity_loop(seed: int) -> ClosedLoopResult:
    effects = UndeclaredEffects.named("gravity_deflection")
    settings = CampaignSettings(effects=effects, n_identify=50, n_validate=100)
    data = emulated_campaign("kr500", seed, settings)
    return run_closed_loop(
        twin_description(data.cell.nominal, "none"), data.campaign, settings=ADMITTED
    )


@pytest.mark.parametrize("seed", [3, 5, 6])
def test_a_spurious_later_effect_leaves_the_ratios_held(seed):
    """The emulator's gravity deflection alone, tracker noise on: the admitted loop's second
    effect is a harmonic fitting noise. Refitting the ratios beside it lowers the SSE a
    little (any refit does); the F-test on the ratios' count keeps them held (measured: no
    refit kept on seeds 1-8)."""
    res = noisy_gravity_loop(seed)
    assert [s.kind for s in res.added] == ["gravity_deflection", "joint_harmonic"]
    assert "gravity_form" not in res.final.shape


@cache
def coupled_loop(
    refit_beside_coupling: bool, coupling_on_profile: bool = True
) -> tuple[ClosedLoopResult, list[float]]:
    """The emulator's gravity deflection with the shoulder's cross compliance (ρ 0.5),
    tracker noise on, 50 poses: the loop offered the gravity term and the coupling."""
    effects = UndeclaredEffects.named("gravity_deflection", "joint_coupling")
    settings = CampaignSettings(effects=effects, n_identify=50, n_validate=100)
    data = emulated_campaign("kr500", 6, settings)
    loop = LoopSettings(
        kinds=("gravity_deflection", "joint_coupling"),
        refit_beside_coupling=refit_beside_coupling,
        coupling_on_profile=coupling_on_profile,
    )
    desc = twin_description(data.cell.nominal, "none")
    result = run_closed_loop(desc, data.campaign, settings=loop)
    return result, truth_errors_mm(data, result)


def test_the_ratios_are_refitted_beside_the_coupling() -> None:
    """The coupling is built on the gravity term's moments; the ratios profiled before it
    was in carry part of it. Refitted beside it (profiled with its κ), the twin is nearer
    the truth (measured 0.0202 against 0.0263 mm held)."""
    res, errors = coupled_loop(True)
    held, held_errors = coupled_loop(False)
    assert [s.kind for s in res.added] == ["gravity_deflection", "joint_coupling"]
    reason = res.final.shape["gravity_form"]["reason"]
    assert "refitted beside coupled compliance" in reason and "coupling's κ" in reason, reason
    assert reason.endswith("): the coupling is in the model"), reason
    assert "gravity_form" not in held.final.shape
    assert errors[-1] < 0.85 * held_errors[-1], (errors, held_errors)


@cache
def planned_coupled_loop(
    seed: int, coupling_on_profile: bool, counterbalance: bool = True
) -> tuple[list[str], str, float]:
    """The plan's 50 poses (``twin plan``'s, the default cell) on a shoulder whose joints
    share compliance (ρ −0.5) beside the emulator's gravity deflection and cyclic grating
    error, noise-free points: the loop's final effects, what its last ratio refit says and
    the twin's validation error against the truth (mm). ``counterbalance`` False: the same
    truth with joint 2's counterbalance taken off (the twin's preset still declares one)."""
    effects = UndeclaredEffects.named(
        "gravity_deflection", "joint_coupling", "grating_cyclic", coupling_coefficient=-0.5
    )
    sc = seed_campaigns(seed, 5000)  # the plan the numbers below were read on
    cell = sc.cell if counterbalance else TrueCell.create(sc.nominal, seed, counterbalance=False)
    settings = CampaignSettings(effects=effects)
    data = measure_campaign(cell, sc.q_id, sc.q_val, np.random.default_rng([seed, 7]), settings)
    exact = data.expected_mm if data.expected_mm is not None else data.tcp_true_mm
    campaign = replace(data.campaign, xyz_mm=exact)
    loop = LoopSettings(
        kinds=("gravity_deflection", "joint_coupling", "joint_harmonic"),
        coupling_on_profile=coupling_on_profile,
    )
    result = run_closed_loop(twin_description(sc.nominal, "none"), campaign, settings=loop)
    refits = [
        st.shape["gravity_form"]["reason"] for st in result.stages if "gravity_form" in st.shape
    ]
    return [s.kind for s in result.added], refits[-1], truth_errors_mm(data, result)[-1]


@pytest.mark.parametrize("seed", [1, 4])
def test_the_coupling_is_rebuilt_on_the_profile_of_the_joint_model(seed) -> None:
    """The ratios' profile beside the coupling fits the coupling's torques from its own
    moments (the joint model, exact); the LM starts there too, the coupling rebuilt on
    those moments and κ, and the lower SSE of the two starts is kept: here the rebuilt
    one. With the coupling's moments frozen when it was offered alone
    (fitted before it was in, so carrying part of it), noise-free points of a planned
    campaign leave what the frozen torques cannot hold (measured: 0.0024 / 0.0028 mm rebuilt
    against 0.0115 / 0.0163 frozen, seeds 1 and 4; seed 6 0.0023 against 0.0044, seed 8
    0.0031 against 0.0073).

    The counterbalance's torque is coupled as gravity's is (the profile reads the torque
    the coupling carries of it): the same truth without its counterbalance leaves no less
    (measured: 0.0024 / 0.0029 mm, seeds 1 and 4; 0.0044 / 0.0062 mm with the
    counterbalance when the coupling was rebuilt on the gravity moments alone)."""
    kinds, reason, rebuilt = planned_coupled_loop(seed, True)
    assert "joint_coupling" in kinds and kinds[0] != "joint_coupling", kinds
    assert "the coupling rebuilt on the profile's moments and the counterbalance" in reason, reason
    _, reason, frozen = planned_coupled_loop(seed, False)
    assert "rebuilt" not in reason, reason
    assert rebuilt < 0.4 * frozen, (rebuilt, frozen)
    *_, uncounterbalanced = planned_coupled_loop(seed, True, counterbalance=False)
    assert rebuilt < 1.2 * uncounterbalanced, (rebuilt, uncounterbalanced)
