"""The planner's I-optimal criterion, with the bias of what the fit leaves out, and the
selection that minimises it by rank-3 updates.

A campaign is worth the error of the twin calibrated from it, averaged over the region
where the robot works. The twin fits some parameters (the geometry and the effects the
closed loop can add from the campaign's pose count, blocks ``h``) and leaves others out
(an effect the loop cannot add from so few poses, blocks ``g``, scaled by their prior
1 σ so their values are N(0, I)): those it absorbs into the fitted ones, and the
prediction is biased. With ``M`` the chosen poses' information plus the prior, ``A = M⁻¹``,
``C = Σ hᵢᵀgᵢ`` and ``D = A·C`` (how the left-out parameters alias into the fitted ones),
the expected mean squared prediction error over the region (mm²) is

    f = trace(W·A) + trace(Dᵀ·W·D) − 2·trace(Dᵀ·X) + z

with ``W``, ``X``, ``z`` the region's means of the unweighted ``hᵀh``, ``hᵀg``, ``trace(gᵀg)``
(the variance of the fit, then the bias: Box & Draper's integrated mean squared error;
with nothing left out it is the Bayesian I-criterion ``trace(W·M⁻¹)``).

Adding (σ = +1) or removing (σ = −1) one pose ``b`` changes ``A`` by ``−u_bᵀK⁻¹u_b`` and ``D``
by ``u_bᵀK⁻¹R_b`` (``u = h·A``, ``K = σI + h_b·A·h_bᵀ``, ``R = g − h·D``): a rank-3 change.
Every candidate's 3×3 and 3×q quantities follow by rank-3 updates too, ``N·9·(r + q)`` a
step instead of ``N·3·r²``: exchange passes (each chosen pose swapped for the candidate
that lowers ``f`` most) on a shortlist, from a start whose information is already well
conditioned (the D-optimal greedy selection: from the prior alone, the first poses would
cut ``h·A·hᵀ`` from ~1e7 to ~1 and the updates would lose every digit).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.identify.pose_selection import block_products

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Candidates an exchange pass considers: the chosen and those whose addition would lower
#: the criterion most (a swap's partner is almost always among them).
SHORTLIST = 200
#: Passes that share one shortlist (the chosen change little between two passes).
RESHORTLIST = 2
#: An exchange pass that lowers the criterion by less than this fraction ends the search.
MIN_PASS_GAIN = 1e-3


@dataclass(frozen=True, eq=False)
class DesignProblem:
    """What the criterion needs: ``h`` ``(N, 3, r)`` fitted and ``g`` ``(N, 3, q)`` left-out
    blocks, both σ-weighted (``g`` scaled by its prior 1 σ); the region's ``w`` ``(r, r)``,
    ``x`` ``(r, q)`` and ``z`` (mm²) of the unweighted blocks; ``prior`` ``(r, r)``."""

    h: FloatArray
    g: FloatArray
    w: FloatArray
    x: FloatArray
    z: float
    prior: FloatArray


@dataclass(frozen=True)
class CriterionValue:
    """``f`` of a set and its parts (mm²): the fit's variance and the left-out bias."""

    variance_mm2: float
    bias_mm2: float

    @property
    def total_mm2(self) -> float:
        return self.variance_mm2 + self.bias_mm2


def criterion_value(problem: DesignProblem, rows: IntArray) -> CriterionValue:
    """``f`` of the poses ``rows`` (module text), exactly."""
    h, g = problem.h[rows], problem.g[rows]
    a = np.linalg.inv(problem.prior + np.einsum("nip,niq->pq", h, h))
    d = a @ np.einsum("nip,niq->pq", h, g)
    bias = float(np.sum(d * (problem.w @ d)) - 2.0 * np.sum(d * problem.x) + problem.z)
    return CriterionValue(float(np.sum(problem.w * a)), bias)


