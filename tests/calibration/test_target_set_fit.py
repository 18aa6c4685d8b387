"""Rotation of a target set about one axis: short arcs, honest uncertainties, CRB, wild points.

The synthetic cell: a link turning about an arbitrarily tilted axis 2.5 m from the tracker,
carrying reflectors on an equilateral triangle of side 360 mm; tracker noise as the
emulator's model, per-axis σ = (15 µm + 6 µm/m · distance) / 2.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.errors import CalibrationError, TargetSetFitError
from calibration.scales.circle_fit import fit_circle_3d
from calibration.scales.relation_fit import crb_covariance
from calibration.scales.target_set_fit import crb_covariance_targets, fit_target_set
from calibration.scales.target_set_model import TargetSetGeometry

SIDE_MM = 360.0


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` about the unit ``axis``."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def tracker_sigma_mm(points: np.ndarray) -> np.ndarray:
    """Per-axis σ of the emulator's tracker at the points' distances (tracker at the origin)."""
    return 1e-3 * (15.0 + 6.0 * np.linalg.norm(points, axis=-1) / 1000.0) / 2.0


class Cell:
    """Reflectors on a link turning about a known axis; the truth of one sweep."""

    def __init__(self, arc_deg: float, n_stops: int, rng: np.random.Generator, targets=3):
        n = rng.normal(size=3)
        self.normal = n / np.linalg.norm(n)
        direction = rng.normal(size=3)
        self.axis_point = 2500.0 * direction / np.linalg.norm(direction)
        e1 = np.cross(self.normal, rng.normal(size=3))
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(self.normal, e1)
        # the triangle (circumradius side/√3) tilted on its mount, 500 mm out from the axis
        circum = SIDE_MM / np.sqrt(3.0)
        ang = 2 * np.pi * np.arange(3) / 3 + rng.uniform(0, 2 * np.pi)
        local = np.column_stack([circum * np.cos(ang), circum * np.sin(ang), np.zeros(3)])
        local = local @ rotation(np.array([1.0, 0.0, 0.0]), rng.uniform(-0.6, 0.6)).T
        local += [500.0, 0.0, 100.0]
        frame = np.stack([e1, e2, self.normal])
        self.home = (self.axis_point + local @ frame)[:targets]  # (T, 3) at θ = 0
        self.theta = np.radians(np.linspace(0.0, arc_deg, n_stops))
        self.true_points = (
            np.stack(
                [(self.home - self.axis_point) @ rotation(self.normal, t).T for t in self.theta]
            )
            + self.axis_point
        )
        self.sigma = tracker_sigma_mm(self.true_points)  # (K, T)
        self.points = (
            self.true_points + rng.normal(size=self.true_points.shape) * self.sigma[..., None]
        )

    def geometry(self) -> TargetSetGeometry:
        """The truth in the fit's gauge: axis_u through target 0 at stop 0 (θ_0 = 0)."""
        w = self.home - self.axis_point
        h = w @ self.normal
        radial = w - np.outer(h, self.normal)
        u = radial[0] / np.linalg.norm(radial[0])
        v = np.cross(self.normal, u)
        return TargetSetGeometry(
            self.axis_point,
            self.normal,
            u,
            h,
            np.linalg.norm(radial, axis=1),
            np.arctan2(radial @ v, radial @ u),
        )


def increment_error(angles: np.ndarray, theta: np.ndarray) -> np.ndarray:
    return (angles - angles[0]) - (theta - theta[0])


def test_the_generator_is_the_model():
    cell = Cell(30.0, 10, np.random.default_rng(0))
    np.testing.assert_allclose(
        cell.geometry().positions_mm(cell.theta), cell.true_points, atol=1e-9
    )
    assert np.linalg.norm(cell.true_points, axis=-1).min() > 1500
    assert np.linalg.norm(cell.true_points, axis=-1).max() < 4000
    sides = np.linalg.norm(cell.home - np.roll(cell.home, 1, axis=0), axis=1)
    np.testing.assert_allclose(sides, SIDE_MM)


