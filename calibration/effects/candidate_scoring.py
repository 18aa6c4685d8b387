"""How the closed loop scores candidate effects and tells look-alikes apart.

Everything here works on the current model linearized at its solution: ``residual``
``(3m,)`` and ``jacobian`` ``(3m, p)`` weighted like the fit, and each candidate's weighted
regressor ``(3m, k)``. Columns are scaled to unit RMS so that units do not matter.

* **Score** (:func:`score_candidate`): the drop of the K-fold cross-validated error in
  units of the noise variance, minus a penalty per parameter, and the partial F-test of
  the candidate's parameters, Bonferroni-corrected over the round's candidates.
* **Scans** (:func:`best_of_scan`): of a harmonic's orders, the one that lowers the
  residual most is scored, its p-value Šidák-corrected for the orders scanned
  (``1 − (1 − p)^K``) before the round's Bonferroni correction: the scan pays for every
  order it looked at.
* **Overlap** (:func:`principal_cosines`): the cosines of the principal angles between two
  candidates' column spaces after the model's is projected out (1: the data cannot tell
  them apart along that direction), and how much of a candidate the model already spans.
* **Physical priority** (:data:`PRIORITY`): when the best-scoring candidate lies within the
  span of a significant candidate of a more physical kind (every principal cosine at
  least :data:`INDISTINGUISHABLE_COSINE`), that one is chosen: a gravity term before a
  harmonic on a joint gravity loads (after geometry is removed, a joint-2
  once-per-revolution harmonic spans exactly the columns of link 2's own gravity term,
  method.md §6), a physical effect before the generic search.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import f as f_distribution

from calibration.effects.effect_base import EffectSpec

FloatArray = NDArray[np.float64]

#: Physical priority of effect kinds (lower first) when the data cannot tell them apart.
#: A link's bending comes after the joint's own gravity deflection (it is offered only with
#: that term in the model, from its moments), and so does the joints' shared compliance
#: (``joint_coupling``, offered the same way: the gravity term's own compliance matrix
#: completed). A term driven by a measured temperature
#: comes before one driven by the clock: the temperature is the cause a drift in time
#: stands in for.
PRIORITY: dict[str, int] = {
    "gravity_deflection": 0,
    "gravity_compliance": 0,
    "link_bending": 1,
    "joint_coupling": 1,
    "thermal_expansion": 2,
    "length_temperature": 2,
    "instrument_scale_temperature": 2,
    "length_drift": 3,
    "lost_motion": 3,
    "instrument_scale": 3,
    "instrument_scale_drift": 3,
    "joint_harmonic": 4,
}
GENERIC_PRIORITY = 5
#: Two candidates whose principal cosines are all at least this cannot be told apart.
INDISTINGUISHABLE_COSINE = 0.95


def priority(spec: EffectSpec) -> int:
    return GENERIC_PRIORITY if spec.generic else PRIORITY.get(spec.kind, GENERIC_PRIORITY)


@dataclass(frozen=True)
class CandidateScore:
    """How one candidate did in one round."""

    spec: EffectSpec
    n_parameters: int  # identifiable parameters (columns not redundant with the model)
    cv_gain: float  # held-out SSE reduction / σ̂²
    score: float  # cv_gain − penalty · n_parameters
    f_statistic: float
    p_value: float
    p_adjusted: float  # Šidák over a scan's orders, then Bonferroni over the round (≤ 1)
    significant: bool
    note: str = ""
    in_model: float = 0.0  # fraction of the candidate's (scaled) columns the model spans

    @property
    def label(self) -> str:
        return self.spec.label

    @property
    def generic(self) -> bool:
        return self.spec.generic

    def as_dict(self) -> dict[str, object]:
        return {
            "effect": self.label,
            "kind": self.spec.kind,
            "generic": self.generic,
            "n_parameters": self.n_parameters,
            "cv_gain_sigma2": _finite(self.cv_gain),
            "score": _finite(self.score),
            "f_statistic": _finite(self.f_statistic),
            "p_value": self.p_value,
            "p_adjusted": self.p_adjusted,
            "significant": self.significant,
            "in_model_fraction": round(float(self.in_model), 4),
            "note": self.note,
        }


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def scaled(a: FloatArray) -> FloatArray:
    """Columns divided by their RMS (zero columns left as they are)."""
    s = np.sqrt(np.mean(a * a, axis=0))
    s[s == 0.0] = 1.0
    out: FloatArray = a / s
    return out


def keep_columns(basis_q: FloatArray, cols: FloatArray, rtol: float) -> NDArray[np.bool_]:
    """Which columns of ``cols`` ``(N, k)`` add a direction to the orthonormal ``basis_q``
    and to the columns kept before them (relative residual > rtol)."""
    q = basis_q
    keep = np.zeros(cols.shape[1], dtype=bool)
    for i in range(cols.shape[1]):
        c = cols[:, i]
        norm = float(np.linalg.norm(c))
        if norm == 0.0:
            continue
        r = c - q @ (q.T @ c)
        r = r - q @ (q.T @ r)
        rn = float(np.linalg.norm(r))
        if rn > rtol * norm:
            keep[i] = True
            q = np.column_stack([q, r / rn])
    return keep


@dataclass(frozen=True, eq=False)
class LinearizedModel:
    """The current model at its solution: orthonormal basis of its scaled columns, the
    residual with the model projected out, noise variance and CV folds."""

    residual: FloatArray  # (3m,)
    jacobian: FloatArray  # (3m, p) scaled
    basis: FloatArray  # (3m, p) orthonormal
    fit0: FloatArray  # (3m,) residual ⊥ model
    sigma2: float
    folds: list[NDArray[np.intp]]
    cv0: float
    gram: FloatArray  # (p, p) JᵀJ
    rhs: FloatArray  # (p,) Jᵀr
    fold_gram: tuple[FloatArray, ...]  # per fold, its rows' JᵀJ
    fold_rhs: tuple[FloatArray, ...]  # per fold, its rows' Jᵀr
    #: leave one pose out (exact, by the hat matrix) instead of the folds
    leave_one_out: bool = False
    #: with ``leave_one_out``: each left-out pose scored by its predictive deviance
    #: (:func:`pose_deviance`) instead of its squared error (:func:`pose_press`)
    deviance: bool = False

    @classmethod
    def build(
        cls,
        residual: FloatArray,
        jacobian: FloatArray,
        n_poses: int,
        n_folds: int,
        seed: int,
        *,
        leave_one_out: bool = False,
        deviance: bool = False,
    ) -> LinearizedModel:
        """The model at its solution; ``leave_one_out``: cross-validated by leaving one
        pose out at a time (:func:`pose_press`; ``deviance``:
        :func:`pose_deviance`), else by ``n_folds`` folds of poses drawn with
        ``seed``."""
        j = scaled(jacobian)
        basis, _ = np.linalg.qr(j)
        fit0 = residual - basis @ (basis.T @ residual)
        sigma2 = float(fit0 @ fit0) / max(len(residual) - j.shape[1], 1)
        pose_fold = np.random.default_rng(seed).permutation(n_poses) % n_folds
        row_fold = np.repeat(pose_fold, 3)
        folds = [np.flatnonzero(row_fold == f) for f in range(n_folds)]
        gram, rhs = j.T @ j, j.T @ residual
        fold_gram = tuple(j[f].T @ j[f] for f in folds)
        fold_rhs = tuple(j[f].T @ residual[f] for f in folds)
        if leave_one_out:
            cv0 = _left_out_score(basis, fit0, sigma2, deviance)
        else:
            cv0 = 0.0
            for f, fg, fr in zip(folds, fold_gram, fold_rhs, strict=True):
                coef, *_ = np.linalg.lstsq(gram - fg, rhs - fr, rcond=None)
                e = residual[f] - j[f] @ coef
                cv0 += float(e @ e)
        return cls(
            residual, j, basis, fit0, sigma2, folds, cv0, gram, rhs, fold_gram, fold_rhs,
            leave_one_out, deviance,
        )  # fmt: skip

    def cv_sse_with(self, cols: FloatArray) -> float:
        """Held-out error of the model plus ``cols`` ``(3m, k)``: each pose predicted by the
        model refitted without it (``leave_one_out``: its predictive deviance with
        ``deviance``, :func:`pose_deviance`, else its squared miss, :func:`pose_press`),
        else the squared misses of each fold refitted without its test rows. The training
        normal equations are the full ones minus the test rows', so a fold costs
        ``O(N_test·q²)`` whatever the number of poses; the model's own blocks are computed
        once, only the candidate's cross blocks are new; a ``(q, q)`` least-squares solve
        keeps nearly dependent columns harmless."""
        if self.leave_one_out:
            qc = _orthonormal(self.perp(cols))
            basis, fit = np.hstack([self.basis, qc]), self.fit0 - qc @ (qc.T @ self.fit0)
            return _left_out_score(basis, fit, self.sigma2, self.deviance)
        j, r = self.jacobian, self.residual
        jc, cc, cr = j.T @ cols, cols.T @ cols, cols.T @ r
        gram = np.block([[self.gram, jc], [jc.T, cc]])
        rhs = np.concatenate([self.rhs, cr])
        total = 0.0
        for f, fg, fr in zip(self.folds, self.fold_gram, self.fold_rhs, strict=True):
            jf, cf, rf = j[f], cols[f], r[f]
            jcf = jf.T @ cf
            g = gram - np.block([[fg, jcf], [jcf.T, cf.T @ cf]])
            coef, *_ = np.linalg.lstsq(g, rhs - np.concatenate([fr, cf.T @ rf]), rcond=None)
            e = rf - jf @ coef[: j.shape[1]] - cf @ coef[j.shape[1] :]
            total += float(e @ e)
        return total

    @property
    def sse0(self) -> float:
        return float(self.fit0 @ self.fit0)

    def perp(self, cols: FloatArray) -> FloatArray:
        """``cols`` with the model's span projected out."""
        return cols - self.basis @ (self.basis.T @ cols)

    def sse_with_perp(self, perp: FloatArray) -> float:
        """Residual SSE with extra columns added to the model, given them with the model's
        span projected out (:meth:`perp`) ``(3m, k)``."""
        coef, *_ = np.linalg.lstsq(perp, self.fit0, rcond=None)
        e = self.fit0 - perp @ coef
        return float(e @ e)