def drift_bias(problem: DesignProblem, rows: IntArray) -> Callable[[FloatArray], float]:
    """How much a drift in time would bias the twin fitted from the poses ``rows``, as a
    function of when they are measured: ``t`` ``(m,)`` (the fraction of the campaign,
    0..1, in the order of ``rows``) → the mean squared prediction error over the region
    (mm²) of a drift of the fitted parameters linear in time that moves the TCP by 1 mm
    (rms over the candidates) from the campaign's start to its end, averaged over the
    directions the candidates observe: how much of the drift the fit takes for geometry
    (its square; the error at mid-campaign, where the fit should be).

    The fit takes ``b = A·S·δ`` of a drift ``δ·(tᵢ − t̄)`` into its parameters, with
    ``S = Σ (tᵢ − t̄)·hᵢᵀhᵢ``; averaged over ``δ`` ~ N(0, I/r) (the scaled columns: 1 mm
    rms each) the region's error is ``trace(Sᵀ·A·W·A·S)/r``. An order whose time is
    orthogonal to every pose's information (a trend-free run order, as in the design of
    experiments) makes it 0."""
    h = problem.h[rows]
    info = np.einsum("nip,niq->npq", h, h)  # (m, r, r)
    a = np.linalg.inv(problem.prior + info.sum(axis=0))
    ev, vec = np.linalg.eigh(a @ problem.w @ a)
    ct = np.sqrt(np.clip(ev, 0.0, None))[:, None] * vec.T  # A·W·A = CᵀC

    def bias_mm2(t: FloatArray) -> float:
        tc = np.asarray(t, dtype=float) - float(np.mean(t))
        s = np.tensordot(tc, info, axes=1)
        return float(np.sum((ct @ s) ** 2)) / len(ct)

    return bias_mm2


def _rows_times(u: FloatArray, a: FloatArray) -> FloatArray:
    """``uᵢ·a`` ``(n, 3, m)`` for blocks ``u`` ``(n, 3, k)``, one BLAS product."""
    n, rows, k = u.shape
    out: FloatArray = (u.reshape(n * rows, k) @ a).reshape(n, rows, a.shape[1])
    return out


def _inv3(k: FloatArray) -> FloatArray:
    """Inverses ``(n, 3, 3)`` of 3×3 matrices ``k`` (adjugate over determinant, vectorised:
    a LAPACK call per 3×3 costs more than its arithmetic)."""
    a, b, c = k[:, 0, 0], k[:, 0, 1], k[:, 0, 2]
    d, e, f = k[:, 1, 0], k[:, 1, 1], k[:, 1, 2]
    g, h, i = k[:, 2, 0], k[:, 2, 1], k[:, 2, 2]
    co = np.stack(
        [e * i - f * h, c * h - b * i, b * f - c * e,
         f * g - d * i, a * i - c * g, c * d - a * f,
         d * h - e * g, b * g - a * h, a * e - b * d],
        axis=1,
    ).reshape(-1, 3, 3)  # fmt: skip
    det = a * co[:, 0, 0] + b * co[:, 1, 0] + c * co[:, 2, 0]
    out: FloatArray = co / det[:, None, None]
    return out


