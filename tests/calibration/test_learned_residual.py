"""The learned residual stage: its Gaussian process, its storage, its use, and what it
recovers of an effect the library does not have.

The undeclared effect comes from a physical parameter set of the test's own, applied to
the emulator's own forward model (``TrueCell.tcp_mm``): a dress pack (cable and hose
bundle) of 400 N effective pull hangs from the forearm and bends it down, by
``F L³ / (3 E I)`` (a 1.2 m aluminium tube, 150/130 mm: 0.30 mm) times a shape of the arm
posture, ``cos²(q2 + q3) · (1 + cos q4)/2`` (the forearm's horizontal reach and the
pack's wind-up on joint 4). No candidate of the library describes it; the twin gets the
campaign and the nominal description, never the shape. Accuracy is judged on 1000 fresh
poses against the emulator's truth.
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from calibration.cli import main
from calibration.effects.calibrate import CalibrationResult, calibrate
from calibration.effects.closed_loop import LoopSettings
from calibration.effects.learned_residual import (
    Hyperparameters,
    LearnedResidual,
    _neg_log_likelihood,
    fit_learned_residual,
    loo_gain,
    stored,
    validation_extra_sd,
)
from calibration.effects.model_effects import predict_tcp, predict_tcp_sd
from calibration.errors import DescriptionError
from calibration.identify.campaign_files import read_points
from calibration.model.description import ResidualDescription, RobotDescription, load_robot
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import (
    CampaignData,
    CampaignSettings,
    emulated_campaign,
    sample_reachable_poses,
)

# -- the Gaussian process ----------------------------------------------------------------


def smooth_data(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n, 3))
    y = np.column_stack([np.sin(q[:, 0]), np.cos(q[:, 1]) * 0.5, np.sin(q[:, 2] + q[:, 0])])
    return q, 0.1 * y + rng.normal(0, 0.01, (n, 3))


def test_likelihood_gradient_matches_finite_differences():
    q, y = smooth_data(40)
    theta = np.array([0.3, -0.2, 0.1, math.log(0.08), math.log(0.02)])
    value, grad = _neg_log_likelihood(theta, q, y)
    for i in range(len(theta)):
        step = np.zeros_like(theta)
        step[i] = 1e-6
        fd = (
            _neg_log_likelihood(theta + step, q, y)[0] - _neg_log_likelihood(theta - step, q, y)[0]
        ) / 2e-6
        assert fd == pytest.approx(grad[i], rel=1e-5, abs=1e-6), i
    assert np.isfinite(value)


def test_leave_one_out_errors_equal_refits_without_each_pose():
    q, y = smooth_data(30)
    hyper = Hyperparameters((1.0, 0.7, 1.3), 0.1, 0.02)
    model = LearnedResidual(q, y, hyper, traced_sd_mm=0.1)
    loo = model.loo_residuals()
    for i in (0, 7, 29):
        keep = np.arange(30) != i
        sub = LearnedResidual(q[keep], y[keep], hyper, traced_sd_mm=0.1)
        assert np.allclose(y[i] - sub.predict(q[i : i + 1]).mean_mm[0], loo[i], atol=1e-9)


def test_variance_projection_matches_the_exact_variance():
    q, y = smooth_data(400, seed=1)
    model = fit_learned_residual(q, y)
    qx = np.random.default_rng(5).uniform(-np.pi, np.pi, (300, 3))
    pred = model.predict(qx)
    exact = model.exact_latent_variance(qx)
    approx = pred.sd_mm**2 - model.hyper.noise_sd_mm**2
    # 2 % of the predictive variance a user reads (noise included): 1 % of its sd
    assert np.max(np.abs(approx - exact)[pred.within_reach]) < 0.02 * np.min(pred.sd_mm**2)


def test_the_kernel_is_periodic_in_each_joint():
    q, y = smooth_data(200, seed=2)
    model = fit_learned_residual(q, y)
    a = np.array([[math.radians(179.999), 0.3, -1.0]])
    b = np.array([[math.radians(-180.001), 0.3, -1.0]])
    assert np.allclose(model.predict(a).mean_mm, model.predict(b).mean_mm, atol=1e-9)


def test_a_pose_beyond_the_reach_gets_the_traced_model_and_says_so():
    q = np.random.default_rng(3).uniform(-0.3, 0.3, (50, 3))
    y = 0.1 * np.sin(q) + np.random.default_rng(4).normal(0, 0.01, (50, 3))
    model = LearnedResidual(q, y, Hyperparameters((0.2, 0.2, 0.2), 0.1, 0.01), 0.123)
    pred = model.predict(np.array([[0.0, 0.0, 0.0], [3.0, 3.0, 3.0]]))
    assert pred.within_reach.tolist() == [True, False]
    assert np.all(pred.mean_mm[1] == 0.0) and pred.sd_mm[1] == 0.123
    assert np.linalg.norm(pred.mean_mm[0]) > 0 and pred.sd_mm[0] < 0.05


def test_a_pose_beyond_the_reach_never_gets_less_than_the_processs_prior_sd():
    q = np.random.default_rng(3).uniform(-0.3, 0.3, (50, 3))
    y = 0.1 * np.sin(q) + np.random.default_rng(4).normal(0, 0.01, (50, 3))
    hyper = Hyperparameters((0.2, 0.2, 0.2), 0.1, 0.01)
    model = LearnedResidual(q, y, hyper, traced_sd_mm=0.05, extra_sd_mm=0.02)
    sd = model.predict(np.array([[3.0, 3.0, 3.0]])).sd_mm[0]
    assert sd == pytest.approx(math.sqrt(0.1**2 + 0.01**2 + 0.02**2))  # not the traced 0.05


def _smooth_noise(n: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n, 3))
    f = np.column_stack([np.sin(q[:, 0]), np.cos(q[:, 1]) * 0.5, np.sin(q[:, 2] + q[:, 0])])
    return q, 0.1 * f + rng.normal(0, noise, (n, 3))


def test_the_validation_poses_widen_a_too_narrow_sd_and_never_narrow_it():
    """Identification residuals quieter than the errors elsewhere (the traced model's
    in-sample fit): δ makes the validation z RMS 1, and fresh poses of the same noise
    score about 1 too; validation poses quieter than the fit leave the sd alone."""
    q, y = _smooth_noise(300, 0.01, 1)
    model = fit_learned_residual(q, y)
    qv, yv = _smooth_noise(150, 0.03, 2)
    extra = validation_extra_sd(model, qv, yv)
    wide = replace(model, extra_sd_mm=extra)
    pv = wide.predict(qv)
    assert np.sqrt(np.mean(((yv - pv.mean_mm) / pv.sd_mm[:, None]) ** 2)) == pytest.approx(1.0)
    assert np.all(wide.predict(qv).mean_mm == model.predict(qv).mean_mm)  # the mean untouched
    qh, yh = _smooth_noise(2000, 0.03, 3)
    ph, narrow = wide.predict(qh), model.predict(qh)
    z_before = np.sqrt(np.mean(((yh - narrow.mean_mm) / narrow.sd_mm[:, None]) ** 2))
    z_after = np.sqrt(np.mean(((yh - ph.mean_mm) / ph.sd_mm[:, None]) ** 2))
    assert z_before > 2.0 and 0.9 < z_after < 1.1, (z_before, z_after)
    assert validation_extra_sd(model, *_smooth_noise(150, 0.005, 4)) == 0.0


# -- stored with the model -----------------------------------------------------------------


def described(robot: str = "kr500", lengths: float = 0.3) -> RobotDescription:
    """The preset with a hand-made learned stage on 40 poses near its Home."""
    desc = load_robot(robot)
    rng = np.random.default_rng(8)
    q = np.radians(desc.home) + rng.uniform(-0.2, 0.2, (40, desc.n_joints))
    r = 0.05 * np.sin(3 * q[:, :3]) + rng.normal(0, 0.005, (40, 3))
    hyper = Hyperparameters((lengths,) * desc.n_joints, 0.05, 0.005)
    return replace(desc, residual=ResidualDescription(0.07, stored(q, r, hyper)))


def test_the_stage_reads_back_identically():
    desc = described()
    g = desc.residual.learned  # type: ignore[union-attr]
    desc = replace(desc, residual=ResidualDescription(0.07, replace(g, extra_sd_mm=0.011)))  # type: ignore[arg-type]
    again = RobotDescription.loads(desc.dumps())
    assert again.residual is not None and again.residual.learned is not None
    assert again.residual.learned.q_deg == desc.residual.learned.q_deg  # type: ignore[union-attr]
    assert again.residual.learned.extra_sd_mm == 0.011
    q = np.radians(desc.home) + np.random.default_rng(9).uniform(-0.3, 0.3, (20, 6))
    a, b = predict_tcp_sd(desc, q), predict_tcp_sd(again, q)
    assert np.array_equal(a.points_mm, b.points_mm) and np.array_equal(a.sd_mm, b.sd_mm)
    assert np.array_equal(predict_tcp(again, q), a.points_mm)
    plain = replace(desc, residual=None)
    assert np.max(np.abs(predict_tcp(desc, q) - predict_tcp(plain, q))) > 1e-3  # applied


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace('kernel = "periodic_ard_se"', 'kernel = "rbf"'), "key 'kernel'"),
        (lambda t: t.replace("traced_sd_mm = 0.07", "traced_sd_mm = -1.0"), "key 'traced_sd_mm'"),
        (lambda t: t.replace("[residual.learned]", "[residual.learned]\nextra = 1"), "key 'extra'"),
        (lambda t: t.replace("extra_sd_mm = 0.0", "extra_sd_mm = -0.01"), "key 'extra_sd_mm'"),
    ],
)
def test_a_bad_stage_is_refused_naming_its_key(edit, message):
    text = edit(described().dumps())
    with pytest.raises(DescriptionError, match=message):
        RobotDescription.loads(text, "cal.toml")


def test_a_stage_stored_before_extra_sd_mm_reads_with_none():
    text = described().dumps()
    assert "extra_sd_mm = 0.0\n" in text
    old = RobotDescription.loads(text.replace("extra_sd_mm = 0.0\n", ""), "cal.toml")
    assert old.residual is not None and old.residual.learned is not None
    assert old.residual.learned.extra_sd_mm == 0.0


def test_rows_must_match_their_residuals():
    desc = described()
    g = desc.residual.learned  # type: ignore[union-attr]
    short = replace(desc.residual, learned=replace(g, residual_mm=g.residual_mm[:-1]))  # type: ignore[arg-type]
    with pytest.raises(DescriptionError, match="key 'residual_mm': 39 rows for 40 rows of q_deg"):
        RobotDescription.loads(replace(desc, residual=short).dumps(), "cal.toml")


def test_twin_predict_writes_sd_and_flags_poses_beyond_reach(tmp_path, capsys):
    desc = described()
    model = tmp_path / "cal.toml"
    desc.save(model)
    near = np.array(desc.home) + 2.0
    far = np.array(desc.home) + np.array([60.0, 30.0, -30.0, 90.0, 40.0, 90.0])
    joints = tmp_path / "joints.csv"
    header = "pose,t_s," + ",".join(f"q{i}_deg" for i in range(1, 7))
    rows = [f"{p},0.0," + ",".join(f"{v:.6f}" for v in q) for p, q in (("a", near), ("b", far))]
    joints.write_text("\n".join([header, *rows]) + "\n")
    out = tmp_path / "points.csv"
    assert main(["predict", "--model", str(model), "--data", str(joints), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "1 row(s) outside the learned residual stage's reach" in err
    text = out.read_text().splitlines()
    assert text[0] == "pose,x_mm,y_mm,z_mm,sd_mm,beyond_reach"
    assert text[1].endswith(",0") and text[2].endswith(",1")
    assert float(text[2].split(",")[4]) == pytest.approx(0.07)
    assert read_points(out)[1].shape == (2, 3)  # the reader still reads it


# -- emulated: what the stage recovers, and that it stays out of clean data -------------

HOSE_PULL_N, TUBE_MM, TUBE_E_N_PER_MM2 = 400.0, 1200.0, 7.0e4
TUBE_I_MM4 = math.pi / 64 * (150.0**4 - 130.0**4)


def dress_pack_mm(data: CampaignData, q_rad: np.ndarray) -> np.ndarray:
    """The dress pack's downward bending of the forearm ``(m, 3)`` mm, tracker frame."""
    sag = HOSE_PULL_N * TUBE_MM**3 / (3 * TUBE_E_N_PER_MM2 * TUBE_I_MM4)
    shape = np.cos(q_rad[:, 1] + q_rad[:, 2]) ** 2 * (1 + np.cos(q_rad[:, 3])) / 2
    down = -data.cell.model.base_rotation()[:, 2]  # the robot base's −z in the tracker frame
    return (sag * shape)[:, None] * down


