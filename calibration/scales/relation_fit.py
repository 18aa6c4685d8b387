"""The relation's fits over one joint's stops (method §2, step 4): to the stop angles
(two-step) or to the tracker points together with the circle or target-set structure,
wild stop angles dropped, and the Cramér-Rao bound of its coefficients."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import ScaleError
from calibration.scales.circle_fit import CircleFit
from calibration.scales.relation_to_points import RelationToPoints, StopPoints
from calibration.scales.scale_relation import RelationBasis
from calibration.scales.target_set_fit import TargetSetFit, crb_covariance_targets
from calibration.scales.whitened_gls import GlsFit, Whitener, gls_fit, whitened, worst_residual
from edges.errors import NumericalError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class NoJointFit(NumericalError):
    """The relation's fit to the points did not converge (the caller falls back)."""


def crb_covariance(
    circle: CircleFit, angle_rad: ArrayLike, design: ArrayLike, sigma_mm: ArrayLike
) -> FloatArray:
    """Cramér-Rao bound on the coefficients of ``θ_k = design_k · β`` (rad units).

    The bound of the direct 3-D model ``p_k = c + ρ(cos θ_k·u + sin θ_k·v) + noise``,
    isotropic per-axis noise ``sigma_mm`` ``(S,)``, with the circle (centre, normal,
    radius) unknown. ``circle`` supplies the geometry, ``angle_rad`` ``(S,)`` the stop
    angles in its frame, ``design`` ``(S, p)`` the relation's columns (the first should be
    the intercept θ₀). Returns the ``(p, p)`` block of the inverse Fisher information.
    """
    th = np.asarray(angle_rad, dtype=float)
    x = np.asarray(design, dtype=float)
    sig = np.broadcast_to(np.asarray(sigma_mm, dtype=float), th.shape)
    u, v = circle.axis_u, circle.axis_v
    radial = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v  # (S, 3)
    tangent = -np.sin(th)[:, None] * u + np.cos(th)[:, None] * v
    rel = circle.radius_mm * radial
    cols = [np.broadcast_to(np.eye(3)[i], rel.shape) for i in range(3)]
    cols += [np.cross(v, rel), -np.cross(u, rel), radial]  # tilts and radius
    cols += [circle.radius_mm * tangent * x[:, j : j + 1] for j in range(x.shape[1])]
    jac = np.stack(cols, axis=-1) / sig[:, None, None]  # (S, 3, 6 + p)
    info = np.einsum("kai,kaj->ij", jac, jac)
    scale = np.sqrt(np.diag(info))
    scale[scale == 0] = 1.0
    cov = np.linalg.pinv(info / np.outer(scale, scale), rcond=1e-12, hermitian=True)
    cov_angles: FloatArray = (cov / np.outer(scale, scale))[6:, 6:]
    return cov_angles


def first_order_gain(
    theta: FloatArray, u: FloatArray, whitened: tuple[Whitener, IntArray], joint: int
) -> float:
    """The straight line's slope (rad per count) of the stop angles ``theta`` ``(K,)`` on
    the count offsets ``u`` ``(K,)``, over the stops ``whitened`` holds."""
    white, idx = whitened
    base = gls_fit(theta[idx], np.column_stack([np.ones(idx.size), u[idx]]), white)
    g0 = float(base.beta[1])
    if g0 == 0 or not np.isfinite(g0):
        raise ScaleError(f"joint {joint}: counts do not change with the joint angle")
    return g0


def basis_over(g0: float, span: FloatArray) -> RelationBasis:
    """The basis for the count offsets ``span`` ``(K,)`` the relation is fitted on: the cyclic
    phase from the first-order gain ``g0`` rad per count, the polynomials over their range."""
    return RelationBasis(
        phase_rad_per_count=g0,
        nonlinear_centre_counts=0.5 * float(span.max() + span.min()),
        nonlinear_half_span_counts=max(0.5 * float(span.max() - span.min()), 1.0),
    )


def relation_design(
    basis: RelationBasis, u: FloatArray, s: FloatArray, terms: Sequence[str]
) -> FloatArray:
    """The relation's design ``(K, 2 + …)``: the intercept θ₀, then the basis columns."""
    _, x = basis.columns(u, s, terms)
    return np.column_stack([np.ones_like(u), x])


