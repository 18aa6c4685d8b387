"""Least-squares circle in 3-D: the path of a target fixed on a link turning about one joint.

The fit follows three steps:

1. **plane** by SVD of the centred points (the normal is the smallest singular vector);
2. **algebraic start**: Taubin's circle fit of the points projected into that plane
   (nearly unbiased on short arcs, where Kåsa's fit shrinks the radius);
3. **geometric refinement** of the 3-D circle (centre, normal, radius) by
   ``scipy.optimize.least_squares``: each point contributes its *axial* distance from the
   plane and its *radial* distance from the circle in the plane, weighted by ``1/sigma``.

The angle of a point about the fitted axis depends only on its *tangential* component,
which the circle parameters do not see; so each angle's error is the tangential noise over
the radius plus a part common to all points, from the centre and normal errors. Both are
propagated into :meth:`CircleFit.angle_covariance_rad2` (first order, with the
a-posteriori variance factor of the fit).

Wild points are found by their radial/axial distance: the worst point is dropped when its
distance, measured against the circle fitted *without* it, exceeds a Bonferroni-corrected
χ²₂ limit. The tangential component of a wild point is invisible here; the grating-scale
relation fit checks the angles again (:mod:`calibration.scales.grating_scale`).

Units: mm and radians. Shapes are given as ``(N, 3)`` for N points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import CircleFitError

if TYPE_CHECKING:  # scipy loads when a circle is fitted, not for a command that only reads
    from scipy.optimize import OptimizeResult

FloatArray = NDArray[np.float64]

MIN_POINTS = 4  # 3 points fix a circle; one more gives a residual to estimate noise from
N_PARAMETERS = 6  # centre (3), normal tilt (2), radius (1)
PARAMETER_NAMES: tuple[str, ...] = (
    "centre_x_mm",
    "centre_y_mm",
    "centre_z_mm",
    "tilt_u_rad",
    "tilt_v_rad",
    "radius_mm",
)


class FactoredAngleCovariance:
    """Angles whose covariance is ``diag(d) + B·Bᵀ`` (:meth:`angle_covariance_factors`):
    independent tangential noise plus a low-rank part shared through the fitted axis. The
    angle origin moves with the axis, so the covariance is meaningful for angle
    *differences*; a common offset is arbitrary."""

    def angle_covariance_factors(self) -> tuple[FloatArray, FloatArray]:
        raise NotImplementedError

    def angle_covariance_rad2(self) -> FloatArray:
        """Covariance of all angles, ``(N, N)`` rad²."""
        d, b = self.angle_covariance_factors()
        return np.diag(d) + b @ b.T

    @property
    def angle_std_rad(self) -> FloatArray:
        """Standard deviation of every angle, ``(N,)`` rad."""
        d, b = self.angle_covariance_factors()
        std: FloatArray = np.sqrt(d + np.einsum("ij,ij->i", b, b))
        return std


@dataclass(frozen=True, eq=False)
class CircleFit(FactoredAngleCovariance):
    """A 3-D circle fitted to N points, with the angle of every point about its axis.

    The angle of a point is measured in the circle's plane from ``axis_u`` towards
    ``axis_v = normal × axis_u``, i.e. counter-clockwise seen from the tip of ``normal``
    (right-hand rule). By default ``normal`` is oriented so that angles *increase* along
    the order in which the points were given.

    ``parameter_covariance`` is over :data:`PARAMETER_NAMES`: the centre, two small tilts
    of the normal towards ``axis_u`` and ``axis_v`` (rad), and the radius, already scaled
    by the a-posteriori ``variance_factor``.
    """

    centre_mm: FloatArray  # (3,)
    normal: FloatArray  # (3,) unit
    axis_u: FloatArray  # (3,) unit, in the plane: angle 0
    radius_mm: float
    points_mm: FloatArray  # (N, 3) all points given, outliers included
    sigma_mm: FloatArray  # (N,) per-point weights as given (relative if sigma was None)
    inlier: NDArray[np.bool_]  # (N,) False for dropped wild points
    variance_factor: float  # a-posteriori s² = weighted RSS / dof
    parameter_covariance: FloatArray  # (6, 6)
    optimize_result: OptimizeResult  # the geometric refinement's result
    start_radius_mm: float  # radius of the algebraic (Taubin) start

    # -- geometry ------------------------------------------------------------------------
    @property
    def axis_v(self) -> FloatArray:
        return np.cross(self.normal, self.axis_u)

    @property
    def n_points(self) -> int:
        return int(self.points_mm.shape[0])

    @property
    def n_inliers(self) -> int:
        return int(self.inlier.sum())

    @property
    def dof(self) -> int:
        """Residual degrees of freedom: two distances per inlier minus six parameters."""
        return 2 * self.n_inliers - N_PARAMETERS

    @property
    def outliers(self) -> tuple[int, ...]:
        """Indices of the points dropped as wild."""
        return tuple(int(i) for i in np.flatnonzero(~self.inlier))

    def _local(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        w = self.points_mm - self.centre_mm
        return w @ self.axis_u, w @ self.axis_v, w @ self.normal

    @property
    def axial_residual_mm(self) -> FloatArray:
        """Signed distance of every point from the circle's plane, ``(N,)``."""
        return self._local()[2]

    @property
    def radial_residual_mm(self) -> FloatArray:
        """In-plane distance from the centre minus the radius, ``(N,)``."""
        x, y, _ = self._local()
        return np.hypot(x, y) - self.radius_mm

    @property
    def residual_rms_mm(self) -> float:
        """RMS 3-D distance of the inliers from the circle."""
        d2 = self.axial_residual_mm**2 + self.radial_residual_mm**2
        return float(np.sqrt(np.mean(d2[self.inlier])))

    @property
    def point_sigma_mm(self) -> FloatArray:
        """A-posteriori per-axis noise of every point, ``(N,)``: ``sqrt(s²)·sigma``."""
        return math.sqrt(self.variance_factor) * self.sigma_mm

    @property
    def angle_rad(self) -> FloatArray:
        """Angle of every point about the axis, ``(N,)`` in (-π, π]."""
        x, y, _ = self._local()
        return np.arctan2(y, x)

    def unwrapped_angle_rad(self) -> FloatArray:
        """:attr:`angle_rad` unwrapped along the point order (consecutive steps < 180°)."""
        return np.unwrap(self.angle_rad)

    @property
    def parameter_std(self) -> FloatArray:
        """Standard deviations of :data:`PARAMETER_NAMES`, ``(6,)``."""
        return np.sqrt(np.diag(self.parameter_covariance))

    # -- angle uncertainty -----------------------------------------------------------------
    def angle_jacobian(self) -> FloatArray:
        """∂angle/∂parameters ``(N, 6)`` (central differences; the radius column is zero)."""
        steps = np.array([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 0.0]) * np.array(
            [max(self.radius_mm, 1.0)] * 3 + [1.0, 1.0, 0.0]
        )
        jac = np.zeros((self.n_points, N_PARAMETERS))
        for k in range(5):
            d = np.zeros(N_PARAMETERS)
            d[k] = steps[k]
            plus = _angles_at(self, d)
            minus = _angles_at(self, -d)
            jac[:, k] = np.angle(np.exp(1j * (plus - minus))) / (2 * steps[k])
        return jac

    def angle_covariance_factors(self) -> tuple[FloatArray, FloatArray]:
        """The angle covariance as ``diag(d) + B·Bᵀ``: ``d`` ``(N,)`` and ``B`` ``(N, 6)``, rad².

        ``d`` is the independent tangential part ``σ_k² / r_k²``; ``B = G·L`` carries the part
        shared through the circle parameters (``G`` = :meth:`angle_jacobian`, ``L·Lᵀ`` =
        :attr:`parameter_covariance`). Cheap for large N, unlike the full matrix.
        """
        x, y, _ = self._local()
        tangential = (self.point_sigma_mm / np.hypot(x, y)) ** 2
        w, e = np.linalg.eigh(self.parameter_covariance)
        root = e * np.sqrt(np.clip(w, 0.0, None))
        return tangential, self.angle_jacobian() @ root

    def flipped(self) -> CircleFit:
        """The same circle with the normal reversed: every angle changes sign."""
        cov = self.parameter_covariance.copy()
        # -n + tu'·u + tv'·v' with v' = -v is the plane of n - tu'·u + tv'·v: tu flips
        sign = np.array([1.0, 1.0, 1.0, -1.0, 1.0, 1.0])
        cov = cov * np.outer(sign, sign)
        return replace(self, normal=-self.normal, parameter_covariance=cov)


