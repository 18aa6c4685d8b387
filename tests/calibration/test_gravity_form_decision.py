"""The gravity form decision's F-test (calibration.effects.gravity_form.form_decision) on
fitted results made up here: its logic, without a robot."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from calibration.effects.effect_base import EffectSpec
from calibration.effects.effect_shapes import PhysicalGravityFit
from calibration.effects.gravity_form import form_decision

M = 50  # poses: 150 rows


def _result(sse: float, n_free: int) -> SimpleNamespace:
    fun = np.full(3 * M, np.sqrt(sse / (3 * M)))
    return SimpleNamespace(optimize_result=SimpleNamespace(fun=fun), free=np.ones(n_free, bool))


def _decide(sse_linear: float, sse_physical: float) -> dict:
    ctx = SimpleNamespace(description=SimpleNamespace(base=None), gravity=np.array([0, 0, -1.0]))
    linear = EffectSpec("gravity_deflection", names=tuple(f"joint2.m{k}" for k in range(34)))
    phys = EffectSpec(
        "gravity_deflection", parameter="physical", joints=(2, 3), names=("a", "b"), shape=(1, 2)
    )
    one = np.ones(2)
    fit = PhysicalGravityFit((2, 3), 2, one, one * 0.1, one, one * 0.1, sse_physical, True)
    out = form_decision(
        ctx,
        M,
        _result(sse_linear, 60),
        _result(sse_physical, 30),
        linear,
        phys,
        fit,  # type: ignore[arg-type]
    )
    return out["gravity_form"]


def test_a_significantly_better_linear_form_is_kept():
    form = _decide(sse_linear=100.0, sse_physical=300.0)
    assert form["kept"] == "linear" and form["p_value"] < 0.01


def test_no_evidence_keeps_the_physical_form_with_its_test():
    form = _decide(sse_linear=148.0, sse_physical=150.0)
    assert form["kept"] == "physical" and form["f_statistic"] == pytest.approx(0.0, abs=0.2)
    assert "extra freedom: F = " in form["reason"]


def test_a_linear_fit_that_stopped_short_is_said_so_not_given_a_negative_f():
    form = _decide(sse_linear=180.0, sse_physical=150.0)
    assert form["kept"] == "physical" and form["f_statistic"] < 0
    assert "did not converge" in form["reason"] and "F = -" not in form["reason"], form
