"""The counts→angle relation fitted straight to the tracker points of one target.

The grating-scale calibration first fits a circle, then the relation to the circle's
angles with their full covariance (generalized least squares, :mod:`calibration.grating_scale`).
The two steps agree with the maximum-likelihood fit to first order, which is enough for
choosing the relation's terms. On a short arc (a few degrees, one target) they do not agree
to second order: the angle covariance is evaluated at the fitted centre, whose error is
correlated with the very noise the relation is fitted to, and the relation's scale comes out
biased by about half its standard deviation (4° arc, 10 stops per pass, 16 µm tracker noise).
This module refines the chosen relation by the joint maximum-likelihood fit::

    p_k = c + R·(cos φ_k·a + sin φ_k·b) + e_k,    φ_k = X_k·β,    e_k ~ N(0, σ_k²·I₃)

over the circle (centre ``c``, two tilts of the normal, radius ``R``; ``a``, ``b`` the
in-plane axes of the tilted normal, as :class:`calibration.circle_fit.CircleFit` defines
them) and the relation coefficients ``β`` together, started from the two-step estimate.
Its noise level comes from all three coordinates (3·N − 6 − q degrees of freedom instead of
N − q), its scale is unbiased on short arcs, and its covariance is the Gauss-Newton one.

Units: mm, radians. ``X`` carries the constant column first (the circle frame's origin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calibration.circle_fit import CircleFit, _tilted_normal

FloatArray = NDArray[np.float64]

_N_CIRCLE = 6  # centre (3), tilts (2), radius
_TILT_STEP = 1e-7  # rad, central differences of the two tilt columns


@dataclass(frozen=True, eq=False)
class RelationToPoints:
    """The joint fit's relation. ``cov_unit`` ``(q, q)`` times ``s2`` is the covariance of
    ``beta``; ``angle_rad`` ``(N,)`` the angle of every point (inliers and not) about the
    refined circle, in its frame, wrapped to (−π, π]."""

    beta: FloatArray  # (q,)
    cov_unit: FloatArray  # (q, q)
    rss: float  # weighted residual sum of squares over the inliers' 3 coordinates
    n: int  # 3 · inliers
    rank: int  # 6 + q
    angle_rad: FloatArray  # (N,)
    radius_mm: float

    @property
    def s2(self) -> float:
        return self.rss / max(self.n - self.rank, 1)


def _frame(circle: CircleFit, tilt: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Normal and in-plane axes for the circle's normal tilted by ``tilt`` (2,)."""
    u0, v0 = circle.axis_u, circle.axis_v
    n = _tilted_normal(circle.normal, u0, v0, tilt[0], tilt[1])
    a = u0 - (u0 @ n) * n
    a /= np.linalg.norm(a)
    return n, a, np.cross(n, a)


def _model(circle: CircleFit, x: FloatArray, design: FloatArray) -> FloatArray:
    _, a, b = _frame(circle, x[3:5])
    phi = design @ x[_N_CIRCLE:]
    return x[:3] + x[5] * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)


def fit_relation_to_points(
    circle: CircleFit, design: FloatArray, beta0: FloatArray, inlier: NDArray[np.bool_]
) -> RelationToPoints | None:
    """Refine ``beta0`` ``(q,)`` and the circle jointly on the inlier points.

    ``design`` ``(N, q)`` over all of ``circle.points_mm`` (the relation's columns, constant
    first); ``beta0`` from the two-step fit in ``circle``'s frame. Returns ``None`` when the
    refinement does not converge to a finite answer (the caller keeps the two-step fit).
    """
    idx = np.flatnonzero(inlier)
    pts = circle.points_mm[idx]
    x_in = design[idx]
    w = 1.0 / circle.sigma_mm[idx]

    def residuals(x: FloatArray) -> FloatArray:
        return ((pts - _model(circle, x, x_in)) * w[:, None]).ravel()

    def jacobian(x: FloatArray) -> FloatArray:
        _, a, b = _frame(circle, x[3:5])
        phi = x_in @ x[_N_CIRCLE:]
        radial = np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b  # (n, 3)
        tangent = -np.sin(phi)[:, None] * a + np.cos(phi)[:, None] * b
        n_pts, q = x_in.shape
        jac = np.empty((n_pts, 3, _N_CIRCLE + q))
        jac[:, :, :3] = -np.eye(3)
        for k in (3, 4):  # the tilts move the in-plane axes: central differences
            d = np.zeros_like(x)
            d[k] = _TILT_STEP
            jac[:, :, k] = -(_model(circle, x + d, x_in) - _model(circle, x - d, x_in)) / (
                2 * _TILT_STEP
            )
        jac[:, :, 5] = -radial
        jac[:, :, _N_CIRCLE:] = -x[5] * tangent[:, :, None] * x_in[:, None, :]
        return (jac * w[:, None, None]).reshape(3 * n_pts, -1)

    x0 = np.concatenate([circle.centre_mm, [0.0, 0.0, circle.radius_mm], beta0])
    try:
        result = least_squares(
            residuals, x0, jac=jacobian, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12
        )
    except (ValueError, np.linalg.LinAlgError):
        return None
    x = result.x
    if not (result.success and np.all(np.isfinite(x)) and x[5] > 0):
        return None
    jac = jacobian(x)
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    cov = np.linalg.pinv((jac / scale).T @ (jac / scale), rcond=1e-12, hermitian=True)
    cov = cov / np.outer(scale, scale)
    _, a, b = _frame(circle, x[3:5])
    rel = circle.points_mm - x[:3]
    q = design.shape[1]
    return RelationToPoints(
        beta=x[_N_CIRCLE:].copy(),
        cov_unit=cov[_N_CIRCLE:, _N_CIRCLE:],
        rss=float(result.fun @ result.fun),
        n=3 * idx.size,
        rank=_N_CIRCLE + q,
        angle_rad=np.arctan2(rel @ b, rel @ a),
        radius_mm=float(x[5]),
    )
