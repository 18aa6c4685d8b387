"""Generalized least squares of the stop angles under their covariance ``diag(d) + B·Bᵀ``
(B of low rank, whitened in O(N)), the nested-model F-test, and the largest
studentized residual (method §2, steps 4-5)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Whitener:
    """``W`` with ``WᵀW = V⁻¹`` for ``V = diag(d) + B·Bᵀ`` (B of low rank), in O(N)."""

    d: FloatArray  # (n,)
    b: FloatArray  # (n, r)
    basis: FloatArray  # (n, r) left singular vectors of D^-1/2 B
    shrink: FloatArray  # (r,)

    @classmethod
    def build(cls, d: FloatArray, b: FloatArray) -> Whitener:
        bd = b / np.sqrt(d)[:, None]
        basis, sv, _ = np.linalg.svd(bd, full_matrices=False)
        return cls(d, b, basis, 1.0 - 1.0 / np.sqrt(1.0 + sv**2))

    def apply(self, x: FloatArray) -> FloatArray:
        """``W·x`` for ``x`` of shape ``(n,)`` or ``(n, p)``."""
        z = x.reshape(len(self.d), -1) / np.sqrt(self.d)[:, None]
        z = z - self.basis @ (self.shrink[:, None] * (self.basis.T @ z))
        return z.reshape(x.shape)

    @property
    def diag(self) -> FloatArray:
        total: FloatArray = self.d + np.einsum("ij,ij->i", self.b, self.b)
        return total


@dataclass(frozen=True, eq=False)
class GlsFit:
    beta: FloatArray
    cov_unit: FloatArray  # (XᵀV⁻¹X)⁻¹
    rss: float  # rᵀV⁻¹r
    rank: int
    n: int

    @property
    def s2(self) -> float:
        return self.rss / max(self.n - self.rank, 1)


def gls_fit(y: FloatArray, x: FloatArray, white: Whitener) -> GlsFit:
    """Generalized least squares of ``y`` on ``x`` (columns scaled for conditioning)."""
    x_w = white.apply(x)
    y_w = white.apply(y)
    norms = np.linalg.norm(x_w, axis=0)
    norms[norms == 0] = 1.0
    a = x_w / norms
    left, sv, vt = np.linalg.svd(a, full_matrices=False)
    keep = sv > 1e-10 * sv[0]
    coef = (vt[keep].T / sv[keep]) @ (left[:, keep].T @ y_w)
    resid_w = y_w - a @ coef
    cov = ((vt[keep].T / sv[keep] ** 2) @ vt[keep]) / np.outer(norms, norms)
    return GlsFit(coef / norms, cov, float(resid_w @ resid_w), int(keep.sum()), len(y))


def f_test(full: GlsFit, reduced: GlsFit) -> tuple[float, int, int, float]:
    """Nested-model F-test: statistic, term dof, residual dof, p-value."""
    from scipy import stats  # loads when a fit runs: a refused input is said at once

    d1 = full.rank - reduced.rank
    d2 = full.n - full.rank
    if d1 <= 0 or d2 <= 0 or full.rss <= 0:
        return 0.0, max(d1, 0), d2, 1.0
    f = ((reduced.rss - full.rss) / d1) / (full.rss / d2)
    return float(f), d1, d2, float(stats.f.sf(max(f, 0.0), d1, d2))


def worst_residual(
    theta: FloatArray, x: FloatArray, white: Whitener, outlier_alpha: float
) -> tuple[int, float, float]:
    """Index of the largest studentized residual (robust scale), its z, and the limit."""
    from scipy import stats  # loads when a fit runs: a refused input is said at once

    fit = gls_fit(theta, x, white)
    resid = theta - x @ fit.beta
    var = white.diag - np.einsum("ij,jk,ik->i", x, fit.cov_unit, x)
    z = resid / np.sqrt(np.maximum(var, 1e-300))
    z = z / max(1.4826 * float(np.median(np.abs(z))), 1e-300)
    k = int(np.argmax(np.abs(z)))
    return k, float(z[k]), float(stats.norm.isf(outlier_alpha / (2 * len(theta))))


def whitened(d: FloatArray, b: FloatArray, inlier: NDArray[np.bool_]) -> tuple[Whitener, IntArray]:
    """The whitener of the inlier stops' angle covariance ``diag(d) + B·Bᵀ``, and their indices."""
    idx = np.flatnonzero(inlier)
    return Whitener.build(d[idx], b[idx]), idx
