"""Rotation of a set of targets about one joint axis: the stop angles of a scale sweep.

With one tracker target on the swept link, a stop's angle comes from a 3-D circle through
all stops (:mod:`calibration.scales.circle_fit`). On short arcs that is badly conditioned: the
centre is poorly determined and every angle increment inherits its error. With two or
more targets fixed on the link (or a 6-DoF probe) each stop's angle is the rigid rotation
of the whole set about the common axis, which the tangential components of the targets
fix almost independently of the centre.

**Model.** K stops (in the order visited), T targets. Target t at stop k::

    p_tk = c + h_t·n + r_t·(cos(θ_k + φ_t)·u + sin(θ_k + φ_t)·v) + e_tk

``n`` the unit axis, ``u`` ⟂ ``n`` the angle origin, ``v = n × u``; ``e_tk`` isotropic
Gaussian of per-axis standard deviation ``s·σ_tk`` (``σ`` the given weights, ``s²`` the
unknown variance factor). NaN rows mark targets not measured at a stop.

**Unknowns.** The axis, 4 dof: the axis point moves in the plane ⟂ ``n`` (2, along ``u``
and ``v``; along ``n`` it is absorbed by the heights) and ``n`` tilts towards ``u`` and
``v`` (2; ``u`` follows ``n`` by projection, as in the circle fit). Per target the height
``h_t`` along the axis, the radius ``r_t`` and the phase ``φ_t`` (``φ_0 = 0``: θ_k is the
angle of target 0, as the circle fit's angle of its one target). Per stop the angle θ_k.
That is ``P = 3T + 3`` structure parameters (:func:`parameter_names`) and K angles. After
the fit the axis point is put at the targets' mean height (``Σ h_t = 0``), the best
determined point of the axis.

**Solver.** Gauss-Newton/Levenberg-Marquardt on all three coordinates of every point,
with the angles *profiled*: for a fixed structure the best θ_k is closed-form, the
argument of the weighted complex sum ``Σ_t r_t e^{−iφ_t} z_tk / σ_tk²`` (``z_tk`` the
in-plane position of the point about the axis). The normal equations have an arrow shape
(each θ_k touches only its own stop), so the angles are eliminated exactly by a Schur
complement: each iteration solves a ``P × P`` system (12 for T = 3) built from
vectorized sums over the ``3·K·T`` residuals, then re-profiles every θ_k exactly. That
keeps the problem small and fast (K = 700, T = 3: about 15 ms in all, 4 iterations).
``scipy.optimize.least_squares`` would need a sparse ``3KT × (K + P)`` Jacobian and an
iterative trust-region solver, slower, and would leave the angle covariance to be
assembled afterwards; the Schur form gives its factors directly (below). LM damping on
the reduced system guards the first steps.
Start: the plane normal by SVD of the per-target centred points (targets at different
phases move along different tangents, so the plane is well defined even on short arcs);
each stop's rotation relative to a template stop by 2-D Procrustes of the projected set
(independent of the unknown centre); then centre and per-target ``r_t e^{iφ_t}`` by
linear least squares of ``z_tk = c + w_t e^{iθ_k}``.

With **T = 1** the tangential components carry no information and the problem *is* the
circle fit: :func:`fit_target_set` delegates to :func:`calibration.scales.circle_fit.fit_circle_3d`
(same angles, same covariance).

**Covariance.** The first-order covariance of all unknowns is ``s²·N⁻¹`` (``N`` the
weighted Gauss-Newton normal matrix at the solution, ``s²`` = weighted RSS / dof, dof =
3·points − P − stops). Through the Schur complement the angle covariance is exactly::

    Cov(θ) = diag(d) + B·Bᵀ,   d_k = s² / Σ_t r_t²/σ_tk²,   B = G·L

``d`` the per-stop tangential part given the structure; ``G = ∂θ̂/∂structure`` ``(K, P)``
the sensitivity of the profiled angles, ``L·Lᵀ`` the structure covariance
(``s²·(N_ss − N_sθ N_θθ⁻¹ N_θs)⁻¹``). This is the form the grating-scale GLS whitens in
O(K) (:meth:`TargetSetFit.angle_covariance_factors`).

**Cramér-Rao bound** (:func:`crb_covariance_targets`): the direct 3-D model with
``θ_k = design_k·β``; the Fisher information over the structure and β, with
``∂p_tk/∂β_j = r_t·t_tk·design_kj`` (``t_tk`` the tangent). For T = 1 it equals
:func:`calibration.scales.relation_fit.crb_covariance`.

**Wild points** are rejected *per point*, not per stop: the tracker measures the targets
one after another, so a wild reading belongs to one target, and the stop keeps its angle
from the others. A point's *deleted* residual (against θ_k from the other points of its
stop) is normalized by its variance (tangential part inflated by the uncertainty of that
θ_k) and compared with the χ²₃ quantile at ``outlier_alpha / N`` (Bonferroni over the N
points in use; χ²₂ for a stop's only point, whose tangential part θ_k absorbs). As in the
circle fit the worst point is screened against a robust scale, refitted out, and dropped
when its deleted residual against the refit still exceeds the limit (at most
``max_outliers`` points). One case is ambiguous: at a stop with two points a purely
tangential disagreement cannot be attributed to either; unless the dropped point is wild
in its radial/axial components alone (χ²₂), the stop's other point goes too. A stop keeps
an angle (``inlier``) while one of its points remains.

**Errors** (:class:`TargetSetFitError`, a :class:`~calibration.scales.circle_fit.CircleFitError`):
shape not ``(K, T, 3)``; fewer than 4 stops with a measured target; a point partly NaN
or infinite; ``sigma`` not finite and positive at a measured point; a target measured at
fewer than 2 stops; targets all on one line parallel to the axis (their in-plane spread
within 10× the noise: the set turns like one target, fit that one alone); stops that do
not turn the link measurably (angle span within 10× the per-stop angle noise).

**Measured** (``tests/test_target_set_fit.py``; reflectors on an equilateral triangle of
side 360 mm about 500 mm from an arbitrarily tilted axis, tracker 1.5–4 m away with
per-axis σ = (15 µm + 6 µm/m · distance)/2; 24 seeds): RMS error of the angle
increments, target 0 alone (circle fit) → 3 targets: 4° arc, 10 stops 345″ → 6.6″
(52×); 20°, 11 stops 71″ → 6.3″ (11×); 90°, 46 stops 13.1″ → 4.9″ (2.7×); 470°, 236
stops 9.7″ → 4.2″ (2.3×). Increment z-scores over 50 seeds: standard deviation 1.00
(4°) and 1.02 (90°). Reported scale variance / CRB over 30 seeds: 1.03 (4°), 1.01 (90°).

Units: mm and radians. Shapes: ``(K, T, 3)`` points, ``(K, T)`` per point, ``(K,)`` per
stop, ``(T,)`` per target, ``(P,)`` per structure parameter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import TargetSetFitError
from calibration.scales.circle_fit import (
    CircleFit,
    FactoredAngleCovariance,
    fit_circle_3d,
)
from calibration.scales.target_set_model import (
    TargetSetGeometry,
    canonical,
    local_coordinates,
    parameter_names,
    point_jacobians,
    profile_theta,
)
from calibration.scales.target_set_solver import (
    MIN_SPREAD_NOISE,
    MIN_STOPS,
    _normal_blocks,
    fit_geometry,
    reject_wild,
    start_geometry,
)

FloatArray = NDArray[np.float64]


BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class TargetSetFit(FactoredAngleCovariance):
    """The rotation of a set of T targets about one axis at K stops (see the module doc).

    Fields mirror :class:`~calibration.scales.circle_fit.CircleFit` where grating_scale uses it:
    ``angle_rad``, ``angle_covariance_factors()``, ``variance_factor``,
    ``point_sigma_mm``, ``inlier``, ``outliers``, ``normal``, ``centre_mm``,
    ``radius_mm``, ``axis_u``/``axis_v``, ``flipped()``. By default ``normal`` is oriented
    so that the angles *increase* along the stop order.

    ``angle_rad_all`` is θ_k of every stop (target 0's angle from ``axis_u`` about
    ``normal``), NaN for a stop with no measured point. A stop whose points were all
    dropped as wild still has an angle, from those points, as the circle fit gives one for
    its outliers. ``parameter_covariance`` is over :func:`parameter_names` (structure
    only; already scaled by ``variance_factor``). For T = 1 ``circle`` is the circle fit
    this result wraps: angles, angle covariance, ``variance_factor`` and
    ``point_sigma_mm`` are its own, and ``parameter_covariance`` is its covariance mapped
    to :func:`parameter_names` (centre along ``u``, ``v``; tilts; centre along ``n`` as
    ``height_0``; radius).
    """

    geometry: TargetSetGeometry
    angle_rad_all: FloatArray  # (K,)
    points_mm: FloatArray  # (K, T, 3) as given (NaN: not measured)
    sigma_mm: FloatArray  # (K, T) per-axis weights as given (relative if sigma was None)
    point_inlier: BoolArray  # (K, T) measured and not dropped as wild
    variance_factor: float  # a-posteriori s² = weighted RSS / dof
    dof: int  # 3·points − (3T + 3) − stops, over the points in use
    parameter_covariance: FloatArray  # (P, P)
    iterations: int  # Levenberg-Marquardt iterations of the final fit (0 for T = 1)
    circle: CircleFit | None = None  # T = 1: the circle fit (target 0 alone)

    # -- geometry ------------------------------------------------------------------------
    @property
    def centre_mm(self) -> FloatArray:
        """The axis point at the targets' mean height (T = 1: the circle's centre)."""
        return self.geometry.centre_mm

    @property
    def normal(self) -> FloatArray:
        return self.geometry.normal

    @property
    def axis_u(self) -> FloatArray:
        return self.geometry.axis_u

    @property
    def axis_v(self) -> FloatArray:
        return self.geometry.axis_v

    @property
    def n_targets(self) -> int:
        return self.geometry.n_targets

    @property
    def n_stops(self) -> int:
        return int(self.points_mm.shape[0])

    @property
    def radii_mm(self) -> FloatArray:
        """Radius of every target's circle about the axis, ``(T,)``."""
        return self.geometry.radii_mm

    @property
    def height_mm(self) -> FloatArray:
        """Position of every target's circle along the axis from ``centre_mm``, ``(T,)``."""
        return self.geometry.height_mm

    @property
    def phase_rad(self) -> FloatArray:
        """Angle of every target from target 0 about the axis, ``(T,)`` (``[0] = 0``)."""
        return self.geometry.phase_rad

    @property
    def radius_mm(self) -> float:
        """Representative radius: RMS of :attr:`radii_mm` (one target with the set's mean
        tangential leverage, the angle information per point being ∝ r²/σ²)."""
        return float(np.sqrt(np.mean(self.radii_mm**2)))

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return parameter_names(self.n_targets)

    @property
    def parameter_std(self) -> FloatArray:
        return np.sqrt(np.diag(self.parameter_covariance))

    # -- stops and points ------------------------------------------------------------------
    @property
    def measured(self) -> BoolArray:
        """``(K, T)``: the target was measured at the stop (finite point)."""
        measured: BoolArray = np.all(np.isfinite(self.points_mm), axis=-1)
        return measured

    @property
    def inlier(self) -> BoolArray:
        """``(K,)``: the stop keeps at least one point, so its angle is in the fit."""
        inlier: BoolArray = np.any(self.point_inlier, axis=1)
        return inlier

    @property
    def n_points(self) -> int:
        return int(self.measured.sum())

    @property
    def n_inliers(self) -> int:
        """Stops with an angle in the fit (as ``CircleFit.n_inliers`` counts points)."""
        return int(self.inlier.sum())

    @property
    def outliers(self) -> tuple[int, ...]:
        """Stops dropped because every measured point of theirs was wild."""
        gone = self.measured.any(axis=1) & ~self.inlier
        return tuple(int(i) for i in np.flatnonzero(gone))

    @property
    def outlier_points(self) -> tuple[tuple[int, int], ...]:
        """``(stop, target)`` of every point dropped as wild."""
        k, t = np.nonzero(self.measured & ~self.point_inlier)
        return tuple((int(a), int(b)) for a, b in zip(k, t, strict=True))

    @property
    def unmeasured(self) -> tuple[int, ...]:
        """Stops with no measured target (angle NaN)."""
        return tuple(int(i) for i in np.flatnonzero(~self.measured.any(axis=1)))

    def _angle_weight(self) -> FloatArray:
        """``(K, T)`` 1/σ² of the points that give each stop's angle (0 elsewhere)."""
        use = np.where(self.inlier[:, None], self.point_inlier, self.measured)
        return np.where(use, 1.0 / self.sigma_mm**2, 0.0)

    @property
    def residual_mm(self) -> FloatArray:
        """Point minus model ``(K, T, 3)`` (NaN where not measured)."""
        return self.points_mm - self.geometry.positions_mm(np.nan_to_num(self.angle_rad_all))

    @property
    def residual_rms_mm(self) -> float:
        """RMS 3-D distance of the points in use from the model."""
        e = self.residual_mm[self.point_inlier]
        return float(np.sqrt(np.mean(np.einsum("ia,ia->i", e, e))))

    @property
    def target_sigma_mm(self) -> FloatArray:
        """A-posteriori per-axis noise of every point, ``(K, T)``: ``sqrt(s²)·σ_tk``."""
        return math.sqrt(self.variance_factor) * self.sigma_mm

    @property
    def point_sigma_mm(self) -> FloatArray:
        """A-posteriori per-axis tracker noise at every stop, ``(K,)`` mm.

        ``sqrt(s²)`` times the RMS of the given σ over the points that give the stop's
        angle (NaN for an unmeasured stop): the tracker noise, as ``CircleFit``'s. The
        noise of one target at ``radius_mm`` that would give the stop's angle variance is
        ``sqrt(d_k)·radius_mm`` (:meth:`angle_covariance_factors`).
        """
        if self.circle is not None:
            return self._from_circle(self.circle.point_sigma_mm)
        w = self._angle_weight()
        n = (w > 0).sum(axis=1)
        mean_s2 = np.where(w > 0, self.sigma_mm**2, 0.0).sum(axis=1) / np.maximum(n, 1)
        return np.where(n > 0, np.sqrt(self.variance_factor * mean_s2), np.nan)

    # -- angles -------------------------------------------------------------------------------
    @property
    def angle_rad(self) -> FloatArray:
        """Angle of every stop about the axis, ``(K,)`` in (−π, π] (NaN: unmeasured)."""
        wrapped: FloatArray = np.angle(np.exp(1j * self.angle_rad_all))
        return wrapped

    def unwrapped_angle_rad(self) -> FloatArray:
        """:attr:`angle_rad` unwrapped along the stop order (consecutive steps < 180°)."""
        out = self.angle_rad.copy()
        ok = np.isfinite(out)
        out[ok] = np.unwrap(out[ok])
        return out

    def _from_circle(self, values: FloatArray) -> FloatArray:
        """Spread a per-measured-stop array of the wrapped circle fit over all K stops."""
        ok = self.measured[:, 0]
        out = np.full((self.n_stops, *values.shape[1:]), np.nan)
        out[ok] = values
        return out

    def angle_sensitivity(self) -> FloatArray:
        """``G = ∂θ̂_k/∂structure`` ``(K, P)`` of the profiled angles (T ≥ 2)."""
        _, n_ts, n_tt, _ = _normal_blocks(self.geometry, self.angle_rad_all, self._angle_weight())
        with np.errstate(divide="ignore", invalid="ignore"):
            sens: FloatArray = -n_ts / n_tt[:, None]
            return sens

    def angle_covariance_factors(self) -> tuple[FloatArray, FloatArray]:
        """The angle covariance as ``diag(d) + B·Bᵀ``: ``d`` ``(K,)``, ``B`` ``(K, P)``, rad².

        ``d_k = s² / Σ_t r_t²/σ_tk²`` is the stop's own (tangential) part given the
        structure; ``B = G·L`` the part shared through the structure parameters (``G`` =
        :meth:`angle_sensitivity`, ``L·Lᵀ`` = :attr:`parameter_covariance`). At the
        a-posteriori variance factor. NaN rows for unmeasured stops. T = 1: the circle
        fit's own factors (``B`` ``(K, 6)``).
        """
        if self.circle is not None:
            d, b = self.circle.angle_covariance_factors()
            return self._from_circle(d), self._from_circle(b)
        w = self._angle_weight()
        n_tt = np.sum(w * self.radii_mm**2, axis=1)
        with np.errstate(divide="ignore"):
            d = np.where(n_tt > 0, self.variance_factor / n_tt, np.nan)
        val, vec = np.linalg.eigh(self.parameter_covariance)
        root = vec * np.sqrt(np.clip(val, 0.0, None))
        return d, self.angle_sensitivity() @ root

    def flipped(self) -> TargetSetFit:
        """The same fit with the normal reversed: every angle, phase and height changes sign."""
        g = self.geometry
        geo = replace(g, normal=-g.normal, height_mm=-g.height_mm, phase_rad=-g.phase_rad)
        # n' = −n, u' = u, v' = −v: centre_v, tilt_u, heights and phases change sign
        t = self.n_targets
        sign = np.concatenate([[1.0, -1.0, -1.0, 1.0], -np.ones(t), np.ones(t), -np.ones(t - 1)])
        return replace(
            self,
            geometry=geo,
            angle_rad_all=-self.angle_rad_all,
            parameter_covariance=self.parameter_covariance * np.outer(sign, sign),
            circle=None if self.circle is None else self.circle.flipped(),
        )


