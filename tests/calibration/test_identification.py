"""Parameter identification against the emulator's truth (sim_devices.truth)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import OptimizeResult, least_squares
from scipy.stats import chi2

from calibration.effects.identification_report import before_model
from calibration.errors import IdentificationError
from calibration.identify import identifiability, identification
from calibration.identify.identifiability import (
    NO_EFFECT,
    analyze_identifiability,
    analyze_model,
    column_references,
)
from calibration.identify.identification import identify, tracker_sigma_mm
from calibration.identify.levenberg_marquardt import LMSettings, levenberg_marquardt
from calibration.identify.position_residuals import position_residual_jacobian, position_residuals
from calibration.identify.runaway_watch import COLLAPSED, RAN_AWAY
from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel, rotation_from_fixed_xyz, tcp_positions
from calibration.model.registration import RegistrationError, rigid_registration
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign

CASES = [("kr500", 0), ("kr500", 1), ("hp20d", 0), ("kr210_r3100", 2)]


def _run(robot: str, seed: int, settings: CampaignSettings | None = None):
    data = emulated_campaign(robot, seed, settings or CampaignSettings())
    c = data.campaign
    idm = c.mask("identify")
    nominal = KinematicModel.from_description(data.cell.nominal)
    result = identify(nominal, c.q_rad[idm], c.xyz_mm[idm])
    return data, result


@pytest.fixture(scope="module", params=CASES, ids=[f"{r}-{s}" for r, s in CASES])
def case(request):
    return _run(*request.param)


def projected_truth(data, result) -> np.ndarray:
    """The truth in the identified (reduced) parameterization: the reduced model fitted to
    noise-free true TCPs at the true joint angles (exact: the truth is representable)."""
    c = data.campaign
    idm = c.mask("identify")
    free_idx = result.identifiability.free_indices
    args = (
        result.start_model.parameter_vector(),
        free_idx,
        result.start_model,
        data.q_true_rad[idm],
        data.tcp_true_mm[idm],
        np.ones(int(idm.sum())),
    )
    fit = least_squares(
        position_residuals,
        result.model.parameter_vector()[free_idx],
        jac=position_residual_jacobian,
        args=args,
        method="lm",
        xtol=1e-15,
        ftol=1e-15,
    )
    assert np.sqrt(np.mean(fit.fun**2)) < 1e-8  # the truth lies in the reduced family
    return fit.x


def z_scores(data, result) -> tuple[np.ndarray, float]:
    free_idx = result.identifiability.free_indices
    diff = result.model.parameter_vector()[free_idx] - projected_truth(data, result)
    z = diff / np.sqrt(np.diag(result.covariance))
    return z, float(diff @ np.linalg.solve(result.covariance, diff))


def test_validation_error_within_1_1_of_true_model(case):
    data, result = case
    c = data.campaign
    vm = c.mask("validate")
    after = np.linalg.norm(c.xyz_mm[vm] - tcp_positions(result.model, c.q_rad[vm]), axis=1)
    true = np.linalg.norm(c.xyz_mm[vm] - data.tcp_true_mm[vm], axis=1)
    assert result.success
    assert after.mean() <= 1.1 * true.mean()


def test_deviations_match_truth_within_standard_errors(case):
    data, result = case
    z, chi_sq = z_scores(data, result)
    k = len(z)
    assert chi_sq < chi2.ppf(0.999, k)
    assert np.max(np.abs(z)) < 4.0
    assert 0.4 < np.sqrt(np.mean(z**2)) < 1.6


def test_predicted_positions_match_truth_within_standard_errors(case):
    data, result = case
    vm = data.campaign.mask("validate")
    q = data.q_true_rad[vm]
    cov = result.prediction_covariance(q)
    diff = tcp_positions(result.model, q) - data.tcp_true_mm[vm]
    maha = np.einsum("ni,ni->n", diff, np.linalg.solve(cov, diff[:, :, None])[:, :, 0])
    # mean of chi-square(3)/3 over correlated poses: loose band around 1
    assert 0.3 < maha.mean() / 3.0 < 2.5


def test_z_scores_pooled_over_cases():
    zs = []
    for robot, seed in [("kr500", 4), ("hp20d", 5)]:
        data, result = _run(robot, seed, CampaignSettings(n_validate=5))
        zs.append(z_scores(data, result)[0])
    z = np.concatenate(zs)
    assert 0.6 < np.mean(np.abs(z)) < 1.05  # 0.80 for a standard normal
    assert np.mean(np.abs(z) > 2.0) < 0.15  # 4.6 % for a standard normal


def test_dropped_parameters(case):
    _, result = case
    dropped = set(result.identifiability.dropped_names)
    # joint 3 is nearly parallel to joint 2 in every preset: Hayati beta kept, d dropped
    assert "joint3.d_mm" in dropped
    assert "joint3.beta_rad" not in dropped
    # joint 1 is fully coupled with the base pose; the last joint's offsets with the tool
    assert {f"joint1.{p}" for p in ("a_mm", "alpha_rad", "d_mm", "theta_offset_rad")} <= dropped
    assert {"joint6.d_mm", "joint6.theta_offset_rad"} <= dropped
    assert not any(n.startswith(("base.", "tool.")) for n in dropped)
    assert result.identifiability.rank == 27
    assert 1.0 < result.identifiability.condition_number < 1e3
    reasons = {d.name: d.reason for d in result.identifiability.dropped}
    assert "base.rz_rad" in reasons["joint1.theta_offset_rad"]


def test_identifiability_is_decided_from_the_data():
    desc = load_robot("kr500")
    model = KinematicModel.from_description(desc)
    rng = np.random.default_rng(3)
    q = rng.uniform(-1.0, 1.0, (60, 6))
    full = analyze_model(model, q)
    q_fixed = q.copy()
    q_fixed[:, 0] = 0.3  # joint 1 never moves: its axis is not observed
    poor = analyze_model(model, q_fixed)
    assert poor.rank < full.rank
    assert set(full.dropped_names) < set(poor.dropped_names)


def test_same_optimum_as_scipy_least_squares(case):
    data, result = case
    c = data.campaign
    idm = c.mask("identify")
    free_idx = result.identifiability.free_indices
    start = result.start_model
    args = (
        start.parameter_vector(),
        free_idx,
        start,
        c.q_rad[idm],
        c.xyz_mm[idm],
        np.ones(int(idm.sum())),
    )
    ref = least_squares(
        position_residuals,
        start.parameter_vector()[free_idx],
        jac=position_residual_jacobian,
        args=args,
        x_scale="jac",
        method="trf",
        xtol=1e-12,
        ftol=1e-12,
    )
    opt = result.optimize_result
    assert abs(opt.cost - ref.cost) <= 1e-4 * ref.cost
    se = np.sqrt(np.diag(result.covariance))
    assert np.max(np.abs(opt.x - ref.x) / se) < 0.05


def test_result_wraps_optimize_result(case):
    _, result = case
    opt = result.optimize_result
    k = result.identifiability.rank
    m3 = opt.fun.shape[0]
    assert isinstance(opt, OptimizeResult)
    assert opt.x.shape == (k,) and opt.grad.shape == (k,) and opt.jac.shape == (m3, k)
    assert opt.success and opt.status == 1 and opt.nit >= 1
    assert result.covariance.shape == (k, k)
    table = result.parameter_table()
    assert len(table) == 39
    assert all(r["unit"] in ("mm", "deg") for r in table)
    assert sum(r["standard_error"] is not None for r in table) == k


def test_registration_start_without_base_guess():
    data = emulated_campaign("hp20d", 7, CampaignSettings(n_validate=40))
    c = data.campaign
    idm, vm = c.mask("identify"), c.mask("validate")
    guessed = identify(
        KinematicModel.from_description(data.cell.nominal), c.q_rad[idm], c.xyz_mm[idm]
    )
    nominal = KinematicModel.from_description(replace(data.cell.nominal, base=None))
    result = identify(nominal, c.q_rad[idm], c.xyz_mm[idm], start="registration")
    assert result.success and result.start_method == "registration"
    # the registered start is already within millimetres of the true base ...
    base_err = result.start_model.base_mm - data.cell.model.base_mm
    assert np.linalg.norm(base_err) < 20.0
    # ... and the same optimum is reached as from the description's base guess
    assert abs(result.optimize_result.cost - guessed.optimize_result.cost) < 1e-6
    after = np.linalg.norm(c.xyz_mm[vm] - tcp_positions(result.model, c.q_rad[vm]), axis=1)
    true = np.linalg.norm(c.xyz_mm[vm] - data.tcp_true_mm[vm], axis=1)
    assert after.mean() <= 1.1 * true.mean()


def test_lm_recovers_from_a_poor_base_guess():
    data = emulated_campaign("kr500", 8, CampaignSettings(selection=None, n_validate=0))
    desc = data.cell.nominal
    poor = replace(desc.base, x_mm=desc.base.x_mm + 300.0, rz_deg=desc.base.rz_deg + 15.0)
    nominal = KinematicModel.from_description(replace(desc, base=poor))
    c = data.campaign
    result = identify(nominal, c.q_rad, c.xyz_mm, start="description")
    resid = np.linalg.norm(result.residuals_mm(c.q_rad, c.xyz_mm), axis=1)
    assert result.success
    assert resid.mean() < 0.05
    # the damping had to rise above its start at least once or the steps were accepted
    mus = [h[2] for h in result.history]
    assert len(mus) >= 2


def test_robust_loss_reports_and_resists_outliers():
    data = emulated_campaign("kr500", 9, CampaignSettings(selection=None, n_validate=60))
    c = data.campaign
    idm, vm = c.mask("identify"), c.mask("validate")
    pts = c.xyz_mm[idm].copy()
    bad = [5, 42]
    pts[bad] += np.array([1.5, -1.0, 0.8])
    nominal = KinematicModel.from_description(data.cell.nominal)
    plain = identify(nominal, c.q_rad[idm], pts)
    robust = identify(nominal, c.q_rad[idm], pts, loss="cauchy")
    assert set(bad) <= set(np.flatnonzero(plain.outliers))
    assert set(np.flatnonzero(robust.outliers)) >= set(bad)
    assert np.all(robust.pose_weights[bad] < 0.05)

    def val(result):
        return np.linalg.norm(
            c.xyz_mm[vm] - tcp_positions(result.model, c.q_rad[vm]), axis=1
        ).mean()

    clean = identify(nominal, c.q_rad[idm], c.xyz_mm[idm])
    assert val(robust) <= 1.05 * val(clean)
    assert val(plain) > 1.2 * val(clean)


def test_tracker_weights(case):
    data, plain = case
    c = data.campaign
    idm, vm = c.mask("identify"), c.mask("validate")
    nominal = KinematicModel.from_description(data.cell.nominal)
    sigma = tracker_sigma_mm(c.xyz_mm[idm])
    assert np.allclose(sigma, data.cell.tracker.sigma_mm(c.xyz_mm[idm]))
    weighted = identify(nominal, c.q_rad[idm], c.xyz_mm[idm], point_sigma_mm=sigma)
    assert 0.75 < weighted.sigma_mm / weighted.reference_sigma_mm < 1.25
    assert plain.reference_sigma_mm is None
    after = np.linalg.norm(c.xyz_mm[vm] - tcp_positions(weighted.model, c.q_rad[vm]), axis=1)
    true = np.linalg.norm(c.xyz_mm[vm] - data.tcp_true_mm[vm], axis=1)
    assert after.mean() <= 1.1 * true.mean()
    with pytest.raises(IdentificationError, match="sigmas"):
        identify(nominal, c.q_rad[idm], c.xyz_mm[idm], point_sigma_mm=-sigma)


def test_noise_free_data_converge_to_the_truth():
    data = emulated_campaign("kr500", 12, CampaignSettings(selection=None, n_validate=0))
    nominal = KinematicModel.from_description(data.cell.nominal)
    result = identify(nominal, data.q_true_rad, data.tcp_true_mm)
    assert result.success, result.optimize_result.message
    resid = np.linalg.norm(result.residuals_mm(data.q_true_rad, data.tcp_true_mm), axis=1)
    assert resid.max() < 1e-6
    # started at the optimum, the solver stops at once and says it converged
    again = identify(result.model, data.q_true_rad, data.tcp_true_mm)
    assert again.success and again.optimize_result.nit <= 2


def test_bad_arguments_raise_calibration_errors():
    model = KinematicModel.from_description(load_robot("kr500"))
    q = np.zeros((10, 6))
    pts = np.zeros((10, 3))
    with pytest.raises(IdentificationError, match="loss"):
        identify(model, q, pts, loss="tukey")
    with pytest.raises(IdentificationError, match="4 poses"):
        identify(model, q[:3], pts[:3])
    with pytest.raises(IdentificationError, match="finite"):
        identify(model, q, np.full((10, 3), np.nan))
    with pytest.raises(IdentificationError, match="fix"):
        identify(model, q, pts, fixed=("joint9.a_mm",))


def test_fixed_parameters_are_held():
    data = emulated_campaign("kr500", 2, CampaignSettings(selection=None, n_validate=0))
    c = data.campaign
    nominal = KinematicModel.from_description(data.cell.nominal)
    result = identify(nominal, c.q_rad, c.xyz_mm, fixed=("joint2.a_mm",), settings=LMSettings())
    i = nominal.parameter_names().index("joint2.a_mm")
    assert not result.free[i]
    assert result.model.parameter_vector()[i] == nominal.parameter_vector()[i]


def test_rigid_registration_recovers_a_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(0.0, 500.0, (20, 3))
    rot = rotation_from_fixed_xyz(0.3, -0.2, 2.5)
    t = np.array([1000.0, -200.0, 50.0])
    reg = rigid_registration(src, src @ rot.T + t)
    assert np.allclose(reg.rotation, rot, atol=1e-12)
    assert np.allclose(reg.translation_mm, t, atol=1e-9)
    assert reg.rms_mm < 1e-9
    assert np.allclose(rotation_from_fixed_xyz(*reg.fixed_xyz_rad()), rot, atol=1e-12)
    with pytest.raises(RegistrationError, match="collinear"):
        line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
        rigid_registration(line, line)
    with pytest.raises(RegistrationError, match="at least 3"):
        rigid_registration(src[:2], src[:2])


# -- parameters without effect, and fits that run away (issue 17) -----------------------------
def tool_on_last_axis() -> RobotDescription:
    """The kr500 preset with its tool on axis 6 (x = y = 0), as hand-written files have it:
    ∂TCP/∂θ6 = z6 × (p − o6) vanishes at the start point."""
    desc = load_robot("kr500")
    return replace(desc, tool=replace(desc.tool, x_mm=0.0, y_mm=0.0))


@pytest.fixture(scope="module")
def on_axis():
    desc = tool_on_last_axis()
    return desc, emulated_campaign(desc, 1, CampaignSettings())


def identify_campaign(desc: RobotDescription, data, **kwargs):
    c = data.campaign
    idm = c.mask("identify")
    return identify(KinematicModel.from_description(desc), c.q_rad[idm], c.xyz_mm[idm], **kwargs)


def validation_ratio(data, model: KinematicModel) -> float:
    """Validation mean AP of ``model`` over that of the true model, on the same points."""
    c = data.campaign
    vm = c.mask("validate")
    after = np.linalg.norm(c.xyz_mm[vm] - tcp_positions(model, c.q_rad[vm]), axis=1)
    true = np.linalg.norm(c.xyz_mm[vm] - data.true_prediction_mm[vm], axis=1)
    return float(after.mean() / true.mean())


def assert_finite_standard_errors(result) -> None:
    se = result.standard_errors()
    assert np.all(np.isfinite(se[result.free])) and np.all(se[result.free] > 0)
    assert np.all(np.isnan(se[~result.free]))  # NaN means dropped, nothing else
    assert all(
        (r["standard_error"] is not None) == r["identified_from_data"]
        for r in result.parameter_table()
    )


def test_tool_on_the_last_axis_drops_the_joint6_offset(on_axis):
    desc, data = on_axis
    result = identify_campaign(desc, data)
    reasons = {d.name: d.reason for d in result.identifiability.dropped}
    assert result.success, result.optimize_result.message
    assert reasons["joint6.theta_offset_rad"] == "no effect on the measured positions"
    assert np.all(np.isfinite(result.parameter_vector()))
    assert_finite_standard_errors(result)
    assert validation_ratio(data, result.model) <= 1.1


def test_vanishing_columns_are_judged_in_their_units():
    """Rounding noise in an angle's column (mm/rad) is no effect; an effect term's column
    (arbitrary units) is only no effect when exactly zero, else scaled like any other."""
    model = KinematicModel.from_description(load_robot("kr500"))
    rng = np.random.default_rng(0)
    geo = rng.normal(size=(60, model.n_parameters))
    noise = 1e-13 * rng.normal(size=60)
    i = model.parameter_names().index("joint6.theta_offset_rad")
    geo[:, i] = noise
    extra = np.column_stack([noise, np.zeros(60)])  # two effect columns
    jac = np.column_stack([geo, extra])
    names = [*model.parameter_names(), "e1_mm", "e2_mm"]
    refs = column_references(model, n_extra=2)
    ana = analyze_identifiability(jac, names, references=refs)
    reasons = {d.name: d.reason for d in ana.dropped}
    assert reasons == {"joint6.theta_offset_rad": NO_EFFECT, "e2_mm": NO_EFFECT}
    assert ana.column_scale[i] == 1.0
    # without references (the old rule), the noise column is scaled up and kept
    assert analyze_identifiability(jac, names).free[i]


def test_a_parameter_that_runs_away_is_dropped_and_the_fit_restarts(on_axis, monkeypatch):
    """Without the start-point test, θ6 runs away in the first step: it is dropped, named,
    and the fit starts again without it."""
    desc, data = on_axis
    monkeypatch.setattr(identifiability, "NO_EFFECT_TOL", 0.0)
    result = identify_campaign(desc, data)
    reasons = {d.name: d.reason for d in result.identifiability.dropped}
    assert reasons["joint6.theta_offset_rad"].startswith(RAN_AWAY)
    assert "beyond ±180°" in reasons["joint6.theta_offset_rad"]
    assert [h[0] for h in result.history].count(0) == 2  # the start and one restart
    assert result.success
    assert_finite_standard_errors(result)
    assert validation_ratio(data, result.model) <= 1.1
    monkeypatch.setattr(identification, "MAX_RESTARTS", 0)
    with pytest.raises(IdentificationError, match=r"joint6\.theta_offset_rad ran away"):
        identify_campaign(desc, data)


def test_a_column_that_collapses_during_the_iterations_is_dropped(monkeypatch):
    data = emulated_campaign("kr500", 2, CampaignSettings(selection=None, n_validate=40))
    desc = data.cell.nominal
    nominal = KinematicModel.from_description(desc)
    target = nominal.parameter_names().index("joint2.a_mm")

    def collapsing(x_free, x_full, free_idx, *rest):
        """The real Jacobian, with joint2.a_mm's column gone once the fit has moved."""
        jac = position_residual_jacobian(x_free, x_full, free_idx, *rest)
        if target in free_idx and not np.array_equal(x_free, x_full[free_idx]):
            jac[:, list(free_idx).index(target)] *= 1e-8
        return jac

    monkeypatch.setattr(identification, "position_residual_jacobian", collapsing)
    result = identify_campaign(desc, data)
    reasons = {d.name: d.reason for d in result.identifiability.dropped}
    assert reasons["joint2.a_mm"].startswith(COLLAPSED)
    assert result.success and not result.free[target]
    assert_finite_standard_errors(result)