@cache
def emulated(
    seed: int, effect: bool, kinds: tuple[str, ...] | None, library: tuple[str, ...] = ()
) -> tuple[CampaignData, CalibrationResult]:
    """1000 identification poses (random: a learned stage needs them spread; the issue's
    largest real campaign), 150 validation; ``library``: the emulator's undeclared effects
    switched on (:data:`sim_devices.effects.EFFECT_NAMES`)."""
    settings = CampaignSettings(
        n_identify=1000, selection=None, effects=UndeclaredEffects.named(*library)
    )
    data = emulated_campaign("kr500", seed, settings)
    campaign = data.campaign
    if effect:
        campaign = replace(campaign, xyz_mm=campaign.xyz_mm + dress_pack_mm(data, data.q_true_rad))
    loop = LoopSettings(kinds=kinds) if kinds else LoopSettings()
    return data, calibrate(data.cell.nominal, campaign, loop_settings=loop)


def held_out(seed: int, effect: bool, kinds: tuple[str, ...] | None) -> dict[str, float]:
    """On 1000 fresh poses: the learned stage's share of the traced model's error against
    the truth, and the RMS z-score of tracker readings against the prediction."""
    data, cal = emulated(seed, effect, kinds)
    q = sample_reachable_poses(data.cell.nominal, 1000, np.random.default_rng([seed, 99]))
    truth = data.cell.tcp_mm(q) + (dress_pack_mm(data, q) if effect else 0.0)
    twin = predict_tcp_sd(cal.description, q)
    traced = predict_tcp(replace(cal.description, residual=None), q)
    e_twin = np.linalg.norm(twin.points_mm - truth, axis=1).mean()
    e_traced = np.linalg.norm(traced - truth, axis=1).mean()
    read, ok = data.cell.tracker.measure(truth, np.random.default_rng([seed, 98]))
    z = (read - twin.points_mm)[ok] / twin.sd_mm[ok, None]
    assert cal.learned is not None
    return {
        "accepted": float(cal.learned.accepted),
        "recovered": 1.0 - e_twin / e_traced,
        "z_rms": float(np.sqrt(np.mean(z**2))),
    }


