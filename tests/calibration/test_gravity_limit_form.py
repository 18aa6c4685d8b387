"""The gravity term's limit form: when the data do not bound some joints' compliance ratios
(they run off to ∞ while their moments go to 0), the physical form's fit converges to the
limit model, each group of joints sharing its own moments, with honest parameter counts."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.effects import effect_shapes
from calibration.effects.candidate_scoring import LinearizedModel
from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec, ModelAtPoses
from calibration.effects.effect_candidates import gravity_candidate
from calibration.effects.effect_gravity import gravity_groups, group_moment_name
from calibration.effects.effect_kinds import KINDS
from calibration.effects.effect_shapes import fit_physical_gravity
from calibration.effects.gravity_form import physical_parameter_count
from calibration.model.description import load_robot
from calibration.model.gravity_regressor import base_moments
from calibration.model.kinematics import KinematicModel
from sim_devices.pose_campaign import sample_reachable_poses

#: Nested like an arm's: joint 2 is loaded by every moment, joint 5 by the last alone.
ACTING = {2: (0, 1, 2, 3), 3: (1, 2, 3), 4: (2, 3), 5: (3,)}


def _problem(
    p: dict[int, list[float]], seed: int = 0, seen: dict[int, float] | None = None
) -> tuple[LinearizedModel, dict]:
    """A linearized model (5 columns) and joint blocks whose true deflections are ``p``
    (per joint, per moment), with noise of 0.01 on 180 rows; ``seen``: a joint's columns
    scaled (how much its deflection moves the TCP; 1 by default)."""
    rng = np.random.default_rng(seed)
    rows = 180
    blocks = {}
    for j, ks in ACTING.items():
        block = np.zeros((rows, 4))
        block[:, list(ks)] = rng.normal(size=(rows, len(ks))) * (seen or {}).get(j, 1.0)
        blocks[j] = block
    jac = rng.normal(size=(rows, 5))
    signal = sum(blocks[j] @ np.asarray(p[j]) for j in ACTING)
    residual = -(signal + jac @ rng.normal(size=5) + 0.01 * rng.normal(size=rows))
    return LinearizedModel.build(residual, jac, rows // 3, 5, 0), blocks


# joints 2 and 3 share moments 0 and 1 and see none of 2, 3; joints 4 and 5 share those:
# no finite compliance ratio of 4 and 5 against 2 gives this (joint 2's p on moments 2, 3
# would be ρ₂·w = 0 while joint 4's is ρ₄·w ≠ 0)
LIMIT = {2: [3.0, 2.0, 0.0, 0.0], 3: [0.0, 1.0, 0.0, 0.0], 4: [0.0, 0.0, 1.5, 1.0],
         5: [0.0, 0.0, 0.0, 0.6]}  # fmt: skip


#: joints 4 and 5 hardly seen (a wrist through few poses): their deflection moves the
#: TCP by a tenth of joint 2's per unit
WRIST_SEEN = {4: 0.1, 5: 0.1}


def test_ratios_that_run_off_converge_to_the_limit_form(monkeypatch):
    lin, blocks = _problem(LIMIT, seen=WRIST_SEEN)
    fit = fit_physical_gravity(lin, blocks)
    assert fit.success
    assert fit.groups == ((2, 3), (4, 5)) and fit.moment_group == (0, 0, 1, 1)
    assert fit.reference == 2 and np.all(np.abs(fit.ratios) < 10.0), fit.ratios
    rho = dict(zip(fit.joints, fit.ratios, strict=True))
    for j, ks in ACTING.items():
        group = next(g for g in fit.groups if j in g)
        for k in ks:
            owned = fit.moment_group[k] == fit.groups.index(group)
            got = rho[j] * fit.moments[k] if owned else 0.0
            assert got == pytest.approx(LIMIT[j][k], abs=0.02), (j, k)
    assert fit.sse < 2.0 * 180 * 0.01**2  # the noise: the limit model is the truth's
    # the same data without the limit form: joint 4's and 5's ratios run off
    monkeypatch.setattr(effect_shapes, "LIMIT_RATIO_GAP", np.inf)
    plain = fit_physical_gravity(lin, blocks)
    assert plain.groups == () and (not plain.success or np.max(np.abs(plain.ratios)) > 1e3)


def test_a_well_seen_joint_whose_ratio_runs_off_is_no_limit():
    """The same deflections with joints 4 and 5 seen as well as joint 2: their ratios
    running off say the one-ratio form does not fit them (as joints 2 and 3 coupled do),
    not that the data leave them unbounded: no limit form, the fit not converged (the
    loop then keeps the linear form)."""
    fit = fit_physical_gravity(*_problem(LIMIT))
    assert fit.groups == () and not fit.success


def test_bounded_ratios_keep_the_physical_form():
    shared = np.array([3.0, 2.0, 1.5, 1.0])
    p = {j: [r * shared[k] if k in ACTING[j] else 0.0 for k in range(4)]
         for j, r in ((2, 1.0), (3, 0.5), (4, 2.0), (5, 0.4))}  # fmt: skip
    fit = fit_physical_gravity(*_problem(p, seed=1))
    assert fit.success and fit.groups == () and fit.moment_group == ()
    truth = np.array([1.0, 0.5, 2.0, 0.4])  # relative to the reference (joint 4 here)
    np.testing.assert_allclose(
        fit.ratios, truth / truth[fit.joints.index(fit.reference)], rtol=0.02
    )


def test_the_limit_forms_regressor_counts_and_file_round_trip():
    """A moment a group owns loads that group's joints alone; the others lose it (ρ·w → 0
    in the limit). The count: moments + ratios but each group's reference."""
    desc = load_robot("kr500")
    q = sample_reachable_poses(desc, 20, np.random.default_rng(3))
    ctx = EffectContext(desc, EffectData.from_sequence(q, np.zeros(20), np.radians(desc.home)))
    kin = ModelAtPoses.of(KinematicModel.from_description(desc), q)
    base = base_moments(desc)
    wrist = {base.names[k] for k in base.per_joint[3]}  # the moments loading joint 4
    names = tuple(group_moment_name((4, 5, 6), n) if n in wrist else n for n in base.names)
    ratios = {2: 0.4, 3: 1.0, 4: 1.0, 5: 0.6, 6: 3.0}
    spec = EffectSpec(
        "gravity_deflection", parameter="physical", joints=(2, 3, 4, 5, 6), names=names,
        shape=tuple(ratios.values()),
    )  # fmt: skip
    assert gravity_groups(spec) == ((2, 3), (4, 5, 6))
    assert physical_parameter_count(spec) == len(names) + 5 - 2
    assert "joints 4+5+6 apart" in spec.label
    w = np.random.default_rng(4).normal(size=len(names))
    linear = gravity_candidate(ctx)
    assert linear is not None
    p = []
    for term in linear.names:
        joint, moment = term.split(".", 1)
        j = int(joint[5:])
        k = base.names.index(moment) if moment in base.names else -1
        owned = k >= 0 and (moment in wrist) == (j >= 4)
        p.append(ratios[j] * w[k] if owned else 0.0)
    kind = KINDS["gravity_deflection"]
    got = kind.regressor(spec, ctx, slice(0, 20), kin) @ w
    want = kind.regressor(linear, ctx, slice(0, 20), kin) @ np.asarray(p)
    np.testing.assert_allclose(got, want, atol=1e-12 * np.abs(want).max())
    back, values = kind.from_parameters(kind.to_parameters(spec, w, 6), 6)
    assert back == spec and np.array_equal(values, w)


