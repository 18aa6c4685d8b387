"""The counts→angle relation fitted straight to the tracker points.

The grating-scale calibration first fits the stops' angles (a circle through one target,
or the rotation of a target set), then could fit the relation to those angles with their
full covariance (generalized least squares, :mod:`calibration.scales.grating_scale`). The two
steps agree with the maximum-likelihood fit to first order, but not to second order on
short arcs: the angle covariance is evaluated at the fitted axis, whose error is correlated
with the very noise the relation is fitted to. On a 4° arc with 10 stops per pass that
biased one target's scale by about half its standard deviation, and with three targets the
GLS noise level came out 7 % low and its F-tests kept twice the terms they should. This
module fits every candidate relation jointly with the structure::

    p_tk = c + h_t·n + r_t·(cos(φ_k + α_t)·a + sin(φ_k + α_t)·b) + e_tk,   φ_k = X_k·β

``e_tk ~ N(0, s²·σ_tk²·I₃)``; the axis point ``c`` (3), two tilts of the normal ``n`` (the
in-plane axes ``a``, ``b`` follow it as :class:`calibration.scales.circle_fit.CircleFit` defines
them), per target the radius ``r_t``, the height ``h_t`` and the phase ``α_t`` along and
about the axis (``h_0 = α_0 = 0``), and the relation ``β`` (constant column first: the
frame's angle origin). That is ``3T + 3`` structure parameters and ``q`` coefficients, on
``3·M`` coordinates of the M points in use. One target is the circle (``T = 1``). Started
from the two-step estimate, Levenberg-Marquardt; covariance Gauss-Newton, noise level from
all three coordinates (``3M − 3T − 3 − q`` degrees of freedom instead of ``K − q``), which
is also the residual of the nested-model F-tests between candidate relations.

The counts carry read noise too (0.5 count and the rounding: 0.55″ per stop on a 220 mm
strip), which moves all the points of a stop together along their tangents, as a
per-stop angle error would. With three targets the tracker fixes a stop's angle to about
1.5″, so that is no longer negligible: each stop's residuals are whitened for it
(covariance ``I + τ²·j·jᵀ`` in units of the points' noise, ``j`` the stop's tangent
levers, rank one per stop). On emulated 4° three-target arcs (1000 seeds) the hysteresis
F statistic averaged 1.19 without it, 1.11 with it (1.01 expected).

Units: mm, radians. Shapes: ``(K, T, 3)`` points, ``(K, T)`` per point, ``(K, q)`` design.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calibration.scales.circle_fit import CircleFit, _tilted_normal
from calibration.scales.target_set_fit import TargetSetFit
from calibration.scales.target_set_model import TargetSetGeometry

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IndexArray = NDArray[np.intp]

_TILT_STEP = 1e-7  # rad, central differences of the two tilt columns


@dataclass(frozen=True, eq=False)
class RelationToPoints:
    """One relation fitted to the points. ``cov_unit`` ``(q, q)`` times :attr:`s2` is the
    covariance of ``beta`` (the structure profiled out); ``angle_rad`` ``(K,)`` each stop's
    angle under the refined structure (its own points, no relation), wrapped to (−π, π]."""

    beta: FloatArray  # (q,)
    cov_unit: FloatArray  # (q, q)
    rss: float  # weighted residual sum of squares over the used points' 3 coordinates
    n: int  # 3 · points in use
    rank: int  # structure parameters + independent relation columns
    angle_rad: FloatArray  # (K,)

    @property
    def s2(self) -> float:
        return self.rss / max(self.n - self.rank, 1)


@dataclass(frozen=True, eq=False)
class StopPoints:
    """The points of a sweep's stops and the structure to start from.

    ``points_mm`` ``(K, T, 3)``, ``sigma_mm`` ``(K, T)`` per-axis weights, ``used``
    ``(K, T)`` the points in the fit; ``start`` the axis and the targets about it, heights
    from the axis point (``height_mm[0] = phase_rad[0] = 0``).
    """

    points_mm: FloatArray
    sigma_mm: FloatArray
    used: BoolArray
    start: TargetSetGeometry

    @classmethod
    def of(cls, fit: CircleFit | TargetSetFit, stop_inlier: BoolArray) -> StopPoints:
        """From the angle fit a sweep's stops came from; ``stop_inlier`` ``(K,)`` the stops
        the relation uses."""
        if isinstance(fit, CircleFit):
            start = TargetSetGeometry(
                fit.centre_mm, fit.normal, fit.axis_u, np.zeros(1), np.array([fit.radius_mm]),
                np.zeros(1),
            )  # fmt: skip
            pts, sigma = fit.points_mm[:, None, :], fit.sigma_mm[:, None]
            return cls(pts, sigma, stop_inlier[:, None], start)
        g = fit.geometry
        start = replace(g, centre_mm=g.centre_mm + g.height_mm[0] * g.normal,
                        height_mm=g.height_mm - g.height_mm[0])  # fmt: skip
        return cls(fit.points_mm, fit.sigma_mm, fit.point_inlier & stop_inlier[:, None], start)

    @property
    def n_targets(self) -> int:
        return self.start.n_targets

    # -- the model --------------------------------------------------------------------------
    def _unpack(self, x: FloatArray) -> tuple[FloatArray, ...]:
        """Centre, normal, in-plane axes a and b, radii, heights, phases, relation β."""
        t = self.n_targets
        u0, v0 = self.start.axis_u, self.start.axis_v
        n = _tilted_normal(self.start.normal, u0, v0, x[3], x[4])
        a = u0 - (u0 @ n) * n
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        radii = x[5 : 5 + t]
        height = np.concatenate([[0.0], x[5 + t : 4 + 2 * t]])
        phase = np.concatenate([[0.0], x[4 + 2 * t : 3 + 3 * t]])
        return x[:3], n, a, b, radii, height, phase, x[3 + 3 * t :]

    def _start(self, beta0: FloatArray) -> FloatArray:
        g = self.start
        return np.concatenate(
            [g.centre_mm, [0.0, 0.0], g.radii_mm, g.height_mm[1:], g.phase_rad[1:], beta0]
        )

    def _positions(self, x: FloatArray, design: FloatArray) -> FloatArray:
        """Model points ``(K, T, 3)``."""
        c, n, a, b, radii, height, phase, beta = self._unpack(x)
        ang = (design @ beta)[:, None] + phase[None, :]  # (K, T)
        radial = np.cos(ang)[..., None] * a + np.sin(ang)[..., None] * b
        positions: FloatArray = c + height[None, :, None] * n + radii[None, :, None] * radial
        return positions

    def stop_angles(self, x: FloatArray) -> FloatArray:
        """Each stop's angle ``(K,)`` from its used points under the structure of ``x``:
        the argument of ``Σ_t r_t e^{−iα_t} z_tk / σ_tk²`` (``z_tk`` the point about the
        axis, in-plane, as a complex number); a stop without used points from all its
        measured points."""
        c, n, a, b, radii, height, phase, _ = self._unpack(x)
        rel = np.nan_to_num(self.points_mm) - c - height[None, :, None] * n
        z = rel @ a + 1j * (rel @ b)
        measured = np.isfinite(self.points_mm).all(axis=-1)
        use = np.where(np.any(self.used, axis=1)[:, None], self.used, measured)
        w = np.where(use, radii / np.where(use, self.sigma_mm, 1.0) ** 2, 0.0)
        angles: FloatArray = np.angle(np.sum(w * np.exp(-1j * phase) * z, axis=1))
        return angles

    def _stop_whitener(
        self,
        x: FloatArray,
        design: FloatArray,
        kk: IndexArray,
        tt: IndexArray,
        w: FloatArray,
        angle_noise_rad: float,
    ) -> Callable[[FloatArray], FloatArray]:
        """``W`` for residuals ``(M, 3, ...)`` scaled by ``w``: per stop, their covariance
        ``I + τ²·j·jᵀ`` (``j`` the stop's scaled tangent levers) whitened along ``j``."""
        if angle_noise_rad <= 0:
            return lambda r: r
        _, _, a, b, radii, _, phase, beta = self._unpack(x)
        ang = (design @ beta)[kk] + phase[tt]
        lever = radii[tt][:, None] * (-np.sin(ang)[:, None] * a + np.cos(ang)[:, None] * b)
        j = lever * w[:, None]  # (M, 3)
        k = self.points_mm.shape[0]
        jj = np.bincount(kk, weights=np.einsum("ia,ia->i", j, j), minlength=k)
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = 1.0 - 1.0 / np.sqrt(1.0 + angle_noise_rad**2 * jj)
            shrink = np.where(jj > 0, gain / jj, 0.0)

        def apply(r: FloatArray) -> FloatArray:
            flat = r.reshape(r.shape[0], 3, -1)
            dots = np.einsum("ia,iap->ip", j, flat)  # (M, P)
            per_stop = np.zeros((k, flat.shape[2]))
            np.add.at(per_stop, kk, dots)
            out = flat - (shrink[kk][:, None, None] * j[:, :, None]) * per_stop[kk][:, None, :]
            return out.reshape(r.shape)

        return apply

    # -- the fit ----------------------------------------------------------------------------
    def fit(
        self, design: FloatArray, beta0: FloatArray, angle_noise_rad: float = 0.0
    ) -> RelationToPoints | None:
        """The relation with columns ``design`` ``(K, q)`` (constant first) and the structure,
        from ``beta0`` ``(q,)`` (the two-step estimate in the start's frame). ``None`` when
        the fit does not converge to a finite answer.

        ``angle_noise_rad``: the standard deviation of each stop's angle about the relation
        that the points do not carry (the grating's read noise times the scale): it moves
        all the points of a stop together along their tangents, so each stop's residuals
        are whitened for it (rank one per stop, evaluated at the start).
        """
        kk, tt = np.nonzero(self.used)
        pts = self.points_mm[kk, tt]
        w = 1.0 / self.sigma_mm[kk, tt]
        t = self.n_targets
        n_struct = 3 * t + 3
        x0 = self._start(beta0)
        whiten = self._stop_whitener(x0, design, kk, tt, w, angle_noise_rad)

        def residuals(x: FloatArray) -> FloatArray:
            return whiten((pts - self._positions(x, design)[kk, tt]) * w[:, None]).ravel()

        def jacobian(x: FloatArray) -> FloatArray:
            jac = self._residual_jacobian(x, design, kk, tt)
            return whiten(jac * w[:, None, None]).reshape(3 * kk.size, -1)

        try:
            result = least_squares(
                residuals,
                x0,
                jac=jacobian,
                method="lm",
                x_scale="jac",
                xtol=1e-12,
                ftol=1e-12,
            )
        except (ValueError, np.linalg.LinAlgError):
            return None
        x = result.x
        if not (result.success and np.all(np.isfinite(x)) and np.all(x[5 : 5 + t] > 0)):
            return None
        cov, rank = _unit_covariance(jacobian(x))
        return RelationToPoints(
            beta=x[n_struct:].copy(),
            cov_unit=cov[n_struct:, n_struct:],
            rss=float(result.fun @ result.fun),
            n=3 * kk.size,
            rank=rank,
            angle_rad=self.stop_angles(x),
        )

    def _residual_jacobian(
        self, x: FloatArray, design: FloatArray, kk: IndexArray, tt: IndexArray
    ) -> FloatArray:
        """∂(point − model)/∂x ``(M, 3, P)`` mm per unit of each parameter, for the used
        points (stop ``kk``, target ``tt``), unweighted."""
        t = self.n_targets
        _, n, a, b, radii, _, phase, beta = self._unpack(x)
        ang = (design @ beta)[kk] + phase[tt]
        radial = np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b  # (M, 3)
        tangent = -np.sin(ang)[:, None] * a + np.cos(ang)[:, None] * b
        m = kk.size
        jac = np.zeros((m, 3, x.size))
        jac[:, :, :3] = -np.eye(3)
        for k in (3, 4):  # the tilts move n, a and b: central differences
            d = np.zeros_like(x)
            d[k] = _TILT_STEP
            plus = self._positions(x + d, design)[kk, tt]
            minus = self._positions(x - d, design)[kk, tt]
            jac[:, :, k] = -(plus - minus) / (2 * _TILT_STEP)
        rows = np.arange(m)
        jac[rows, :, 5 + tt] = -radial
        lever = radii[tt][:, None] * tangent  # ∂p/∂angle
        for j in range(1, t):
            sel = tt == j
            jac[sel, :, 4 + t + j] = -n
            jac[sel, :, 3 + 2 * t + j] = -lever[sel]
        jac[:, :, 3 * t + 3 :] = -lever[:, :, None] * design[kk][:, None, :]
        return jac


def _unit_covariance(jac: FloatArray) -> tuple[FloatArray, int]:
    """``(JᵀJ)⁻¹`` ``(P, P)`` of a weighted Jacobian ``(N, P)`` (columns scaled, directions
    below 1e-10 of the largest singular value left out), and its rank."""
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    _, sv, vt = np.linalg.svd(jac / scale, full_matrices=False)
    keep = sv > 1e-10 * sv[0]
    cov: FloatArray = ((vt[keep].T / sv[keep] ** 2) @ vt[keep]) / np.outer(scale, scale)
    return cov, int(keep.sum())
