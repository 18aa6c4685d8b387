"""Effect library: regressors (against finite differences, the mass model and the emulator's
physics), [[effect]] tables, candidates, and `predict_tcp` applying every kind."""

from __future__ import annotations

import tomllib
from dataclasses import replace

import numpy as np
import pytest
import tomli_w

from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec, ModelAtPoses
from calibration.effects.effect_candidates import (
    candidate_effects,
    gravity_candidate,
    harmonic_orders,
)
from calibration.effects.effect_gravity import counterbalance_terms
from calibration.effects.effect_kinds import (
    KINDS,
    from_description,
    regressor_matrix,
    to_descriptions,
)
from calibration.effects.model_effects import ModelEffectError, predict_tcp
from calibration.errors import EffectLibraryError
from calibration.model.description import EffectDescription, RobotDescription, load_robot
from calibration.model.gravity_regressor import (
    base_moments,
    raw_moments_from_masses,
    raw_regressor,
)
from calibration.model.kinematics import KinematicModel, flange_poses, tcp_positions
from calibration.model.statics import STANDARD_GRAVITY_M_S2
from sim_devices.effects import UndeclaredEffects, true_tcp_mm
from sim_devices.pose_campaign import sample_reachable_poses

DESC = load_robot("kr500")
MODEL = KinematicModel.from_description(DESC)
Q = sample_reachable_poses(DESC, 40, np.random.default_rng(3))
T = np.linspace(0.0, 3600.0, 40)
CTX = EffectContext(DESC, EffectData.from_sequence(Q, T, np.radians(DESC.home)))
KIN = ModelAtPoses.of(MODEL, Q)
ALL = slice(0, len(Q))

GRAVITY = gravity_candidate(CTX)
assert GRAVITY is not None
PHYSICAL = EffectSpec(
    "gravity_deflection",
    parameter="physical",
    joints=(2, 3, 4, 5, 6),
    names=base_moments(DESC).names,
    shape=(1.0, 0.7, 2.0, 1.5, 0.5),
)
PHYSICAL_CB = replace(PHYSICAL, names=PHYSICAL.names + counterbalance_terms(2))
SPECS = [
    GRAVITY,
    PHYSICAL_CB,
    EffectSpec("gravity_compliance", joints=(2, 3, 5)),
    EffectSpec("link_bending", joint=2, names=("link2.mx", "link3.my"), shape=(120.0, -40.0)),
    EffectSpec(
        "joint_coupling",
        joints=(2, 3),
        names=("link2.mx", "link3.my", "joint2.counterbalance.cos2"),
        shape=(120.0, -40.0, 8.0),
    ),
    EffectSpec("joint_harmonic", joint=1, order=2),
    EffectSpec("lost_motion", joint=3),
    EffectSpec("length_drift", joint=2, parameter="a"),
    EffectSpec("length_drift", joint=4, parameter="d", span_s=(600.0, 3000.0)),
    EffectSpec("length_drift", joint=3, parameter="a", shape=(900.0,)),
    EffectSpec("instrument_scale"),
    EffectSpec("instrument_scale_drift"),
    EffectSpec("thermal_expansion", joints=(1, 2, 3), t_ref_c=21.5),
    EffectSpec("length_temperature", joint=2, parameter="a", t_ref_c=21.5),
    EffectSpec("instrument_scale_temperature", t_ref_c=21.5),
    EffectSpec("cartesian_harmonic", joint=4, order=3),
    EffectSpec("link_harmonic", joint=2, order=1),
    EffectSpec("cartesian_time", joint=0, order=2),
    EffectSpec("cartesian_time", joint=2, order=1, span_s=(0.0, 1800.0)),
]


def test_every_kind_is_covered():
    assert {s.kind for s in SPECS} == set(KINDS)