def test_a_coupled_shoulder_is_fitted_with_its_coupling_beside():
    """Joints 2 and 3 sharing compliance load each other with their torques (``κ·D·w``):
    no set of ratios holds that, so the plain fit leaves much of it; fitted with the
    coupling's columns beside, the ratios, the moments and κ come back and the residual
    is the noise's."""
    shared = np.array([3.0, 2.0, 1.5, 1.0])
    ratios = {2: 1.0, 3: 0.5, 4: 2.0, 5: 0.4}
    p = {j: [r * shared[k] if k in ACTING[j] else 0.0 for k in range(4)] for j, r in ratios.items()}
    lin, blocks = _problem(p, seed=2)
    rng = np.random.default_rng(5)
    coupling = rng.normal(size=(180, 4))
    kappa = -0.3
    lin = LinearizedModel.build(lin.residual - kappa * coupling @ shared, lin.jacobian, 60, 5, 0)
    noise_sse = 180 * 0.01**2
    plain = fit_physical_gravity(lin, blocks)
    assert plain.coupling_ratio is None
    assert not plain.success or plain.sse > 100 * noise_sse
    fit = fit_physical_gravity(lin, blocks, coupling)
    assert fit.success and fit.groups == () and fit.sse < 2.0 * noise_sse
    ref = ratios[fit.reference]
    truth = np.array([ratios[j] for j in fit.joints]) / ref
    np.testing.assert_allclose(fit.ratios, truth, rtol=0.02)
    np.testing.assert_allclose(fit.moments, shared * ref, rtol=0.02)
    assert fit.coupling_ratio == pytest.approx(kappa / ref, rel=0.02)