#: A pose's own share of a direction (an eigenvalue of its 3×3 block of the hat matrix)
#: above ``1 − LEVERAGE_FLOOR``: the direction is determined by that pose alone.
LEVERAGE_FLOOR = 1e-9


def _pose_directions(basis: FloatArray, fit: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per pose, ``1 − λ`` of its hat-matrix block's eigenvalues and its residual along
    their eigenvectors (each ``(m, 3)``; ``1 − λ`` is NaN where the pose alone determines
    the direction, ``1 − λ`` below :data:`LEVERAGE_FLOOR`)."""
    q = basis.reshape(-1, 3, basis.shape[1])
    e = fit.reshape(-1, 3)
    lam, vec = np.linalg.eigh(np.einsum("iak,ibk->iab", q, q))  # H_ii = V·diag(λ)·Vᵀ
    free = 1.0 - lam
    along = np.einsum("iab,ia->ib", vec, e)  # e_i in the eigenvectors
    return np.where(free > LEVERAGE_FLOOR, free, np.nan), along


def pose_press(basis: FloatArray, fit: FloatArray) -> float:
    """The exact leave-one-pose-out prediction error (PRESS, Allen 1974) of a linear model:
    ``Σ_i ‖(I − H_ii)⁻¹·e_i‖²`` over the poses i (rows ``3i .. 3i + 2``), ``H_ii`` the
    pose's ``(3, 3)`` block of the hat matrix ``Q·Qᵀ`` (``basis`` ``Q`` ``(3m, q)``
    orthonormal, the model's span) and ``e_i`` its residual (``fit`` ``(3m,)``, the
    model's span projected out). The same as refitting without each pose in turn, at the
    cost of one fit: ``O(m·q)``. A direction a pose alone determines (``1 − λ`` below
    :data:`LEVERAGE_FLOOR`) cannot be predicted without it and carries no residual: it
    counts 0."""
    free, along = _pose_directions(basis, fit)
    return float(np.nansum((along / free) ** 2))


def pose_deviance(basis: FloatArray, fit: FloatArray, sigma2: float) -> float:
    """The leave-one-pose-out predictive deviance of a linear model, in the units of
    :func:`pose_press` (mm² as weighted): ``Σ_i [e_iᵀ(I − H_ii)⁻¹e_i − σ²·ln det(I − H_ii)]``,
    σ² times −2 ln of the density the model refitted without pose i gives the pose's point
    (its prediction error ``(I − H_ii)⁻¹e_i``, its covariance ``σ²(I − H_ii)⁻¹``), up to a
    constant. To first order in the leverage it equals the PRESS (both ``SSE + 2kσ²``);
    where a pose nearly alone determines a direction (λ → 1) the PRESS multiplies that
    direction's residual by ``1/(1 − λ)²``, so one pose at the design's edge can decide
    between two candidates by its noise, while the deviance weighs the miss against the
    prediction's own uncertainty and charges that uncertainty as ``−ln(1 − λ)``. (A
    planned KR500 campaign with a pose at λ = 0.992 put a drift on the wrong link by the
    PRESS: docs/closed-loop.md, "Predictive deviance, not the PRESS".) Directions a pose alone
    determines count 0, as in :func:`pose_press`."""
    free, along = _pose_directions(basis, fit)
    return float(np.nansum(along * along / free - sigma2 * np.log(free)))


def _left_out_score(basis: FloatArray, fit: FloatArray, sigma2: float, deviance: bool) -> float:
    """The leave-one-pose-out score the model is built with: :func:`pose_deviance` or
    :func:`pose_press`."""
    return pose_deviance(basis, fit, sigma2) if deviance else pose_press(basis, fit)


def _orthonormal(a: FloatArray) -> FloatArray:
    """An orthonormal basis of the columns of ``a`` ``(N, k)`` (rank-deficient ones
    dropped, as :func:`residual_basis` does)."""
    if a.size == 0:
        return a
    u, sv, _ = np.linalg.svd(a, full_matrices=False)
    out: FloatArray = u[:, sv > 1e-8 * max(float(sv.max(initial=0.0)), 1e-300)]
    return out


def score_candidate(
    lin: LinearizedModel,
    spec: EffectSpec,
    cols: FloatArray,
    *,
    n_candidates: int,
    alpha: float,
    penalty: float,
    rtol: float,
    extra_parameters: int = 0,
    scanned: int = 1,
) -> CandidateScore:
    """Score one candidate's weighted columns ``(3m, k)`` against the linearized model.

    ``extra_parameters`` counts shape parameters profiled for this candidate (a lag's τ):
    they are charged in the F-test's degrees of freedom and the penalty like linear ones.
    ``scanned``: the candidate is the best of that many scanned alternatives (a harmonic's
    orders, :func:`best_of_scan`); its p-value is Šidák-corrected for them.
    """
    cs = scaled(cols)
    energy = float(np.sum(cs * cs))
    perp_all = lin.perp(cs)
    in_model = 1.0 - float(np.sum(perp_all * perp_all)) / energy if energy > 0 else 1.0
    keep = keep_columns(lin.basis, cs, rtol)
    k = int(keep.sum())
    if k == 0:
        return CandidateScore(
            spec, 0, 0.0, 0.0, 0.0, 1.0, 1.0, False,
            "a combination of the parameters already in the model", in_model,
        )  # fmt: skip
    ck = cs[:, keep]
    sse1 = lin.sse_with_perp(perp_all[:, keep])
    k_eff = k + extra_parameters
    dof = len(lin.residual) - lin.jacobian.shape[1] - k_eff
    f_stat = ((lin.sse0 - sse1) / k_eff) / (sse1 / dof) if dof > 0 and sse1 > 0 else math.inf
    p_value = float(f_distribution.sf(f_stat, k_eff, dof)) if dof > 0 else 1.0
    p_scan = -math.expm1(scanned * math.log1p(-p_value)) if p_value < 1.0 else 1.0
    p_adj = min(1.0, p_scan * max(n_candidates, 1))
    cv1 = lin.cv_sse_with(ck)
    gain = (lin.cv0 - cv1) / lin.sigma2
    score = gain - penalty * k_eff
    notes = [] if k == cols.shape[1] else [f"{cols.shape[1] - k} parameter(s) redundant"]
    if scanned > 1:
        notes.append(f"the best of {scanned} orders scanned")
    note = "; ".join(notes)
    significant = bool(p_adj < alpha and score > 0.0)
    return CandidateScore(spec, k, gain, score, f_stat, p_value, p_adj, significant, note, in_model)


def best_of_scan(lin: LinearizedModel, scan: Sequence[FloatArray]) -> int:
    """Index of the scanned alternative (each its weighted columns ``(3m, k)``, e.g. one
    harmonic order) that lowers the residual sum of squares most, the model refitted
    beside it. Cheap (a projection and a small least-squares solve each): the full score is
    computed for the winner alone."""
    gains = []
    for cols in scan:  # the SSE drop c·b of the normal equations, small (k, k) solves
        perp = lin.perp(scaled(cols))
        b = perp.T @ lin.fit0
        coef, *_ = np.linalg.lstsq(perp.T @ perp, b, rcond=None)
        gains.append(float(coef @ b))
    return int(np.argmax(gains))


def principal_cosines(lin: LinearizedModel, a: FloatArray, b: FloatArray) -> FloatArray:
    """Cosines of the principal angles (largest first) between the column spaces of ``a``
    and ``b`` (each ``(3m, k)``) after the model's span is projected out of both."""
    return cosines_between(residual_basis(lin, a), residual_basis(lin, b))


def residual_basis(lin: LinearizedModel, cols: FloatArray) -> FloatArray:
    """Orthonormal basis ``(3m, r)`` of a candidate's columns with the model projected out."""
    a = lin.perp(scaled(cols))
    if a.size == 0:
        return a
    q, r = np.linalg.qr(a)
    d = np.abs(np.diag(r))
    keep = d > 1e-8 * max(float(d.max(initial=0.0)), 1e-300)
    if keep.all():
        return q
    u, sv, _ = np.linalg.svd(a, full_matrices=False)  # rank-deficient: the robust way
    return u[:, sv > 1e-8 * max(float(sv.max(initial=0.0)), 1e-300)]


def cosines_between(qa: FloatArray, qb: FloatArray) -> FloatArray:
    """Principal cosines (largest first) of two orthonormal bases."""
    if qa.shape[1] == 0 or qb.shape[1] == 0:
        return np.zeros(0)
    return np.clip(np.linalg.svd(qa.T @ qb, compute_uv=False), 0.0, 1.0)


def contained_in(cosines: FloatArray, k_smaller: int) -> bool:
    """Whether a candidate of ``k_smaller`` independent columns lies within another's span:
    its every principal cosine is at least :data:`INDISTINGUISHABLE_COSINE`."""
    return (
        k_smaller > 0
        and len(cosines) >= k_smaller
        and bool(np.all(cosines[:k_smaller] >= INDISTINGUISHABLE_COSINE))
    )


@dataclass(frozen=True)
class Competitor:
    """A candidate close to an added effect: how close, and what separated them."""

    label: str
    kind: str
    cosines: tuple[float, ...]  # principal cosines with the added effect, largest first
    score: float
    significant: bool
    separated_by: str

    def as_dict(self) -> dict[str, object]:
        return {
            "effect": self.label,
            "kind": self.kind,
            "principal_cosines": [round(c, 4) for c in self.cosines],
            "score": _finite(self.score),
            "significant": self.significant,
            "separated_by": self.separated_by,
        }


def choose(
    lin: LinearizedModel,
    scores: Sequence[CandidateScore],
    columns: dict[EffectSpec, FloatArray],
) -> tuple[CandidateScore, str]:
    """The candidate to add from a round's scores (significant ones only), and why.

    The best penalized CV score wins, unless it lies within the span of a significant
    candidate of higher physical priority (:func:`contained_in`): then the best-scoring of
    those is chosen, and the reason says so.
    """
    ranked = sorted((s for s in scores if s.significant), key=lambda s: -s.score)
    best = ranked[0]
    prior = [s for s in ranked if priority(s.spec) < priority(best.spec)]
    if prior:
        best_basis = residual_basis(lin, columns[best.spec])
        for other in prior:  # by score
            cos = cosines_between(best_basis, residual_basis(lin, columns[other.spec]))
            if contained_in(cos, best.n_parameters):
                shown = ", ".join(f"{c:.3f}" for c in cos[:3])
                reason = (
                    f"physical priority: {best.label} (score {best.score:.1f}) lies within "
                    f"{other.label} (principal cosines {shown}); "
                    f"a {other.spec.kind.replace('_', ' ')} comes before a "
                    f"{best.spec.kind.replace('_', ' ')} when the data cannot tell them apart"
                )
                return other, reason
    return best, "best penalized cross-validated score of the significant candidates"


def competitors(
    lin: LinearizedModel,
    chosen: CandidateScore,
    scores: Sequence[CandidateScore],
    columns: dict[EffectSpec, FloatArray],
    *,
    top: int = 3,
) -> tuple[Competitor, ...]:
    """The ``top`` candidates closest to ``chosen`` (largest principal cosine) and the
    evidence that separated each from it."""
    rows = []
    chosen_basis = residual_basis(lin, columns[chosen.spec])
    for s in scores:
        if s.spec == chosen.spec or s.n_parameters == 0:
            continue
        cos = cosines_between(chosen_basis, residual_basis(lin, columns[s.spec]))
        if cos.size:
            rows.append((float(cos[0]), s, cos))
    rows.sort(key=lambda r: -r[0])
    out = []
    for _, s, cos in rows[:top]:
        by_score = f"score {chosen.score:.1f} against {s.score:.1f} σ²"
        shown = ", ".join(f"{c:.2f}" for c in cos[:3])
        if contained_in(cos, s.n_parameters) or contained_in(cos, chosen.n_parameters):
            by = "physical priority" if priority(chosen.spec) < priority(s.spec) else by_score
            why = f"cannot be told apart by the data (principal cosines {shown}); {by}"
        elif not s.significant:
            why = f"not significant (corrected p {s.p_adjusted:.2g}, score {s.score:.1f} σ²)"
        elif s.score > chosen.score:
            why = (
                f"scored higher ({s.score:.1f} against {chosen.score:.1f} σ²), but through "
                f"directions the chosen effect spans (principal cosines {shown}); "
                "physical priority"
            )
        else:
            why = by_score
        out.append(
            Competitor(s.label, s.spec.kind, tuple(float(c) for c in cos[:3]), s.score,
                       s.significant, why)
        )  # fmt: skip
    return tuple(out)
