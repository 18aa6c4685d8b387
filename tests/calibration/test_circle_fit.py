"""3-D circle fit: exactness, short arcs, wild points, and honest angle uncertainties."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.errors import CalibrationError
from calibration.scales.circle_fit import CircleFitError, fit_circle_3d, taubin_circle_2d

SIGMA_MM = 0.016  # a laser tracker at a few metres


def circle_points(arc_deg: float, n: int, sigma: float, rng: np.random.Generator, radius=800.0):
    """Points on a random circle over ``arc_deg``; returns points, true angles, geometry."""
    centre = rng.uniform(-2000, 2000, 3)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, rng.normal(size=3))
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    theta = np.radians(np.linspace(0.0, arc_deg, n)) + rng.uniform(-np.pi, np.pi)
    pts = centre + radius * (np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v)
    return pts + rng.normal(0.0, sigma, pts.shape), theta, centre, normal


@pytest.mark.parametrize("arc_deg", [20.0, 90.0, 360.0, 700.0])
def test_noise_free_points_are_fitted_exactly(arc_deg):
    rng = np.random.default_rng(1)
    n = int(arc_deg / 2) + 1
    pts, theta, centre, normal = circle_points(arc_deg, n, 0.0, rng)
    fit = fit_circle_3d(pts)
    assert fit.radius_mm == pytest.approx(800.0, abs=1e-8)
    np.testing.assert_allclose(fit.centre_mm, centre, atol=1e-8)
    assert abs(fit.normal @ normal) == pytest.approx(1.0, abs=1e-12)
    angles = fit.unwrapped_angle_rad()
    np.testing.assert_allclose(angles - angles[0], theta - theta[0], atol=1e-11)
    assert fit.residual_rms_mm < 1e-9
    assert fit.outliers == ()


def test_angles_increase_along_the_point_order_and_flip_negates_them():
    rng = np.random.default_rng(2)
    pts, *_ = circle_points(120.0, 61, SIGMA_MM, rng)
    forward = fit_circle_3d(pts)
    backward = fit_circle_3d(pts[::-1])
    assert np.all(np.diff(forward.unwrapped_angle_rad()) > 0)
    assert np.all(np.diff(backward.unwrapped_angle_rad()) > 0)
    assert forward.normal @ backward.normal == pytest.approx(-1.0, abs=1e-6)
    flipped = forward.flipped()
    np.testing.assert_allclose(flipped.angle_rad, -forward.angle_rad, atol=1e-12)
    np.testing.assert_allclose(flipped.angle_std_rad, forward.angle_std_rad, rtol=1e-6)


def test_taubin_start_is_close_on_a_short_arc():
    rng = np.random.default_rng(3)
    theta = np.radians(np.linspace(0, 20, 11))
    xy = 500.0 * np.column_stack([np.cos(theta), np.sin(theta)]) + [10.0, -20.0]
    centre, radius = taubin_circle_2d(xy + rng.normal(0, SIGMA_MM, xy.shape))
    assert radius == pytest.approx(500.0, rel=0.02)
    np.testing.assert_allclose(centre, [10.0, -20.0], atol=12.0)


@pytest.mark.parametrize("arc_deg", [20.0, 45.0, 90.0, 180.0, 360.0])
def test_noisy_arcs_recover_the_circle_within_its_uncertainty(arc_deg):
    z_radius, z_centre = [], []
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        n = max(int(arc_deg / 2) + 1, 11)
        pts, _, centre, _ = circle_points(arc_deg, n, SIGMA_MM, rng)
        fit = fit_circle_3d(pts, SIGMA_MM)
        std = fit.parameter_std
        z_radius.append((fit.radius_mm - 800.0) / std[5])
        z_centre.append((fit.centre_mm - centre) / std[:3])
        assert fit.outliers == ()  # no false wild points on clean data
    assert 0.6 < np.std(z_radius) < 1.5
    assert np.abs(z_centre).max() < 5.0


@pytest.mark.parametrize("arc_deg", [20.0, 60.0, 360.0])
def test_angle_uncertainty_is_calibrated(arc_deg):
    """z-scores of recovered angle increments over seeds have a standard deviation ≈ 1."""
    zs = []
    for seed in range(60):
        rng = np.random.default_rng(1000 + seed)
        n = max(int(arc_deg / 2) + 1, 11)
        pts, theta, *_ = circle_points(arc_deg, n, SIGMA_MM, rng)
        sigma = SIGMA_MM * rng.uniform(0.8, 1.2, n)  # per-point weights are used as given
        fit = fit_circle_3d(pts + 0.0, sigma)
        angles = fit.unwrapped_angle_rad()
        cov = fit.angle_covariance_rad2()
        var = np.diag(cov) + cov[0, 0] - 2 * cov[:, 0]  # of θ_k − θ_0
        inc = (angles - angles[0]) - (theta - theta[0])
        zs.append(inc[1:] / np.sqrt(var[1:]))
    z = np.concatenate(zs)
    assert 0.85 < np.std(z) < 1.2
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), fit.angle_std_rad, rtol=1e-9)


@pytest.mark.parametrize(("arc_deg", "n"), [(20.0, 11), (90.0, 46), (360.0, 181)])
def test_one_wild_point_is_reported_and_dropped(arc_deg, n):
    for seed in range(5):
        rng = np.random.default_rng(50 + seed)
        pts, *_ = circle_points(arc_deg, n, SIGMA_MM, rng)
        clean = fit_circle_3d(pts, SIGMA_MM)
        wild = int(rng.integers(0, n))
        direction = rng.normal(size=3)
        pts[wild] += 0.8 * direction / np.linalg.norm(direction)  # 50σ off
        fit = fit_circle_3d(pts, SIGMA_MM)
        assert fit.outliers == (wild,)
        assert not fit.inlier[wild]
        assert fit.radius_mm == pytest.approx(clean.radius_mm, abs=4 * clean.parameter_std[5])
        assert fit.residual_rms_mm < 3 * SIGMA_MM


def test_bad_inputs_raise_a_calibration_error():
    rng = np.random.default_rng(4)
    pts, *_ = circle_points(90.0, 20, SIGMA_MM, rng)
    with pytest.raises(CircleFitError, match="at least 4"):
        fit_circle_3d(pts[:3])
    bad = pts.copy()
    bad[3, 1] = np.nan
    with pytest.raises(CircleFitError, match="finite"):
        fit_circle_3d(bad)
    line = np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0])
    with pytest.raises(CalibrationError, match=r"collinear|coincide|singular"):
        fit_circle_3d(line)
    with pytest.raises(CircleFitError, match="shape"):
        fit_circle_3d(pts[:, :2])
    with pytest.raises(CircleFitError, match="sigma"):
        fit_circle_3d(pts, -1.0)