@pytest.mark.parametrize("targets", [2, 3])
@pytest.mark.parametrize(("arc_deg", "n_stops"), [(4.0, 10), (90.0, 46), (470.0, 236)])
def test_noise_free_target_sets_are_fitted_exactly(targets, arc_deg, n_stops):
    cell = Cell(arc_deg, n_stops, np.random.default_rng(1), targets)
    fit = fit_target_set(cell.true_points, cell.sigma)
    truth = cell.geometry()
    assert fit.n_targets == targets
    np.testing.assert_allclose(fit.radii_mm, truth.radii_mm, atol=1e-7)
    assert fit.normal @ truth.normal == pytest.approx(1.0, abs=1e-12)  # angles increase
    offset = np.cross(fit.centre_mm - cell.axis_point, truth.normal)  # on the true axis
    assert np.linalg.norm(offset) < 1e-7
    angles = fit.unwrapped_angle_rad()
    np.testing.assert_allclose(increment_error(angles, cell.theta), 0.0, atol=1e-11)
    assert fit.outlier_points == ()
    assert fit.residual_rms_mm < 1e-9


@pytest.mark.parametrize(
    ("arc_deg", "n_stops", "min_ratio"),
    [(4.0, 10, 3.0), (20.0, 11, 1.0), (90.0, 46, 1.0), (470.0, 236, 1.0)],
)
def test_three_reflectors_beat_one_on_short_arcs(arc_deg, n_stops, min_ratio):
    """Issue 18 item 3: on a 4° arc with 10 stops, increments ≥ 3× better than the circle."""
    one, three = [], []
    for seed in range(24):
        cell = Cell(arc_deg, n_stops, np.random.default_rng(10 + seed))
        circle = fit_circle_3d(cell.points[:, 0], cell.sigma[:, 0])
        fit = fit_target_set(cell.points, cell.sigma)
        one.append(increment_error(circle.unwrapped_angle_rad(), cell.theta)[1:])
        three.append(increment_error(fit.unwrapped_angle_rad(), cell.theta)[1:])
    rms_one = np.sqrt(np.mean(np.square(one)))
    rms_three = np.sqrt(np.mean(np.square(three)))
    ratio = rms_one / rms_three
    arcsec = np.degrees(1.0) * 3600.0
    print(
        f"\n{arc_deg:g}° arc, {n_stops} stops, 24 seeds: increment RMS error "
        f"1 target {rms_one * arcsec:.3f}″, 3 targets {rms_three * arcsec:.3f}″, "
        f"ratio {ratio:.1f}"
    )
    assert ratio >= min_ratio


@pytest.mark.parametrize(("arc_deg", "n_stops"), [(4.0, 10), (90.0, 46)])
def test_angle_uncertainty_is_calibrated(arc_deg, n_stops):
    """z-scores of recovered increments over seeds have a standard deviation ≈ 1."""
    zs = []
    for seed in range(50):
        cell = Cell(arc_deg, n_stops, np.random.default_rng(1000 + seed))
        fit = fit_target_set(cell.points, cell.sigma)
        cov = fit.angle_covariance_rad2()
        var = np.diag(cov) + cov[0, 0] - 2 * cov[:, 0]  # of θ_k − θ_0
        inc = increment_error(fit.unwrapped_angle_rad(), cell.theta)
        zs.append(inc[1:] / np.sqrt(var[1:]))
    z = np.std(np.concatenate(zs))
    print(f"\n{arc_deg:g}° arc, T = 3, 50 seeds: z-score std {z:.3f}")
    assert 0.85 < z < 1.2
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), fit.angle_std_rad, rtol=1e-9)
    d, b = fit.angle_covariance_factors()
    assert d.shape == (n_stops,)
    assert b.shape == (n_stops, 3 * 3 + 3)


