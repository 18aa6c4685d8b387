"""Joint harmonics of any order per revolution: a scan over orders that pays for them.

The cyclic grating error comes from the emulator's own parameters (order, amplitude,
phase of ``UndeclaredEffects``) at orders the old fixed set (1, 2, 3) did not offer; the
twin is told nothing and gets no mass model.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest

from benchmarks.bench_attribution import twin_description
from calibration.effects.candidate_scoring import LinearizedModel, score_candidate
from calibration.effects.closed_loop import ClosedLoopResult, run_closed_loop
from calibration.effects.effect_base import (
    MAX_HARMONIC_ORDER,
    MIN_HARMONIC_ORDER,
    EffectData,
    EffectSpec,
)
from calibration.effects.effect_candidates import (
    harmonic_orders,
    order_resolution,
    resolved_beside,
    resolved_candidates,
)
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignData, CampaignSettings, emulated_campaign

HARMONIC_KINDS = ("joint_harmonic", "link_harmonic", "cartesian_harmonic")


@cache
def loop(robot: str, seed: int, joint: int, order: int) -> tuple[CampaignData, ClosedLoopResult]:
    """The loop on a campaign with a cyclic error of ``joint`` at ``order`` (0: clean)."""
    eff = (
        UndeclaredEffects.named("grating_cyclic", cyclic_joint=joint, cyclic_order=order)
        if order
        else UndeclaredEffects()
    )
    data = emulated_campaign(robot, seed, CampaignSettings(effects=eff))
    return data, run_closed_loop(twin_description(data.cell.nominal, "none"), data.campaign)


FOUND = [("kr500", 1, 7, s) for s in (1, 2, 3)] + [("hp20d", 3, 5, s) for s in (1, 2)]


@pytest.mark.parametrize(("robot", "joint", "order", "seed"), FOUND)
def test_an_undeclared_order_is_found_at_its_order(robot, joint, order, seed):
    """Joint 1 of the KR500 at order 7, the HP20D's elbow at order 5 (0.004°): named at
    their order, and the amplitude and phase are the emulator's (within 5 standard errors)."""
    data, res = loop(robot, seed, joint, order)
    spec = EffectSpec("joint_harmonic", joint=joint, order=order)
    assert res.added == (spec,), [s.label for s in res.added]
    eff = data.effects
    a, phase = eff.cyclic_amplitude_deg, math.radians(eff.cyclic_phase_deg)
    truth = -a * np.array([math.sin(phase), math.cos(phase)])  # reading = q + A sin(kq + φ)
    values, se = res.final.values_of(spec), res.final.standard_errors_of(spec)
    assert np.all(np.abs(values - truth) < 5 * se), (values, truth, se)
    assert "orders scanned" in res.final.added.note  # the scan paid for its orders
    assert res.final.mean_ap("validate") < 0.8 * res.geometric.mean_ap("validate")


@pytest.mark.parametrize("robot", ["kr500", "hp20d"])
@pytest.mark.parametrize("seed", [101, 102])
def test_clean_data_gets_no_harmonic_from_the_scan(robot, seed):
    """(tests/test_closed_loop.py checks seeds 1 and 3 of both robots too.)"""
    _data, res = loop(robot, seed, 1, 0)
    assert res.added == (), [s.label for s in res.added]
    assert res.stop.code == "none_significant"
    assert res.stop.best_remaining is not None and not res.stop.best_remaining.significant


def test_orders_follow_the_poses_coverage():
    full = np.linspace(-math.pi, math.pi, 100)
    assert harmonic_orders(full) == tuple(range(1, MAX_HARMONIC_ORDER + 1))
    # 20 poses over a revolution resolve a period of 4 poses: order 5
    assert harmonic_orders(np.linspace(-math.pi, math.pi, 20)) == (1, 2, 3, 4, 5)
    # never fewer than orders 1..3, none for a joint that stands still
    assert harmonic_orders(np.linspace(0, 2 * math.pi, 6)) == tuple(
        range(1, MIN_HARMONIC_ORDER + 1)
    )
    assert harmonic_orders(np.full(50, 0.3)) == ()