def _check_inputs(
    points_mm: ArrayLike, sigma_mm: ArrayLike | float | None
) -> tuple[FloatArray, FloatArray, BoolArray]:
    pts = np.asarray(points_mm, dtype=float)
    if pts.ndim != 3 or pts.shape[2] != 3 or pts.shape[1] < 1:
        raise TargetSetFitError(f"points must have shape (K stops, T targets, 3), got {pts.shape}")
    k, t, _ = pts.shape
    if k < MIN_STOPS:
        raise TargetSetFitError(f"a target-set fit needs at least {MIN_STOPS} stops, got {k}")
    nan = np.isnan(pts)
    measured = ~nan.any(axis=-1)
    if np.any(nan.any(axis=-1) & ~nan.all(axis=-1)) or np.any(np.isinf(pts)):
        raise TargetSetFitError(
            "points must be finite, or NaN in all three coordinates for a target not measured"
        )
    if sigma_mm is None:
        sigma = np.ones((k, t))
    else:
        s = np.asarray(sigma_mm, dtype=float)
        if s.shape == (k,):
            s = s[:, None]
        try:
            sigma = np.broadcast_to(s, (k, t)).copy()
        except ValueError:
            raise TargetSetFitError(
                f"sigma must be a scalar, (K,) or (K, T) = ({k}, {t}), got shape {s.shape}"
            ) from None
        if not np.all(np.isfinite(sigma[measured]) & (sigma[measured] > 0)):
            raise TargetSetFitError("sigma must be finite and positive for every measured point")
        sigma[~measured] = 1.0  # never used
    n_stops = int(measured.any(axis=1).sum())
    if n_stops < MIN_STOPS:
        raise TargetSetFitError(
            f"a target-set fit needs at least {MIN_STOPS} stops with a measured target, "
            f"got {n_stops}"
        )
    if t > 1:
        for i, n in enumerate(measured.sum(axis=0)):
            if n < 2:
                raise TargetSetFitError(f"target {i} is measured at {n} stops; at least 2 needed")
    return pts, sigma, measured