#: The fast tests offer the loop only the gravity candidate (the loop's generic harmonics
#: take a part of the dress pack's shape and the 77-candidate search costs 10 s a seed):
#: the learned stage then sees all of it. The slow sweep offers every candidate.
FAST_KINDS = ("gravity_deflection",)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_undeclared_smooth_effect_is_learned(seed):
    r = held_out(seed, True, FAST_KINDS)
    assert r["accepted"] == 1.0
    assert r["recovered"] >= 0.7, r
    assert 0.8 <= r["z_rms"] <= 1.25, r


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_clean_data_keep_no_learned_stage(seed):
    r = held_out(seed, False, FAST_KINDS)
    assert r["accepted"] == 0.0, r
    assert 0.8 <= r["z_rms"] <= 1.25, r


@pytest.mark.slow
def test_twenty_seeds_the_effect_is_learned():
    """``pytest -m slow tests/calibration/test_learned_residual.py``: the fast test over 20 seeds.

    With every candidate offered the loop first adds generic harmonics of joint 4 that take
    a part of the shape, and the stage recovers less of what is left: 0.574 at worst over 20
    seeds (the final twin no less accurate; docs/closed-loop.md); this sweep checks the
    stage on the whole effect."""
    effect = [held_out(seed, True, FAST_KINDS) for seed in range(1, 21)]
    assert min(r["recovered"] for r in effect) >= 0.7, effect
    for r in effect:
        assert r["accepted"] == 1.0 and 0.8 <= r["z_rms"] <= 1.25, r


