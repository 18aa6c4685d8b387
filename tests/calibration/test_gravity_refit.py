"""The physical gravity form's compliance ratios are refitted once a later effect is in.

The ratios are a shape the LM holds, profiled when the term is added; an effect the loop
adds after it (here the emulator's cyclic grating error of joint 1) was part of the
residual they were profiled on. On noise-free points (the emulator's own gravity
deflection and cyclic error, nothing else) the model the loop ends with is exact, so what
is left on the validation poses is what the held ratios cost.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import pytest

from benchmarks.bench_attribution import twin_description
from benchmarks.bench_plan import ADMITTED  # the gravity term and the cyclic errors, two
from calibration.effects.closed_loop import ClosedLoopResult, run_closed_loop
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign


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