def fit_target_set(
    points_mm: ArrayLike,
    sigma_mm: ArrayLike | float | None = None,
    *,
    outlier_alpha: float = 1e-3,
    max_outliers: int | None = None,
) -> TargetSetFit:
    """Fit the rotation of T targets about one common axis at K stops (see the module doc).

    ``points_mm`` ``(K, T, 3)``: K ≥ 4 stops in the order visited, T ≥ 1 targets on the
    swept link, tracker frame; a row of NaN for a target not measured at a stop.
    ``sigma_mm``: per-axis noise of every point, scalar, ``(K,)`` (per stop) or ``(K, T)``; only its
    relative size matters, the scale comes from the residuals (``variance_factor``).
    Wild points are dropped one at a time (χ² limit at ``outlier_alpha / N`` over the N
    points in use; at most ``max_outliers`` points, default ``max(1, N // 25)``).

    T = 1 is the circle fit (:func:`~calibration.scales.circle_fit.fit_circle_3d` on the measured
    stops). Raises :class:`TargetSetFitError` for bad shapes, fewer than 4 stops,
    non-finite or non-positive ``sigma``, or targets all on one line parallel to the axis.
    """
    pts, sigma, measured = _check_inputs(points_mm, sigma_mm)
    t_n = pts.shape[1]
    if t_n == 1:
        return _wrap_circle(pts, sigma, measured, outlier_alpha, max_outliers)
    if max_outliers is None:
        max_outliers = max(1, int(measured.sum()) // 25)
    filled = np.where(measured[..., None], pts, 0.0)
    weight = np.where(measured, 1.0 / sigma**2, 0.0)
    start = start_geometry(filled, measured, weight)
    fit = fit_geometry(filled, weight, measured, start)
    used, fit = reject_wild(filled, weight, measured.copy(), fit, outlier_alpha, max_outliers)

    geo, theta = canonical(fit.geo, fit.theta)
    # stops that lost every point still get an angle from their own points
    lost = measured.any(axis=1) & ~used.any(axis=1)
    if lost.any():
        z = local_coordinates(geo, filled)[0]
        theta = np.where(lost, profile_theta(geo, z, weight), theta)
    result = TargetSetFit(
        geometry=geo,
        angle_rad_all=theta,
        points_mm=pts,
        sigma_mm=sigma,
        point_inlier=used,
        variance_factor=fit.s2,
        dof=fit.dof,
        parameter_covariance=fit.s2 * _unit_covariance(geo, theta, np.where(used, weight, 0.0)),
        iterations=fit.iterations,
    )
    return _turning(result)


def _unit_covariance(geo: TargetSetGeometry, theta: FloatArray, w_used: FloatArray) -> FloatArray:
    """Covariance of the structure parameters per unit variance, the stop angles profiled
    out (Schur complement of the normal matrix), for the weights ``w_used`` ``(K, T)`` of
    the points in use; an error when the stops do not determine the axis."""
    n_ss, n_ts, n_tt, _ = _normal_blocks(geo, theta, w_used)
    inv_tt = np.where(n_tt > 0, 1.0 / np.where(n_tt > 0, n_tt, 1.0), 0.0)
    reduced = n_ss - n_ts.T @ (n_ts * inv_tt[:, None])
    scale = np.sqrt(np.maximum(np.diag(reduced), 1e-300))
    a = reduced / np.outer(scale, scale)
    val = np.linalg.eigvalsh(a)
    if not val[0] > 1e-13 * val[-1]:
        raise TargetSetFitError(
            "the stops do not determine the axis (singular fit: no rotation between the "
            "stops, or a target on the axis)"
        )
    cov_unit: FloatArray = np.linalg.inv(a) / np.outer(scale, scale)
    return cov_unit


def _turning(result: TargetSetFit) -> TargetSetFit:
    """``result`` oriented with the stops' order, once they turn the link measurably."""
    angles = result.unwrapped_angle_rad()[result.inlier]
    noise = float(np.median(np.sqrt(result.angle_covariance_factors()[0][result.inlier])))
    if np.ptp(angles) <= MIN_SPREAD_NOISE * noise:
        raise TargetSetFitError(
            f"the stops do not turn the link measurably (angle span {np.ptp(angles):.3g} rad, "
            f"noise {noise:.2g} rad per stop): no axis to fit"
        )
    return result.flipped() if np.diff(angles).sum() < 0 else result


def _wrap_circle(
    pts: FloatArray,
    sigma: FloatArray,
    measured: BoolArray,
    outlier_alpha: float,
    max_outliers: int | None,
) -> TargetSetFit:
    """T = 1: the circle fit of the measured stops, as a :class:`TargetSetFit`."""
    ok = measured[:, 0]
    circle = fit_circle_3d(
        pts[ok, 0], sigma[ok, 0], max_outliers=max_outliers, outlier_alpha=outlier_alpha
    )
    u, v, n = circle.axis_u, circle.axis_v, circle.normal
    geo = TargetSetGeometry(
        circle.centre_mm, n, u, np.zeros(1), np.array([circle.radius_mm]), np.zeros(1)
    )
    # circle parameters (c, tilt_u, tilt_v, ρ) -> (c·u, c·v, tilt_u, tilt_v, h = c·n, ρ)
    m = np.zeros((6, 6))
    m[0, :3], m[1, :3], m[4, :3] = u, v, n
    m[2, 3] = m[3, 4] = m[5, 5] = 1.0
    theta = np.full(len(pts), np.nan)
    theta[ok] = circle.angle_rad
    inlier = np.zeros_like(measured)
    inlier[ok, 0] = circle.inlier
    return TargetSetFit(
        geometry=geo,
        angle_rad_all=theta,
        points_mm=pts,
        sigma_mm=sigma,
        point_inlier=inlier,
        variance_factor=circle.variance_factor,
        dof=circle.dof,
        parameter_covariance=m @ circle.parameter_covariance @ m.T,
        iterations=0,
        circle=circle,
    )


def crb_covariance_targets(
    geometry: TargetSetGeometry | TargetSetFit,
    angle_rad: ArrayLike,
    design: ArrayLike,
    sigma_mm: ArrayLike | float,
    measured: ArrayLike | None = None,
) -> FloatArray:
    """Cramér-Rao bound on the coefficients of ``θ_k = design_k · β`` (rad units), T targets.

    The bound of the direct 3-D model ``p_tk = c + h_t·n + r_t(cos(θ_k + φ_t)·u +
    sin(θ_k + φ_t)·v) + noise``, isotropic per-axis noise ``sigma_mm`` (scalar, ``(K,)``
    or ``(K, T)``), with the structure unknown (axis point and tilts, every ``h_t``,
    ``r_t``, ``φ_t`` but ``φ_0``). ``geometry`` supplies the structure (a
    :class:`TargetSetGeometry`, e.g. the truth, or a :class:`TargetSetFit`),
    ``angle_rad`` ``(K,)`` the stop angles in its frame (target 0's), ``design`` ``(K, p)``
    the relation's columns (the first should be the intercept θ₀), ``measured``
    ``(K, T)`` which points exist (default all). Returns the ``(p, p)`` block of the
    inverse Fisher information. For T = 1 it equals
    :func:`calibration.scales.relation_fit.crb_covariance`.
    """
    geo = geometry.geometry if isinstance(geometry, TargetSetFit) else geometry
    th = np.asarray(angle_rad, dtype=float)
    x = np.asarray(design, dtype=float).reshape(th.shape[0], -1)
    k, t = th.shape[0], geo.n_targets
    sig = np.asarray(sigma_mm, dtype=float)
    if sig.shape == (k,):
        sig = sig[:, None]
    sig = np.broadcast_to(sig, (k, t))
    mask = np.ones((k, t), bool) if measured is None else np.asarray(measured, dtype=bool)
    weight = np.where(mask, 1.0 / np.where(mask, sig, 1.0) ** 2, 0.0)
    js, j_theta = point_jacobians(geo, th)
    jac = np.concatenate([js, j_theta[..., None] * x[:, None, None, :]], axis=-1)
    a = (np.sqrt(weight)[..., None, None] * jac).reshape(-1, jac.shape[-1])
    info = a.T @ a
    scale = np.sqrt(np.diag(info))
    scale[scale == 0] = 1.0
    cov = np.linalg.pinv(info / np.outer(scale, scale), rcond=1e-12, hermitian=True)
    n_par = js.shape[-1]
    cov_targets: FloatArray = (cov / np.outer(scale, scale))[n_par:, n_par:]
    return cov_targets