def test_one_target_is_the_circle_fit():
    cell = Cell(60.0, 31, np.random.default_rng(3))
    pts, sigma = cell.points[:, 0], cell.sigma[:, 0]
    circle = fit_circle_3d(pts, sigma)
    fit = fit_target_set(pts[:, None], sigma[:, None])
    np.testing.assert_array_equal(fit.angle_rad, circle.angle_rad)
    d, b = fit.angle_covariance_factors()
    d_c, b_c = circle.angle_covariance_factors()
    np.testing.assert_array_equal(d, d_c)
    np.testing.assert_array_equal(b, b_c)
    assert fit.variance_factor == circle.variance_factor
    np.testing.assert_array_equal(fit.point_sigma_mm, circle.point_sigma_mm)
    assert fit.radius_mm == circle.radius_mm
    np.testing.assert_array_equal(fit.normal, circle.normal)
    np.testing.assert_array_equal(fit.flipped().angle_rad, circle.flipped().angle_rad)
    # same parameters in the target-set layout: radius and tilts carry over
    assert fit.parameter_std[5] == pytest.approx(circle.parameter_std[5], rel=1e-12)
    assert fit.parameter_std[2:4] == pytest.approx(circle.parameter_std[3:5], rel=1e-12)
    # a stop not measured is left out of the circle and has no angle
    holed = pts.copy()
    holed[7] = np.nan
    fit = fit_target_set(holed[:, None], sigma)
    keep = np.arange(31) != 7
    np.testing.assert_array_equal(
        fit.angle_rad[keep], fit_circle_3d(pts[keep], sigma[keep]).angle_rad
    )
    assert np.isnan(fit.angle_rad[7]) and not fit.inlier[7]
    assert fit.unmeasured == (7,)


def test_crb_with_one_target_is_the_circle_bound():
    cell = Cell(60.0, 31, np.random.default_rng(4))
    circle = fit_circle_3d(cell.points[:, 0], cell.sigma[:, 0])
    fit = fit_target_set(cell.points[:, :1], cell.sigma[:, :1])
    x = np.column_stack([np.ones(31), cell.theta, np.sin(cell.theta)])
    expected = crb_covariance(circle, circle.angle_rad, x, cell.sigma[:, 0])
    got = crb_covariance_targets(fit, fit.angle_rad, x, cell.sigma[:, :1])
    np.testing.assert_allclose(got, expected, rtol=1e-8)


def test_angles_increase_along_the_stop_order_and_flip_negates_them():
    cell = Cell(120.0, 61, np.random.default_rng(5))
    forward = fit_target_set(cell.points, cell.sigma)
    backward = fit_target_set(cell.points[::-1], cell.sigma[::-1])
    assert np.all(np.diff(forward.unwrapped_angle_rad()) > 0)
    assert np.all(np.diff(backward.unwrapped_angle_rad()) > 0)
    assert forward.normal @ backward.normal == pytest.approx(-1.0, abs=1e-6)
    flipped = forward.flipped()
    np.testing.assert_allclose(flipped.angle_rad, -forward.angle_rad, atol=1e-12)
    np.testing.assert_allclose(flipped.angle_std_rad, forward.angle_std_rad, rtol=1e-6)
    np.testing.assert_allclose(flipped.residual_mm, forward.residual_mm, atol=1e-9)
    np.testing.assert_allclose(
        flipped.angle_covariance_rad2(), forward.angle_covariance_rad2(), rtol=1e-6, atol=1e-18
    )