def test_lm_status_says_converged_or_failed():
    one = np.array([[1.0]])
    # a kink at the start: no step of any damping lowers the finite error norm: converged
    kink = levenberg_marquardt(lambda x: np.array([1.0 + 1e9 * abs(x[0])]), lambda x: one, [0.0])
    assert kink.status == -1 and kink.success
    # residuals not finite away from the start at any damping: ran away
    cliff = levenberg_marquardt(
        lambda x: np.array([1.0 if x[0] == 0.0 else np.nan]), lambda x: one, [0.0]
    )
    assert cliff.status == -2 and not cliff.success
    # the iteration limit before convergence
    short = levenberg_marquardt(
        lambda x: x - 5.0, lambda x: one, [0.0], settings=LMSettings(max_iterations=1)
    )
    assert short.status == 0 and not short.success


@pytest.mark.slow
@pytest.mark.parametrize("robot", ["kr500", "hp20d", "kr210_r3100"])
def test_many_seeds(robot):
    ratios, zs, before_ap, after_ap, true_ap = [], [], [], [], []
    for seed in range(10, 20):
        data, result = _run(robot, seed)
        c = data.campaign
        idm, vm = c.mask("identify"), c.mask("validate")
        reference = before_model(result.start_model, c.q_rad[idm], c.xyz_mm[idm])
        before = np.linalg.norm(c.xyz_mm[vm] - tcp_positions(reference, c.q_rad[vm]), axis=1)
        after = np.linalg.norm(c.xyz_mm[vm] - tcp_positions(result.model, c.q_rad[vm]), axis=1)
        true = np.linalg.norm(c.xyz_mm[vm] - data.tcp_true_mm[vm], axis=1)
        before_ap.append(before.mean())
        after_ap.append(after.mean())
        true_ap.append(true.mean())
        ratios.append(after.mean() / true.mean())
        z, chi_sq = z_scores(data, result)
        assert chi_sq < chi2.ppf(0.9999, len(z))
        zs.append(z)
    z = np.concatenate(zs)
    print(
        f"\n{robot}, 10 seeds, validation mean AP (mm): before {np.mean(before_ap):.4f}, "
        f"after {np.mean(after_ap):.4f}, true model {np.mean(true_ap):.4f}; after/true "
        f"max {max(ratios):.3f} mean {np.mean(ratios):.3f}; z over {len(z)} parameters: "
        f"mean|z| {np.mean(np.abs(z)):.3f} rms {np.sqrt(np.mean(z**2)):.3f} "
        f"max|z| {np.max(np.abs(z)):.2f} P(|z|>2) {np.mean(np.abs(z) > 2):.3f}"
    )
    assert max(ratios) <= 1.1
    assert 0.7 < np.mean(np.abs(z)) < 0.95
    assert 0.85 < np.sqrt(np.mean(z**2)) < 1.2
    assert np.max(np.abs(z)) < 5.0