def test_the_scan_pays_for_its_orders():
    """The best of K scanned orders carries a Šidák-corrected p: 1 − (1 − p)^K, then the
    round's Bonferroni factor; the rest of the score is the candidate's own."""
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(300, 4))
    cols = rng.normal(size=(300, 2))
    residual = rng.normal(size=300) + 0.2 * cols[:, 0]
    lin = LinearizedModel.build(residual, jac, 100, 5, 0)
    spec = EffectSpec("joint_harmonic", joint=1, order=1)
    kw = dict(n_candidates=10, alpha=1e-3, penalty=1.0, rtol=1e-6)
    one = score_candidate(lin, spec, cols, **kw)
    many = score_candidate(lin, spec, cols, scanned=24, **kw)
    assert many.p_value == one.p_value and many.score == one.score
    expected = min(1.0, (1.0 - (1.0 - one.p_value) ** 24) * 10)
    assert many.p_adjusted == pytest.approx(expected, rel=1e-9)
    assert many.p_adjusted > one.p_adjusted


def test_with_scale_maps_from_sweeps_the_resolution_rule_does_not_apply():
    """``twin run``'s loop (data with a sweep reference: the joint harmonics correct scale
    maps measured over each joint's whole range) is offered the unresolved order too; the
    same poses without maps are not."""
    q = np.zeros((50, 3))
    q[:, 1] = np.radians(np.linspace(-180.0, -120.0, 50))  # joint 2 covers 60°
    model = (EffectSpec("joint_harmonic", joint=2, order=20),)
    near = [EffectSpec("joint_harmonic", joint=2, order=24)]
    assert resolved_candidates(near, model, EffectData(q)) == []
    with_maps = EffectData(q, sweep_reference=np.zeros(3))
    assert resolved_candidates(near, model, with_maps) == near


def test_a_second_order_must_be_resolved_over_the_joints_coverage():
    """Two orders of one joint are told apart only when they drift a full cycle against
    each other over the covered angles (|k − k'|·coverage ≥ 2π; the coverage the central
    98 % of the readings; to the nearest order): over 60° that is 6."""
    assert order_resolution(np.linspace(-math.pi, math.pi, 50)) == 1.0
    part = np.radians(np.linspace(-180.0, -120.0, 50))
    assert order_resolution(part) == 6.0  # 360° / (0.98 · 60°) to the nearest order
    rng = np.random.default_rng(1)
    assert order_resolution(rng.uniform(-math.pi, math.pi, 300)) == 1.0  # read all round
    # one parked pose far from 100 or more others does not stretch the coverage
    many = np.radians(np.linspace(-180.0, -120.0, 120))
    assert order_resolution(np.append(many, math.radians(-90.0))) == 6.0
    assert order_resolution(np.full(10, 0.2)) == math.inf
    q = np.zeros((50, 3))
    q[:, 1] = np.radians(np.linspace(-180.0, -120.0, 50))  # joint 2 covers 60°
    q[:, 0] = np.linspace(-math.pi, math.pi, 50)  # joint 1 a whole revolution
    model = (EffectSpec("joint_harmonic", joint=2, order=20),)

    def offered(kind: str, joint: int, order: int) -> bool:
        return resolved_beside(EffectSpec(kind, joint=joint, order=order), model, q)

    assert not offered("joint_harmonic", 2, 24) and not offered("joint_harmonic", 2, 15)
    assert not offered("link_harmonic", 2, 23)  # any harmonic kind of the same joint
    assert offered("joint_harmonic", 2, 26) and offered("joint_harmonic", 2, 14)
    assert offered("link_harmonic", 2, 20)  # the same order: another direction
    assert offered("joint_harmonic", 1, 21)  # another joint
    assert resolved_beside(EffectSpec("lost_motion", joint=2), model, q)  # not a harmonic
    full = (EffectSpec("joint_harmonic", joint=1, order=7),)
    assert resolved_beside(EffectSpec("joint_harmonic", joint=1, order=8), full, q)