def scale_gls(fit, design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GLS of the fit's angles on ``design`` with V = diag(d) + B·Bᵀ: coefficients, covariance."""
    d, b = fit.angle_covariance_factors()
    v_inv = np.linalg.inv(np.diag(d) + b @ b.T)
    cov = np.linalg.inv(design.T @ v_inv @ design)
    return cov @ design.T @ v_inv @ fit.unwrapped_angle_rad(), cov


@pytest.mark.parametrize(("arc_deg", "n_stops"), [(4.0, 10), (90.0, 46)])
def test_reported_scale_variance_is_close_to_the_cramer_rao_bound(arc_deg, n_stops):
    """The two-step estimate (target set, then GLS) loses nothing against the direct 3-D fit.

    The relation is θ_k = θ₀ + g·x_k with a known design (x the commanded fraction of the
    sweep, g the arc in rad). The bound is taken at the true geometry and noise; the
    reported variance carries the fit's variance factor (≈ 1 here, since σ is the true
    noise), so each seed also checks the bound's shape at unit variance factor.
    """
    ratios = []
    for seed in range(30):
        cell = Cell(arc_deg, n_stops, np.random.default_rng(300 + seed))
        fit = fit_target_set(cell.points, cell.sigma)
        x = np.column_stack([np.ones(n_stops), np.linspace(0.0, 1.0, n_stops)])
        beta, cov = scale_gls(fit, x)
        bound = crb_covariance_targets(cell.geometry(), cell.theta, x, cell.sigma)
        assert beta[1] == pytest.approx(cell.theta[-1], abs=6 * np.sqrt(cov[1, 1]))
        ratios.append(cov[1, 1] / bound[1, 1])
        assert cov[1, 1] / fit.variance_factor / bound[1, 1] == pytest.approx(1.0, rel=0.05)
    print(
        f"\n{arc_deg:g}° arc: reported scale variance / CRB over 30 seeds: mean "
        f"{np.mean(ratios):.3f} (min {np.min(ratios):.2f}, max {np.max(ratios):.2f})"
    )
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.25)


@pytest.mark.parametrize("targets", [2, 3])
@pytest.mark.parametrize(("arc_deg", "n_stops"), [(4.0, 10), (90.0, 46)])
def test_a_wild_point_is_found_and_only_that_point_dropped(targets, arc_deg, n_stops):
    for seed in range(5):
        rng = np.random.default_rng(200 + seed)
        cell = Cell(arc_deg, n_stops, rng, targets)
        clean = fit_target_set(cell.points, cell.sigma)
        assert clean.outlier_points == ()  # no false wild points on clean data
        k, t = int(rng.integers(n_stops)), int(rng.integers(targets))
        direction = rng.normal(size=3)
        pts = cell.points.copy()
        pts[k, t] += 1.0 * direction / np.linalg.norm(direction)  # 1 mm, 50-70σ
        fit = fit_target_set(pts, cell.sigma)
        assert fit.outlier_points == ((k, t),)
        assert fit.inlier.all() and fit.outliers == ()  # the stop keeps its other targets
        inc = increment_error(fit.unwrapped_angle_rad(), cell.theta)
        std = fit.angle_std_rad
        assert np.all(np.abs(inc) < 5 * np.sqrt(std**2 + std[0] ** 2))
        assert fit.residual_rms_mm < 3 * cell.sigma.max()


def test_a_tangential_disagreement_of_two_targets_drops_the_stop():
    """With two targets, a purely tangential wild point cannot be told from its partner."""
    cell = Cell(90.0, 46, np.random.default_rng(6), targets=2)
    fit = fit_target_set(cell.points, cell.sigma)
    k = 20
    _, tangent = _radial_tangent(fit, k, 1)
    pts = cell.points.copy()
    pts[k, 1] += 1.0 * tangent
    fit = fit_target_set(pts, cell.sigma)
    assert fit.outliers == (k,)
    assert set(fit.outlier_points) == {(k, 0), (k, 1)}
    assert np.isfinite(fit.angle_rad[k])  # still an angle, like the circle fit's outliers


def _radial_tangent(fit, k: int, t: int) -> tuple[np.ndarray, np.ndarray]:
    alpha = fit.angle_rad[k] + fit.phase_rad[t]
    u, v = fit.axis_u, fit.axis_v
    return np.cos(alpha) * u + np.sin(alpha) * v, -np.sin(alpha) * u + np.cos(alpha) * v