@pytest.mark.slow
def test_random_poses_for_comparison():
    """The source's protocol (random identification poses, no selection), for the docs."""
    ratios = []
    for seed in range(10, 20):
        data, result = _run("kr500", seed, CampaignSettings(selection=None))
        c = data.campaign
        vm = c.mask("validate")
        after = np.linalg.norm(c.xyz_mm[vm] - tcp_positions(result.model, c.q_rad[vm]), axis=1)
        true = np.linalg.norm(c.xyz_mm[vm] - data.tcp_true_mm[vm], axis=1)
        ratios.append(after.mean() / true.mean())
    print(f"\nkr500 random poses, 10 seeds: after/true max {max(ratios):.3f} "
          f"mean {np.mean(ratios):.3f}")  # fmt: skip
    assert max(ratios) <= 1.2


@pytest.mark.slow
def test_tracker_weights_many_seeds():
    """Unweighted against data-sheet weighted: z statistics and flagged (false) outliers."""
    stats = {}
    for weighted in (False, True):
        zs, flagged, noise = [], 0, []
        for robot in ("kr500", "hp20d"):
            for seed in range(30, 38):
                data = emulated_campaign(robot, seed)
                c = data.campaign
                idm = c.mask("identify")
                nominal = KinematicModel.from_description(data.cell.nominal)
                sigma = tracker_sigma_mm(c.xyz_mm[idm]) if weighted else None
                result = identify(nominal, c.q_rad[idm], c.xyz_mm[idm], point_sigma_mm=sigma)
                zs.append(z_scores(data, result)[0])
                flagged += int(result.outliers.sum())
                if weighted:
                    noise.append(result.sigma_mm / result.reference_sigma_mm)
        z = np.concatenate(zs)
        stats[weighted] = (np.sqrt(np.mean(z**2)), flagged)
        extra = f", noise/stated {np.mean(noise):.3f}" if weighted else ""
        label = "weighted" if weighted else "unweighted"
        rms = stats[weighted][0]
        print(f"\n{label}, 16 campaigns: rms z {rms:.3f}, flagged {flagged} of 1600 poses{extra}")
    assert stats[True][1] <= stats[False][1]
    assert 0.85 < stats[True][0] < 1.2