@pytest.mark.slow
def test_twenty_clean_seeds_every_candidate():
    """Clean data, every candidate kind offered: the stage is kept in at most 1 of 20."""
    clean = [held_out(seed, False, None) for seed in range(1, 21)]
    assert sum(r["accepted"] for r in clean) <= 1, clean
    for r in clean:
        assert 0.8 <= r["z_rms"] <= 1.25, r


#: Effects the library has, from the emulator's own physics: the gravity deflection of its
#: masses and stiffnesses, joint 1's grating ovality (order 2), a 20 ppm tracker scale.
LIBRARY_EFFECTS = ("gravity_deflection", "grating_cyclic", "tracker_scale")
#: The fast test offers the loop the kinds that describe them (the 20 ppm scale about the
#: tracker is mostly taken by the base and link lengths: the loop need not name it).
LIBRARY_KINDS = ("gravity_deflection", "joint_harmonic", "instrument_scale")


@pytest.mark.parametrize("seed", [1, 2])
def test_effects_all_in_the_library_keep_no_learned_stage(seed):
    _data, cal = emulated(seed, False, LIBRARY_KINDS, LIBRARY_EFFECTS)
    assert cal.loop is not None and cal.learned is not None
    kinds = {s.kind for s in cal.loop.added}
    assert {"gravity_deflection", "joint_harmonic"} <= kinds, cal.loop.added  # named first
    assert not cal.learned.accepted, cal.learned