def test_missing_points_are_handled():
    rng = np.random.default_rng(7)
    cell = Cell(90.0, 46, rng)
    full = fit_target_set(cell.points, cell.sigma)
    pts = cell.points.copy()
    holes = rng.random(pts.shape[:2]) < 0.2  # a fifth of the points not measured
    holes[holes.all(axis=1), 0] = False  # every stop but one keeps a target
    pts[holes] = np.nan
    pts[5] = np.nan  # a stop with no target at all
    fit = fit_target_set(pts, cell.sigma)
    assert fit.unmeasured == (5,)
    assert np.isnan(fit.angle_rad[5]) and not fit.inlier[5]
    assert np.isnan(fit.angle_covariance_factors()[0][5])
    assert fit.outlier_points == ()
    ok = np.arange(46) != 5
    assert fit.inlier[ok].all()
    a, b = fit.unwrapped_angle_rad()[ok], full.unwrapped_angle_rad()[ok]
    diff = (a - a[0]) - (b - b[0])
    assert np.abs(diff).max() < 5 * fit.angle_std_rad[ok].max()
    inc = increment_error(fit.unwrapped_angle_rad()[ok], cell.theta[ok])
    assert np.abs(inc).max() < 5 * np.sqrt(2) * fit.angle_std_rad[ok].max()


def test_700_stops_of_3_targets_are_all_used():
    """A full wrist sweep's worth of stops (its speed is a benchmark row:
    ``python -m benchmarks.bench_scale``, ``target_set_fit``)."""
    cell = Cell(1400.0, 700, np.random.default_rng(8))
    fit = fit_target_set(cell.points, cell.sigma)
    assert fit.n_inliers == 700 and fit.iterations < 20
    assert np.all(np.isfinite(fit.angle_rad))


def test_bad_inputs_raise_a_calibration_error():
    cell = Cell(30.0, 12, np.random.default_rng(9))
    pts, sigma = cell.points, cell.sigma
    with pytest.raises(TargetSetFitError, match="shape"):
        fit_target_set(pts[..., :2])
    with pytest.raises(TargetSetFitError, match="shape"):
        fit_target_set(pts[:, 0])
    with pytest.raises(TargetSetFitError, match="at least 4 stops"):
        fit_target_set(pts[:3], sigma[:3])
    few = pts.copy()
    few[3:] = np.nan
    with pytest.raises(TargetSetFitError, match="at least 4 stops"):
        fit_target_set(few, sigma)
    for bad_sigma in (np.where(np.arange(12)[:, None] == 4, np.nan, sigma), -sigma, np.inf):
        with pytest.raises(TargetSetFitError, match="sigma"):
            fit_target_set(pts, bad_sigma)
    with pytest.raises(TargetSetFitError, match="sigma"):
        fit_target_set(pts, sigma[:, :2])
    inf = pts.copy()
    inf[2, 1, 0] = np.inf
    with pytest.raises(TargetSetFitError, match="finite"):
        fit_target_set(inf, sigma)
    # three reflectors on one line parallel to the axis turn like one target
    offsets = np.array([0.0, 150.0, 300.0])[:, None] * cell.normal
    line = cell.points[:, :1] + offsets + np.random.default_rng(0).normal(0, 0.015, (12, 3, 3))
    with pytest.raises(CalibrationError, match="parallel to the joint axis"):
        fit_target_set(line, 0.015)
    # no rotation between the stops
    still = np.broadcast_to(cell.true_points[:1], pts.shape).copy()
    still += np.random.default_rng(1).normal(0, 0.015, still.shape)
    with pytest.raises(CalibrationError, match="do not turn"):
        fit_target_set(still, 0.015)
    with pytest.raises(CalibrationError, match="target 2"):
        lonely = pts.copy()
        lonely[1:, 2] = np.nan
        fit_target_set(lonely, sigma)