def _joint_shift(dq: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    return (tcp_positions(MODEL, Q + eps * dq) - tcp_positions(MODEL, Q - eps * dq)) / (2 * eps)


def test_joint_angle_regressors_match_finite_differences():
    # harmonic: d TCP / d cos_deg = ∂TCP/∂q1 · cos(2 q1) · π/180
    r = KINDS["joint_harmonic"].regressor(
        EffectSpec("joint_harmonic", joint=1, order=2), CTX, ALL, KIN
    )
    dq = np.zeros_like(Q)
    dq[:, 0] = np.cos(2 * Q[:, 0]) * np.pi / 180
    np.testing.assert_allclose(r[:, :, 0], _joint_shift(dq), atol=1e-6)
    # compliance: per µrad/(kN·m), the joint turns by tau · 1e-12 rad
    r = KINDS["gravity_compliance"].regressor(SPECS[2], CTX, ALL, KIN)
    dq = np.zeros_like(Q)
    dq[:, 2] = KIN.torques_nmm(CTX.masses)[:, 2] * 1e-12
    np.testing.assert_allclose(r[:, :, 1], _joint_shift(dq, eps=1.0), rtol=1e-6, atol=1e-10)
    # lost motion: the approach direction of joint 3 times π/180
    r = KINDS["lost_motion"].regressor(EffectSpec("lost_motion", joint=3), CTX, ALL, KIN)
    dq = np.zeros_like(Q)
    dq[:, 2] = CTX.data.direction[:, 2] * np.pi / 180
    np.testing.assert_allclose(r[:, :, 0], _joint_shift(dq), atol=1e-6)


def test_gravity_deflection_regressor_without_masses():
    """Linear form: a free deflection per joint and base moment, Ŷ·1e-6 rad per µrad; the
    physical form is the linear one with p_jk = ρ_j·w_k; with p_jk = c_j·g·β_k from the
    description's mass model both reproduce the mass-model compliance term exactly."""
    y = raw_regressor(MODEL, Q)  # (N, n, 3n)
    names = [m for j in range(6) for m in (f"link{j + 1}.mx", f"link{j + 1}.my", f"link{j + 1}.mz")]
    r = KINDS["gravity_deflection"].regressor(GRAVITY, CTX, ALL, KIN)
    # 30 joint-moment terms and, the preset declaring a counterbalance on joint 2, its
    # torque profile's harmonics 2 and 3
    assert r.shape == (40, 3, 34) and GRAVITY.names[30:] == counterbalance_terms(2)
    for col, k, f in ((30, 2, np.cos), (33, 3, np.sin)):
        dq = np.zeros_like(Q)
        dq[:, 1] = f(k * Q[:, 1]) * 1e-6
        np.testing.assert_allclose(r[:, :, col], _joint_shift(dq, eps=1.0), atol=1e-9)
    for col in (0, 9, 17, 29):
        joint, moment = GRAVITY.names[col].split(".", 1)
        j = int(joint[5:])
        dq = np.zeros_like(Q)
        dq[:, j - 1] = y[:, j - 1, names.index(moment)] * 1e-6
        np.testing.assert_allclose(r[:, :, col], _joint_shift(dq, eps=1.0), atol=1e-9)
    # physical = linear with p_jk = ρ_j w_k
    w = np.random.default_rng(4).normal(size=len(PHYSICAL.names))
    rho = dict(zip(PHYSICAL.joints, PHYSICAL.shape, strict=True))
    p = []
    for term in GRAVITY.names[:30]:
        joint, moment = term.split(".", 1)
        p.append(rho[int(joint[5:])] * w[PHYSICAL.names.index(moment)])
    phys = regressor_matrix([PHYSICAL], CTX, ALL, KIN) @ w
    np.testing.assert_allclose(phys, r[:, :, :30] @ np.array(p), atol=1e-12)
    # the mass model's compliance term is one point of the linear form
    compliance = np.array([0.0, 11.0, 95.0, 700.0, 400.0, 900.0])  # µrad/(kN·m)
    beta = base_moments(DESC).values_from_raw(raw_moments_from_masses(DESC), MODEL)
    base_names = base_moments(DESC).names
    p = [
        compliance[int(t.split(".")[0][5:]) - 1]
        * 1e-6  # µrad/(kN·m) -> µrad/(N·mm)
        * STANDARD_GRAVITY_M_S2
        * beta[base_names.index(t.split(".", 1)[1])]
        for t in GRAVITY.names[:30]
    ]
    spec = EffectSpec("gravity_compliance", joints=(1, 2, 3, 4, 5, 6))
    expected = regressor_matrix([spec], CTX, ALL, KIN) @ compliance
    got = r[:, :, :30] @ np.array(p)
    np.testing.assert_allclose(got, expected, atol=1e-9 * np.abs(expected).max())
    # an arm without a declared counterbalance: the 30 terms alone
    hp = load_robot("hp20d")
    q_hp = sample_reachable_poses(hp, 10, np.random.default_rng(5))
    hp_spec = gravity_candidate(EffectContext(hp, EffectData(q_hp)))
    assert hp_spec is not None and len(hp_spec.names) == 30


def test_gravity_direction_comes_from_the_description(tmp_path):
    """`[base] gravity` (a direction in the robot base frame, any length) turns the
    regressor; a ceiling mount's is the floor's negated; [0, 0, 0] is rejected."""
    ceiling = replace(DESC, base=replace(DESC.base, gravity=(0.0, 0.0, 2.0)))
    path = tmp_path / "ceiling.toml"
    ceiling.save(path)
    back = RobotDescription.load(path)
    assert back.base.gravity == (0.0, 0.0, 2.0)
    ctx = EffectContext(back, CTX.data)
    np.testing.assert_allclose(ctx.gravity, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(
        raw_regressor(MODEL, Q, ctx.gravity), -raw_regressor(MODEL, Q), atol=1e-15
    )
    # the calibrated description keeps it
    assert KinematicModel.from_description(back).to_description(back).base.gravity == (
        0.0,
        0.0,
        2.0,
    )
    doc = tomllib.loads(path.read_text())
    doc["base"]["gravity"] = [0.0, 0.0, 0.0]
    path.write_text(tomli_w.dumps(doc))
    with pytest.raises(ValueError, match=r"\[base\]: key 'gravity': must be a direction"):
        RobotDescription.load(path)


def test_length_scale_and_time_regressors():
    x = MODEL.parameter_vector()
    x[5 * 1 + 0] += 1.0  # a2 + 1 mm
    axis = tcp_positions(MODEL.with_parameters(x), Q) - tcp_positions(MODEL, Q)
    drift = EffectSpec("length_drift", joint=2, parameter="a")
    r = KINDS["length_drift"].regressor(drift, CTX, ALL, KIN)
    np.testing.assert_allclose(r[:, :, 0], axis * (T / 3600.0)[:, None], atol=1e-9)
    # a first-order lag: the final growth times 1 − e^(−t/τ)
    lag = replace(drift, shape=(900.0,))
    r = KINDS["length_drift"].regressor(lag, CTX, ALL, KIN)
    np.testing.assert_allclose(r[:, :, 0], axis * (1 - np.exp(-T / 900.0))[:, None], atol=1e-9)
    # a polynomial in time is held at the campaign's span: never extrapolated
    held = replace(drift, span_s=(600.0, 1800.0))
    r = KINDS["length_drift"].regressor(held, CTX, ALL, KIN)
    t_held = np.clip(T, 600.0, 1800.0) / 3600.0
    np.testing.assert_allclose(r[:, :, 0], axis * t_held[:, None], atol=1e-9)
    assert np.any(T > 1800.0) and np.any(T < 600.0)
    r = KINDS["instrument_scale"].regressor(EffectSpec("instrument_scale"), CTX, ALL, KIN)
    np.testing.assert_allclose(r[:, :, 0], tcp_positions(MODEL, Q) * 1e-6)
    scale_drift = EffectSpec("instrument_scale_drift")
    r = KINDS["instrument_scale_drift"].regressor(scale_drift, CTX, ALL, KIN)
    np.testing.assert_allclose(r[:, :, 0], tcp_positions(MODEL, Q) * 1e-6 * (T / 3600)[:, None])
    r = KINDS["cartesian_time"].regressor(EffectSpec("cartesian_time", order=2), CTX, ALL, KIN)
    assert r.shape == (40, 3, 6)
    np.testing.assert_allclose(r[:, 1, 4], (T / 3600.0) ** 2)
    # link frames read off the Jacobian are the kinematic frames
    for frame in (1, 2, 4, 6):
        rot = flange_poses(MODEL.truncated(frame), Q[:, :frame])[:, :3, :3]
        np.testing.assert_allclose(KIN.frame_axes(frame), rot, atol=1e-12)
    # a link turning about its own axes: z is the joint's own column, x the next alpha's
    rot = KIN.rotation_axes(2)
    np.testing.assert_allclose(rot[:, :, 2], KIN.joint_axis(2), atol=1e-9)
    np.testing.assert_allclose(rot[:, :, 0], KIN.jacobian[:, :, 5 * 2 + 1], atol=1e-9)
    link = EffectSpec("link_harmonic", joint=2, order=1)
    r = KINDS["link_harmonic"].regressor(link, CTX, ALL, KIN)
    np.testing.assert_allclose(
        r[:, :, 5], rot[:, :, 2] * np.sin(Q[:, 1])[:, None] * np.pi / 180, atol=1e-12
    )


def test_compliance_matches_the_emulators_deflection():
    """The twin's first-order compliance term predicts the emulator's exact deflection."""
    eff = UndeclaredEffects.named("gravity_deflection")
    sim = true_tcp_mm(eff, DESC, Q, T) - tcp_positions(MODEL, Q)
    from sim_devices.effects import deflection_stiffness_nmm_per_rad

    k = deflection_stiffness_nmm_per_rad(eff, DESC)
    spec = EffectSpec("gravity_compliance", joints=(2, 3, 4, 5))
    c = np.array([1e12 / k[j - 1] for j in spec.joints])  # µrad/(kN·m)
    twin = regressor_matrix([spec], CTX, ALL, KIN) @ c
    assert np.max(np.abs(sim)) > 0.2
    assert np.max(np.linalg.norm(twin - sim, axis=1)) < 1e-3


def test_descriptions_round_trip_and_predict_applies_every_kind(tmp_path):
    rng = np.random.default_rng(0)
    values = [rng.normal(size=len(s.parameter_names())) * 0.01 for s in SPECS]
    effects = to_descriptions(SPECS, np.concatenate(values), 6)
    desc = replace(DESC, effects=effects)
    path = tmp_path / "m.toml"
    desc.save(path)
    back = RobotDescription.load(path)
    text = path.read_text()
    assert 'kind = "gravity_compliance"' in text and "compliance_urad_per_knm" in text
    assert "a_rate_mm_per_h" in text and "d_rate_mm_per_h" in text and "t0_s" in text
    assert 'form = "linear"' in text and '"joint2.link2.mx"' in text
    assert 'form = "physical"' in text and "compliance_ratio" in text
    assert '"joint2.counterbalance.cos2"' in text and "counterbalance_urad" in text
    assert "a_final_mm" in text and "time_constant_s = 900.0" in text
    assert "t_min_s = 600.0" in text and "t_max_s = 3000.0" in text
    expected = tcp_positions(MODEL, Q)
    for spec, v, e in zip(SPECS, values, back.effects, strict=True):
        spec2, v2 = from_description(e, 6)
        if spec.kind == "gravity_compliance":  # written for every joint, zeros elsewhere
            assert spec2.joints == (1, 2, 3, 4, 5, 6) and v2[[1, 2, 4]].tolist() == v.tolist()
        else:
            assert spec2 == spec and np.array_equal(v2, v)
        expected = expected + KINDS[spec.kind].regressor(spec, CTX, ALL, KIN) @ v
    np.testing.assert_allclose(predict_tcp(back, Q, T), expected, atol=1e-12)


def test_predict_names_bad_effects():
    def bad(kind, **params):
        desc = replace(DESC, effects=(EffectDescription(kind, params),))
        with pytest.raises(ModelEffectError) as info:
            predict_tcp(desc, Q[:3], T[:3])
        return str(info.value)

    assert "cos_deg" in bad("joint_harmonic", joint=1.0, order=2.0, sin_deg=0.0)
    assert "joint must be 1..6" in bad("lost_motion", joint=7.0, half_width_deg=0.01)
    assert "wobble" in bad("lost_motion", joint=1.0, half_width_deg=0.01, wobble=1.0)
    assert "6 numbers" in bad("gravity_compliance", compliance_urad_per_knm=(1.0, 2.0))
    assert "exactly one" in bad("length_drift", joint=2.0)
    assert "time_constant_s" in bad("length_drift", joint=2.0, a_final_mm=0.1)
    assert "must be > 0" in bad("length_drift", joint=2.0, a_final_mm=0.1, time_constant_s=-5.0)
    assert "t_min_s" in bad("length_drift", joint=2.0, a_rate_mm_per_h=0.1, t_max_s=5.0)
    assert "form must be" in bad("gravity_deflection", form="quadratic")
    assert "jointJ.linkK.mA" in bad(
        "gravity_deflection", form="linear", terms=("joint2.link9.mx",), deflection_urad=(1.0,)
    )
    assert "1 numbers" in bad(
        "gravity_deflection", form="linear", terms=("joint2.link2.mx",), deflection_urad=(1.0, 2.0)
    )
    assert "unknown moment" in bad(
        "gravity_deflection",
        form="physical",
        joints=(2.0,),
        compliance_ratio=(1.0,),
        moments=("link2.mq",),
        weighted_moment_urad=(1.0,),
    )
    desc = replace(
        DESC, effects=(EffectDescription("instrument_scale_drift", {"rate_ppm_per_h": 1.0}),)
    )
    with pytest.raises(ModelEffectError, match="t_s"):
        predict_tcp(desc, Q[:3])


def test_directions_follow_time_order():
    shuffle = np.random.default_rng(1).permutation(len(Q))
    data = EffectData.from_sequence(Q[shuffle], T[shuffle], np.zeros(6))
    np.testing.assert_array_equal(data.direction, CTX.data.direction[shuffle])
    np.testing.assert_array_equal(CTX.data.direction[0], np.sign(Q[0]))
    np.testing.assert_array_equal(CTX.data.direction[1:], np.sign(np.diff(Q, axis=0)))
    # standing still (read noise far below 1e-5 rad) keeps the last direction
    q = np.repeat(np.array([[0.1, -0.2], [0.3, -0.5]]), [1, 4], axis=0)
    q[2:] += np.random.default_rng(2).normal(0, 1e-7, (3, 2))
    data = EffectData.from_sequence(q, None, np.zeros(2))
    np.testing.assert_array_equal(data.direction, np.tile([1.0, -1.0], (5, 1)))
    still = np.array([[0.0, 0.0], [1e-7, -1e-7], [0.0, 0.0]])
    data = EffectData.from_sequence(still, None, np.zeros(2))
    np.testing.assert_array_equal(data.direction, np.zeros((3, 2)))


def test_candidates():
    specs = candidate_effects(CTX)
    kinds = [s.kind for s in specs]
    # harmonics: every order the poses resolve, per joint (3..24 of them; was 1..3)
    orders = [harmonic_orders(CTX.data.q_rad[:, j]) for j in range(6)]
    assert all(o == tuple(range(1, len(o) + 1)) and 3 <= len(o) <= 24 for o in orders)
    n_orders = sum(len(o) for o in orders)
    for kind in ("joint_harmonic", "cartesian_harmonic", "link_harmonic"):
        assert sorted((s.joint, s.order) for s in specs if s.kind == kind) == sorted(
            (j + 1, k) for j, o in enumerate(orders) for k in o
        )
    assert len(specs) == 23 + 3 * n_orders  # gravity, 6 lost motions, 6 drifts, 2 scales, 8 time
    assert kinds.count("lost_motion") == 6 and kinds.count("cartesian_time") == 8
    drift = {(s.joint, s.parameter) for s in specs if s.kind == "length_drift"}
    assert drift == {(1, "d"), (2, "a"), (3, "a"), (4, "a"), (4, "d"), (6, "d")}
    gravity = next(s for s in specs if s.kind == "gravity_deflection")
    assert gravity.joints == (2, 3, 4, 5, 6) and len(gravity.parameter_names()) == 34
    assert "gravity_compliance" not in kinds  # the mass-model form only when named
    assert len(set(specs)) == len(specs)  # hashable and distinct
    # no times: no drift terms; no masses: the same gravity candidate; a restricted set
    no_t = EffectContext(DESC, EffectData.from_sequence(Q))
    assert not any(KINDS[s.kind].needs_time for s in candidate_effects(no_t))
    massless = replace(DESC, joints=tuple(replace(j, mass_kg=None) for j in DESC.joints))
    massless = replace(massless, tool=replace(DESC.tool, mass_kg=None))
    ctx = EffectContext(massless, CTX.data)
    assert gravity in candidate_effects(ctx)
    assert "gravity_compliance" not in {
        s.kind for s in candidate_effects(ctx, ["gravity_compliance"])
    }
    named = candidate_effects(CTX, ["gravity_compliance"])
    assert [s.kind for s in named] == ["gravity_compliance"] and 1 not in named[0].joints
    only = candidate_effects(CTX, ["instrument_scale", "lost_motion"])
    assert {s.kind for s in only} == {"instrument_scale", "lost_motion"}
    with pytest.raises(EffectLibraryError, match="unknown effect kind 'sag'"):
        candidate_effects(CTX, ["sag"])