@pytest.mark.slow
def test_twenty_seeds_effects_all_in_the_library_every_candidate():
    """``pytest -m slow tests/calibration/test_learned_residual.py -k library``: effects
    all in the library, every candidate kind offered, 20 seeds: the stage is kept in at
    most 1 (issue 29)."""
    stages = [emulated(seed, False, None, LIBRARY_EFFECTS)[1].learned for seed in range(1, 21)]
    kept = [(seed, s.p_value) for seed, s in enumerate(stages, start=1) if s and s.accepted]
    assert len(kept) <= 1, kept


@pytest.mark.slow
def test_the_gain_tests_spread_is_that_of_white_residuals():
    """White residuals (Gaussian and Student-t with 5 degrees of freedom), hyperparameters
    held: the gain's standardised score has mean 0 and sd 1, and the test (centred on a
    zero gain, above the white residuals' mean) rejects about its level at 5 %. (The
    per-pose paired t-test it replaces spread its scores by √2: it rejected 12.5 % at 5 %
    here, docs/closed-loop.md.) 300 draws, ~15 s: `pytest -m slow -k gain_tests_spread`."""
    rng = np.random.default_rng(29)
    hyper = Hyperparameters((0.5,) * 6, 0.006, 0.02)
    z, p = [], []
    for rep in range(300):
        q = rng.uniform(-np.pi, np.pi, (120, 6))
        y = 0.02 * (rng.standard_t(5, (120, 3)) if rep % 2 else rng.normal(size=(120, 3)))
        g = loo_gain(LearnedResidual(q, y, hyper, traced_sd_mm=0.02).loo_operator(), y)
        z.append((g.gain - g.null_mean) / g.null_sd)
        p.append(g.p_value)
    assert abs(np.mean(z)) < 0.15 and 0.87 < np.std(z) < 1.13, (np.mean(z), np.std(z))
    assert np.mean(np.asarray(p) < 0.05) <= 0.05 + 0.03


def test_the_gain_test_sees_a_smooth_residual():
    q, y = smooth_data(120, seed=4)
    model = fit_learned_residual(q, y)
    assert loo_gain(model.loo_operator(), y).p_value < 1e-6
    loo = model.loo_residuals()
    assert loo_gain(model.loo_operator(), y).gain == pytest.approx(np.sum(y**2) - np.sum(loo**2))


def test_tracking_holds_the_learned_stage_with_the_effects():
    """``twin track``'s held terms are the description's prediction minus its geometry,
    the learned stage included (a model with a stage and no ``[[effect]]`` too)."""
    from calibration.effects.model_effects import predict_tcp
    from calibration.model.kinematics import KinematicModel, tcp_positions
    from calibration.twin.tracking import effect_offsets

    desc = described()
    assert not desc.effects
    q = np.radians(np.array(desc.home))[None, :] + np.linspace(-0.2, 0.2, 5)[:, None]
    t = np.arange(5.0)
    expected = predict_tcp(desc, q, t) - tcp_positions(KinematicModel.from_description(desc), q)
    assert np.abs(expected).max() > 1e-6  # the stage moves these poses
    np.testing.assert_array_equal(effect_offsets(desc, q, t), expected)


def test_the_report_states_the_sds_widening_by_the_validation_poses():
    """report.json and report.md say the validation z RMS with the fitted noise and the
    extra sd it asked for (0: not widened, never narrowed)."""
    from calibration.effects.identification_report import learned_residual_document
    from calibration.effects.report_rendering import _learned_markdown

    _, cal = emulated(1, True, FAST_KINDS)
    assert cal.learned is not None
    doc = learned_residual_document(cal.learned)
    assert doc["extra_sd_mm"] == cal.learned.extra_sd_mm >= 0.0
    z = doc["validate_z_rms_before_extra_sd"]
    assert z is not None and z == pytest.approx(cal.learned.validate_z_rms)
    text = "\n".join(_learned_markdown(doc))
    assert f"z RMS {z:.2f} with the fitted noise" in text
    assert ("widened by" in text) == (cal.learned.extra_sd_mm > 0)