class _State:
    """The chosen set's ``A``, ``D`` and, for the candidates ``rows``, ``u = h·A``, ``u·W``,
    ``Q = h·A·hᵀ``, ``T = u·W·uᵀ``, ``R = g − h·D`` and ``F = u·(W·D − X)``; kept up to date
    by :meth:`update` (mutable working arrays, never a result)."""

    def __init__(
        self, problem: DesignProblem, rows: IntArray, info: FloatArray, cross: FloatArray
    ) -> None:
        p = problem
        self.problem, self.rows = p, rows
        self.h, self.g = p.h[rows], p.g[rows]
        self.a: FloatArray = np.linalg.inv(info).astype(np.float64)
        self.d = self.a @ cross
        self.u = _rows_times(self.h, self.a)
        self.uw = _rows_times(self.u, p.w)
        self.q3 = block_products(self.u, self.h)
        self.t3 = block_products(self.uw, self.u)
        self.res = self.g - _rows_times(self.h, self.d)
        self.f3 = _rows_times(self.u, p.w @ self.d - p.x)

    def deltas(self, sign: float) -> FloatArray:
        """The change of ``f`` ``(n,)`` from adding (``sign`` +1) or removing (−1) each row."""
        return _deltas(self.q3, self.t3, self.res, self.f3, sign)

    def update(
        self, local: int, sign: float, *, apply: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Add (``sign`` +1) or remove (−1) the candidate at ``local`` (module text); the
        new ``Q``, ``T``, ``R``, ``F``. Without ``apply`` the state stays as it is and the
        costly ``u``, ``u·W`` are not updated: what a trial removal needs."""
        b, u_b, uw_b = self.h[local], self.u[local].copy(), self.uw[local].copy()
        t_b, r_b, f_b = self.t3[local].copy(), self.res[local].copy(), self.f3[local].copy()
        k_inv = np.linalg.inv(sign * np.eye(3) + self.q3[local])
        c = _rows_times(self.u, b.T)  # h·A·bᵀ (n, 3, 3)
        pw = _rows_times(self.uw, u_b.T)  # u·W·u_bᵀ (n, 3, 3)
        ck = c @ k_inv
        ckt = ck.transpose(0, 2, 1)
        kr = k_inv @ r_b
        q3 = self.q3 - ck @ c.transpose(0, 2, 1)
        t3 = self.t3 - ck @ pw.transpose(0, 2, 1) - pw @ ckt + ck @ t_b @ ckt
        res = self.res - _rows_times(ck, r_b)
        f3 = self.f3 - _rows_times(ck, f_b) + _rows_times(pw, kr) - _rows_times(ck, t_b @ kr)
        if apply:
            self.u -= _rows_times(ck, u_b)
            self.uw -= _rows_times(ck, uw_b)
            self.a -= u_b.T @ k_inv @ u_b
            self.d += u_b.T @ kr
            self.q3, self.t3, self.res, self.f3 = q3, t3, res, f3
        return q3, t3, res, f3


def _deltas(
    q3: FloatArray, t3: FloatArray, res: FloatArray, f3: FloatArray, sign: float
) -> FloatArray:
    """``−tr(K⁻¹T) + 2·tr(K⁻¹·F·Rᵀ) + tr(K⁻¹·T·K⁻¹·R·Rᵀ)`` ``(n,)``, ``K = σI + Q``: the
    change of ``f`` from adding (σ = +1) or removing (−1) each row."""
    k_inv = _inv3(sign * np.eye(3) + q3)
    res_t = res.transpose(0, 2, 1)
    fr = f3 @ res_t  # (n, 3, 3)
    rr = res @ res_t
    kt = k_inv @ t3
    # tr(X·Y) = Σ X ∘ Yᵀ
    out: FloatArray = (
        -np.trace(kt, axis1=1, axis2=2)
        + 2.0 * np.sum(k_inv * fr.transpose(0, 2, 1), axis=(1, 2))
        + np.sum((kt @ k_inv) * rr, axis=(1, 2))  # rr symmetric
    )
    return out


def _info(problem: DesignProblem, chosen: list[int]) -> tuple[FloatArray, FloatArray]:
    h, g = problem.h[chosen], problem.g[chosen]
    info = problem.prior + np.einsum("nip,niq->pq", h, h)
    return info, np.einsum("nip,niq->pq", h, g)


def exchange(problem: DesignProblem, chosen: list[int], passes: int) -> int:
    """Exchange passes on ``chosen`` (in place): each chosen pose in turn swapped for the
    shortlisted candidate that lowers ``f`` most, if that beats keeping it; until a pass
    swaps nothing, gains less than :data:`MIN_PASS_GAIN`, or ``passes`` are done. Returns
    the swaps made."""
    n = problem.h.shape[0]
    swaps = 0
    value = criterion_value(problem, np.array(chosen)).total_mm2
    rows = np.zeros(0, dtype=np.intp)
    for i in range(passes):
        if i % RESHORTLIST == 0:
            full = _State(problem, np.arange(n), *_info(problem, chosen))
            gain = -full.deltas(1.0)
            gain[chosen] = -np.inf
            short = np.argsort(gain)[::-1][: min(SHORTLIST, n - len(chosen))]
            rows = np.concatenate([np.array(chosen, dtype=np.intp), short])
        state = _State(problem, rows, *_info(problem, chosen))  # exact again, each pass
        local = {int(r): j for j, r in enumerate(rows)}
        in_set = np.isin(rows, chosen)
        made = 0
        for pos in range(len(chosen)):
            out = local[chosen[pos]]
            delta = _deltas(*state.update(out, -1.0, apply=False), 1.0)  # after its removal
            keep = float(delta[out])  # putting it back
            delta[in_set] = np.inf
            best = int(np.argmin(delta))
            if not delta[best] < keep - 1e-9 * abs(keep):
                continue
            state.update(out, -1.0)
            state.update(best, 1.0)
            in_set[out], in_set[best] = False, True
            chosen[pos] = int(rows[best])
            made += 1
        swaps += made
        new = criterion_value(problem, np.array(chosen)).total_mm2
        if not made or value - new < MIN_PASS_GAIN * value:
            break
        value = new
    return swaps