def _basis(normal: FloatArray) -> FloatArray:
    """A unit vector in the plane of ``normal``: the world axis least aligned with it."""
    ref = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = ref - (ref @ normal) * normal
    unit: FloatArray = u / np.linalg.norm(u)
    return unit


def _tilted_normal(
    normal: FloatArray, u: FloatArray, v: FloatArray, tu: float, tv: float
) -> FloatArray:
    n = normal + tu * u + tv * v
    unit: FloatArray = n / np.linalg.norm(n)
    return unit


def _angles_at(fit: CircleFit, delta: FloatArray) -> FloatArray:
    """Angles of all points for the fit's parameters moved by ``delta`` (6,)."""
    c = fit.centre_mm + delta[:3]
    u0, v0 = fit.axis_u, fit.axis_v
    n = _tilted_normal(fit.normal, u0, v0, delta[3], delta[4])
    # axis_u follows the normal the same way the fit defines it: projection of u0
    u = u0 - (u0 @ n) * n
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    w = fit.points_mm - c
    angles: FloatArray = np.arctan2(w @ v, w @ u)
    return angles


def _plane_svd(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    return centroid, vt[2]


def taubin_circle_2d(xy: FloatArray) -> tuple[FloatArray, float]:
    """Taubin's algebraic circle fit (SVD form, after Chernov): centre ``(2,)`` and radius."""
    centroid = xy.mean(axis=0)
    x, y = (xy - centroid).T
    z = x * x + y * y
    z_mean = z.mean()
    if not z_mean > 0:
        raise CircleFitError("all points coincide")
    z0 = (z - z_mean) / (2.0 * math.sqrt(z_mean))
    _, s, vt = np.linalg.svd(np.column_stack([z0, x, y]), full_matrices=False)
    a = vt[2].copy()
    a0 = a[0] / (2.0 * math.sqrt(z_mean))
    a3 = -z_mean * a0
    if abs(a0) < 1e-14 * np.linalg.norm(a[1:]) or s[1] <= 0:
        raise CircleFitError("points are collinear: no circle through them")
    centre = -a[1:3] / a0 / 2.0 + centroid
    radius = math.sqrt(a[1] ** 2 + a[2] ** 2 - 4.0 * a0 * a3) / abs(a0) / 2.0
    return centre, radius


def circle_residuals(
    x: FloatArray,
    points: FloatArray,
    weight: FloatArray,
    normal0: FloatArray,
    u0: FloatArray,
    v0: FloatArray,
) -> FloatArray:
    """Weighted axial then radial distances ``(2N,)`` of ``points`` from the circle ``x``.

    ``x = (cx, cy, cz, tilt_u, tilt_v, radius)``; the normal is ``normal0`` tilted by
    ``tilt_u·u0 + tilt_v·v0`` and renormalized. Pure: no state is changed.
    """
    n = _tilted_normal(normal0, u0, v0, x[3], x[4])
    w = points - x[:3]
    a = w @ n
    r = np.sqrt(np.maximum(np.einsum("ij,ij->i", w, w) - a * a, 0.0))
    return np.concatenate([a * weight, (r - x[5]) * weight])


def circle_jacobian(
    x: FloatArray,
    points: FloatArray,
    weight: FloatArray,
    normal0: FloatArray,
    u0: FloatArray,
    v0: FloatArray,
) -> FloatArray:
    """Analytic Jacobian ``(2N, 6)`` of :func:`circle_residuals`."""
    m = normal0 + x[3] * u0 + x[4] * v0
    length = np.linalg.norm(m)
    n = m / length
    proj = np.eye(3) - np.outer(n, n)
    dn = np.stack([proj @ u0, proj @ v0], axis=1) / length  # (3, 2)
    w = points - x[:3]
    a = w @ n
    r = np.sqrt(np.maximum(np.einsum("ij,ij->i", w, w) - a * a, 1e-300))
    v = w - a[:, None] * n
    da_dt = w @ dn  # (N, 2)
    jac = np.empty((2 * len(points), N_PARAMETERS))
    n_pts = len(points)
    jac[:n_pts, :3] = -n
    jac[:n_pts, 3:5] = da_dt
    jac[:n_pts, 5] = 0.0
    jac[n_pts:, :3] = -v / r[:, None]
    jac[n_pts:, 3:5] = -(a / r)[:, None] * da_dt
    jac[n_pts:, 5] = -1.0
    weighted: FloatArray = jac * np.concatenate([weight, weight])[:, None]
    return weighted


@dataclass(frozen=True, eq=False)
class _Core:
    centre: FloatArray
    normal: FloatArray
    radius: float
    covariance_unit: FloatArray  # (6,6) for unit variance factor, tilts about (u, v) below
    u: FloatArray
    s2: float
    rss: float
    dof: int
    result: OptimizeResult
    start_radius: float


def _fit_core(points: FloatArray, sigma: FloatArray) -> _Core:
    centroid, n0 = _plane_svd(points)
    u0 = _basis(n0)
    v0 = np.cross(n0, u0)
    local = points - centroid
    xy = np.column_stack([local @ u0, local @ v0])
    c2, rho0 = taubin_circle_2d(xy)
    c0 = centroid + c2[0] * u0 + c2[1] * v0
    weight = 1.0 / sigma
    x0 = np.concatenate([c0, [0.0, 0.0, rho0]])
    args = (points, weight, n0, u0, v0)
    from scipy.optimize import least_squares

    result = least_squares(
        circle_residuals,
        x0,
        jac=circle_jacobian,
        args=args,
        method="lm",
        x_scale="jac",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    x = result.x
    normal = _tilted_normal(n0, u0, v0, x[3], x[4])
    # re-express the tilt covariance about the final normal's own basis
    u = u0 - (u0 @ normal) * normal
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    jac = circle_jacobian(np.concatenate([x[:3], [0.0, 0.0], x[5:]]), *args[:2], normal, u, v)
    info = jac.T @ jac
    try:
        # numpy's stubs type inv() of a float64 array as floating[Any]
        cov_unit = cast(FloatArray, np.linalg.inv(info))
    except np.linalg.LinAlgError as exc:
        raise CircleFitError("points do not determine a circle (singular fit)") from exc
    dof = 2 * len(points) - N_PARAMETERS
    rss = float(np.sum(result.fun**2))
    s2 = rss / dof
    return _Core(x[:3].copy(), normal, float(x[5]), cov_unit, u, s2, rss, dof, result, rho0)


def _point_chi2(core: _Core, points: FloatArray, sigma: FloatArray) -> FloatArray:
    w = points - core.centre
    a = w @ core.normal
    r = np.sqrt(np.maximum(np.einsum("ij,ij->i", w, w) - a * a, 0.0))
    chi2: FloatArray = (a * a + (r - core.radius) ** 2) / sigma**2
    return chi2


def fit_circle_3d(
    points_mm: ArrayLike,
    sigma_mm: ArrayLike | float | None = None,
    *,
    max_outliers: int | None = None,
    outlier_alpha: float = 1e-3,
) -> CircleFit:
    """Fit a circle to points in 3-D; drop wild points; give each point's angle.

    ``points_mm`` ``(N, 3)``, N ≥ 4, in the order the target visited them. ``sigma_mm``: the
    per-axis noise of each point (scalar or ``(N,)``); only its *relative* size matters
    for the fit, the scale comes from the residuals (``variance_factor``). A point is
    dropped when its squared distance from the circle fitted without it, in units of the
    noise, exceeds the χ²₂ quantile at ``outlier_alpha / N`` (at most ``max_outliers``
    points, default ``max(1, N // 25)``).
    """
    pts, sigma = _checked_inputs(points_mm, sigma_mm)
    n = len(pts)
    if max_outliers is None:
        max_outliers = max(1, n // 25)
    inlier, core = _without_wild_points(pts, sigma, max_outliers, outlier_alpha)
    fit = CircleFit(
        centre_mm=core.centre,
        normal=core.normal,
        axis_u=core.u,
        radius_mm=core.radius,
        points_mm=pts,
        sigma_mm=sigma,
        inlier=inlier,
        variance_factor=core.s2,
        parameter_covariance=core.s2 * core.covariance_unit,
        optimize_result=core.result,
        start_radius_mm=core.start_radius,
    )
    steps = np.diff(np.unwrap(fit.angle_rad[inlier]))
    return fit.flipped() if steps.sum() < 0 else fit


def _checked_inputs(
    points_mm: ArrayLike, sigma_mm: ArrayLike | float | None
) -> tuple[FloatArray, FloatArray]:
    """The points ``(N, 3)`` mm and their σ ``(N,)`` (ones when not given), checked."""
    pts = np.asarray(points_mm, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CircleFitError(f"points must have shape (N, 3), got {pts.shape}")
    n = len(pts)
    if n < MIN_POINTS:
        raise CircleFitError(f"a 3-D circle fit needs at least {MIN_POINTS} points, got {n}")
    if not np.all(np.isfinite(pts)):
        raise CircleFitError("points must be finite (no NaN or inf)")
    if sigma_mm is None:
        return pts, np.ones(n)
    sigma = np.broadcast_to(np.asarray(sigma_mm, dtype=float), (n,)).copy()
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise CircleFitError("sigma must be finite and positive")
    return pts, sigma


def _without_wild_points(
    pts: FloatArray, sigma: FloatArray, max_outliers: int, outlier_alpha: float
) -> tuple[NDArray[np.bool_], _Core]:
    """Drop the worst point while, fitted without it, it lies beyond the χ²₂ limit (at
    most ``max_outliers``); the points kept ``(N,)`` and their fit."""
    inlier = np.ones(len(pts), dtype=bool)
    core = _fit_core(pts, sigma)
    while (~inlier).sum() < max_outliers and inlier.sum() > MIN_POINTS + 1:
        idx = np.flatnonzero(inlier)
        chi2 = _point_chi2(core, pts[idx], sigma[idx])
        robust_s2 = max(float(np.median(chi2)) / (2.0 * math.log(2.0)), 1e-300)
        limit = 2.0 * math.log(len(idx) / outlier_alpha)  # χ²₂ tail at alpha / N
        worst = int(np.argmax(chi2))
        if chi2[worst] / robust_s2 <= limit:
            break
        trial = inlier.copy()
        trial[idx[worst]] = False
        candidate = _fit_core(pts[trial], sigma[trial])
        deleted = _point_chi2(candidate, pts[idx[worst] : idx[worst] + 1], sigma[idx[worst]])[0]
        inflation = 1.0 + N_PARAMETERS / trial.sum()
        if deleted / (candidate.s2 * inflation) <= limit:
            break
        inlier, core = trial, candidate
    return inlier, core