@dataclass(frozen=True, eq=False)
class WildAngles:
    """The test for wild stop angles (a tangential wild point is invisible to the circle):
    the angles ``theta`` ``(K,)`` on the full model ``design`` ``(K, p)``, their covariance
    factors ``d`` ``(K,)``, ``b`` ``(K, r)``, the stops' rows ``order`` ``(K,)``."""

    theta: FloatArray
    design: FloatArray
    d: FloatArray
    b: FloatArray
    order: IntArray

    def drop(
        self, inlier: NDArray[np.bool_], dropped: list[tuple[int, str]], outlier_alpha: float
    ) -> tuple[Whitener, IntArray]:
        """Drop the worst stop while its studentized residual is beyond the limit, at most
        one stop in 25 (``inlier`` and ``dropped`` in place); the whitener of the stops left
        and their indices."""
        white, idx = whitened(self.d, self.b, inlier)
        for _ in range(max(1, int(inlier.sum()) // 25)):
            k, z, limit = worst_residual(self.theta[idx], self.design[idx], white, outlier_alpha)
            if abs(z) <= limit:
                break
            inlier[idx[k]] = False
            dropped.append((int(self.order[idx[k]]), f"relation: angle residual {z:+.1f}σ"))
            white, idx = whitened(self.d, self.b, inlier)
        return white, idx


@dataclass(frozen=True, eq=False)
class RelationFits:
    """The relation's fits over one joint's stops (K of them): their count offsets from the
    zero ``u`` and pass signs ``s`` ``(K,)``, their angles ``theta`` ``(K,)`` rad, the stops
    used ``idx`` and the whitener of their angles' covariance."""

    basis: RelationBasis
    u: FloatArray
    s: FloatArray
    theta: FloatArray
    idx: IntArray
    white: Whitener
    points: StopPoints
    read_noise_rad: float
    joint_fits: dict[tuple[str, ...], RelationToPoints] = field(default_factory=dict)

    def design(self, terms: Sequence[str]) -> FloatArray:
        return relation_design(self.basis, self.u, self.s, terms)

    def fit_angles(self, terms: Sequence[str]) -> GlsFit:
        """Two-step: the relation fitted to the stop angles."""
        return gls_fit(self.theta[self.idx], self.design(terms)[self.idx], self.white)

    def fit_points(self, terms: Sequence[str]) -> GlsFit:
        """The relation and the structure fitted to the tracker points (kept per terms)."""
        key = tuple(terms)
        if key not in self.joint_fits:
            fit = self.points.fit(
                self.design(terms), self.fit_angles(terms).beta, self.read_noise_rad
            )
            if fit is None:
                raise NoJointFit
            self.joint_fits[key] = fit
        fit = self.joint_fits[key]
        return GlsFit(fit.beta, fit.cov_unit, fit.rss, fit.rank, fit.n)

    def refined_angles(self, kept: Sequence[str], circle: CircleFit | TargetSetFit) -> FloatArray:
        """The stops' angles ``(K,)`` rad under the structure refined with the relation
        ``kept`` (the circle's when the joint fit did not run)."""
        if tuple(kept) not in self.joint_fits:
            return self.theta
        refined = self.joint_fits[tuple(kept)].angle_rad
        theta: FloatArray = self.theta + np.angle(np.exp(1j * (refined - circle.angle_rad)))
        return theta

    def stop_angle_variance(
        self, final: GlsFit, x_all: FloatArray, b_all: FloatArray, d_circle: FloatArray
    ) -> FloatArray:
        """Unit variance ``(K,)`` of each stop's angle from Home by the circle, θ_k − θ̂₀:
        var = V_kk + var(θ̂₀) − 2 cov(θ̂₀, θ_k), cov(θ̂₀, θ_k) = [Cov·Xᵀ·V⁻¹·V]₀ₖ."""
        idx = self.idx
        wb = self.white.apply(b_all[idx])
        cov_theta0 = (final.cov_unit @ (self.white.apply(x_all[idx]).T @ wb))[0] @ b_all.T
        cov_theta0[idx] = (final.cov_unit @ x_all[idx].T)[0]  # used stops: V⁻¹·V = I
        var_stop = d_circle + np.einsum("ij,ij->i", b_all, b_all)
        var: FloatArray = var_stop + final.cov_unit[0, 0] - 2 * cov_theta0
        return var


def relation_crb(
    circle: CircleFit | TargetSetFit,
    theta_used: FloatArray,
    x_used: FloatArray,
    idx: IntArray,
    inlier: NDArray[np.bool_],
) -> tuple[FloatArray, CircleFit | TargetSetFit]:
    """The Cramér-Rao bound of the relation's coefficients over the stops used (their angles
    and design rows), and the angle fit as stored (a circle with the relation's inliers)."""
    if isinstance(circle, CircleFit):
        crb = crb_covariance(circle, theta_used, x_used, circle.point_sigma_mm[idx])
        return crb, replace(circle, inlier=inlier.copy())
    # a target set: its own bound; stops dropped by the relation are in `used`
    crb = crb_covariance_targets(
        circle, theta_used, x_used, circle.target_sigma_mm[idx], circle.point_inlier[idx]
    )
    return crb, circle
