"""Choosing measurement poses by an observability index of the identification Jacobian.

For m poses, let σ_1 ≥ … ≥ σ_r be the singular values of the stacked, column-scaled
identification Jacobian restricted to the identifiable parameters (r of them). Indices:

* ``O1`` (Borm & Menq): (σ_1 ⋯ σ_r)^(1/r) / √m, the geometric mean of the singular values,
  i.e. the volume of the parameter-error ellipsoid's inverse (D-optimality).
* ``O2`` (Driels & Pathre): σ_r / σ_1, the inverse condition number.
* ``O3`` (Nahvi): σ_r, the minimum singular value (the worst-determined direction).
* ``O4`` (Nahvi & Hollerbach): σ_r² / σ_1, the noise amplification index.

:func:`select_poses` picks k of N candidate poses: greedy forward selection (for O1 by the
matrix determinant lemma, for the others on the information matrix's eigenvalues) then
DETMAX-style exchange passes that swap a chosen pose for a better candidate while the index
improves.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import PoseSelectionError
from calibration.identify.identifiability import analyze_model
from calibration.model.kinematics import KinematicModel, identification_jacobian

FloatArray = NDArray[np.float64]


def _o1(s: FloatArray, m: int) -> FloatArray:
    with np.errstate(divide="ignore"):
        geo = np.exp(np.mean(np.log(s), axis=-1))
    o1: FloatArray = np.where(s[..., -1] > 0, geo, 0.0) / np.sqrt(m)
    return o1


def _ratio(num: FloatArray, den: FloatArray) -> FloatArray:
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


#: Observability indices from singular values (descending along the last axis, r of them)
#: and the pose count m; vectorized over leading axes.
OBSERVABILITY_INDICES: dict[str, Callable[[FloatArray, int], FloatArray]] = {
    "O1": _o1,
    "O2": lambda s, m: _ratio(s[..., -1], s[..., 0]),
    "O3": lambda s, m: s[..., -1],
    "O4": lambda s, m: _ratio(s[..., -1] ** 2, s[..., 0]),
}


def _check_index(index: str) -> None:
    if index not in OBSERVABILITY_INDICES:
        raise PoseSelectionError(
            f"unknown observability index {index!r} (valid: {', '.join(OBSERVABILITY_INDICES)})"
        )


def _singular_values_of_information(info: FloatArray) -> FloatArray:
    """Singular values (descending) of J from its information matrix JᵀJ ``(..., k, k)``."""
    ev = np.linalg.eigvalsh(info)
    sv: FloatArray = np.sqrt(np.clip(ev[..., ::-1], 0.0, None))
    return sv


def observability_indices(jac: ArrayLike) -> dict[str, float]:
    """All indices of a Jacobian ``(m, 3, k)`` (m poses, already scaled and reduced)."""
    a = np.asarray(jac, dtype=float)
    if a.ndim != 3:
        raise PoseSelectionError(f"Jacobian must have shape (m, 3, k), got {a.shape}")
    s = np.linalg.svd(a.reshape(-1, a.shape[-1]), compute_uv=False)
    return {name: float(f(s, a.shape[0])) for name, f in OBSERVABILITY_INDICES.items()}


@dataclass(frozen=True)
class PoseSelection:
    """The chosen candidates and the index values of the chosen set."""

    indices: NDArray[np.intp]  # (k,) rows of the candidate array, in selection order
    index: str
    value: float  # the chosen index of the selected set
    values: dict[str, float]  # every index of the selected set
    random_value: float  # the chosen index of the first k candidates (a random baseline)
    exchanges: int  # swaps made by the exchange passes


def _index_of_info(info: FloatArray, m: int, index: str) -> FloatArray:
    return OBSERVABILITY_INDICES[index](_singular_values_of_information(info), m)


def select_poses(
    jac: ArrayLike,
    k: int,
    *,
    index: str = "O1",
    exchange_passes: int = 3,
    shortlist: int = 24,
) -> PoseSelection:
    """Pick ``k`` of the N candidate poses whose Jacobian blocks are ``jac`` ``(N, 3, p)``.

    The blocks should be column-scaled and restricted to identifiable parameters (see
    :func:`select_poses_for_model`, which does this from a model and joint vectors). For
    O2..O4 each step evaluates the exact index only on the ``shortlist`` candidates with the
    largest determinant gain (the index needs an eigen-decomposition per candidate).
    """
    _check_index(index)
    h = np.asarray(jac, dtype=float)
    if h.ndim != 3 or h.shape[1] != 3:
        raise PoseSelectionError(f"Jacobian blocks must have shape (N, 3, p), got {h.shape}")
    n_cand = h.shape[0]
    if not 1 <= k <= n_cand:
        raise PoseSelectionError(f"cannot pick {k} of {n_cand} candidate poses")
    cands = _Candidates.of(h)
    chosen, available, info = _greedy(cands, k, index, shortlist)
    exchanges = 0
    for _ in range(exchange_passes):
        swaps, info = _exchange_pass(cands, chosen, available, info, index, shortlist)
        exchanges += swaps
        if not swaps:
            break
    idx = np.array(chosen, dtype=np.intp)
    values = observability_indices(h[idx])
    baseline = observability_indices(h[:k])[index]
    return PoseSelection(
        indices=idx,
        index=index,
        value=values[index],
        values=values,
        random_value=baseline,
        exchanges=exchanges,
    )


def spd3_cholesky(s: FloatArray) -> tuple[FloatArray, ...]:
    """The Cholesky factor of symmetric positive definite 3×3 matrices ``s`` ``(N, 3, 3)``
    in closed form, vectorised over N (a gufunc call per 3×3 costs more than its flops):
    ``(l00, l10, l11, l20, l21, l22)``, each ``(N,)``."""
    tiny = 1e-300  # a pivot rounded to ≤ 0 (a singular matrix) stays finite
    l00 = np.sqrt(np.maximum(s[:, 0, 0], tiny))
    l10 = s[:, 1, 0] / l00
    l20 = s[:, 2, 0] / l00
    l11 = np.sqrt(np.maximum(s[:, 1, 1] - l10 * l10, tiny))
    l21 = (s[:, 2, 1] - l20 * l10) / l11
    l22 = np.sqrt(np.maximum(s[:, 2, 2] - l20 * l20 - l21 * l21, tiny))
    return l00, l10, l11, l20, l21, l22


def spd3_logdet(s: FloatArray) -> FloatArray:
    """``log det`` ``(N,)`` of SPD 3×3 matrices ``s`` ``(N, 3, 3)`` (closed-form Cholesky:
    stable where the cofactor formula cancels)."""
    l00, _, l11, _, _, l22 = spd3_cholesky(s)
    out: FloatArray = 2.0 * (np.log(l00) + np.log(l11) + np.log(l22))
    return out


def spd3_solve(s: FloatArray, t: FloatArray) -> FloatArray:
    """``s⁻¹ t`` ``(N, 3, k)`` for SPD 3×3 ``s`` ``(N, 3, 3)`` and ``t`` ``(N, 3, k)``."""
    l00, l10, l11, l20, l21, l22 = spd3_cholesky(s)
    inv = 1.0 / np.stack([l00, l11, l22], axis=1)[:, :, None]  # (N, 3, 1)
    y0 = t[:, 0] * inv[:, 0]
    y1 = (t[:, 1] - l10[:, None] * y0) * inv[:, 1]
    y2 = (t[:, 2] - l20[:, None] * y0 - l21[:, None] * y1) * inv[:, 2]
    x2 = y2 * inv[:, 2]
    x1 = (y1 - l21[:, None] * x2) * inv[:, 1]
    x0 = (y0 - l10[:, None] * x1 - l20[:, None] * x2) * inv[:, 0]
    out: FloatArray = np.stack([x0, x1, x2], axis=1)
    return out


def block_products(u: FloatArray, v: FloatArray) -> FloatArray:
    """``uᵢ vᵢᵀ`` ``(N, 3, 3)`` for blocks ``u``, ``v`` ``(N, 3, p)``."""
    out: FloatArray = np.einsum("nip,njp->nij", u, v, optimize=False)
    return out


def times_matrix(h: FloatArray, a: FloatArray) -> FloatArray:
    """``hᵢ a`` ``(N, 3, q)`` for blocks ``h`` ``(N, 3, p)`` and one ``a`` ``(p, q)``: one
    BLAS product over every row at once (a stacked matmul calls BLAS once per block)."""
    n, rows, p = h.shape
    out: FloatArray = (h.reshape(n * rows, p) @ a).reshape(n, rows, a.shape[1])
    return out


@dataclass(frozen=True, eq=False)
class _Candidates:
    """The candidate poses' Jacobian blocks ``h`` ``(N, 3, p)``; a tiny ridge ``(p, p)``
    (1e-9 of a mean pose's information) keeps the first steps' information invertible.
    A block's information ``HᵢᵀHᵢ`` is formed only for the few poses that need it
    (:meth:`block`): all N at once would be ``N·p²`` numbers (330 MB for 5000
    candidates and 91 parameters)."""

    h: FloatArray
    ridge: FloatArray
    rows_t: FloatArray  # (p, 3N): every row as a column, the layout BLAS reads fastest

    @classmethod
    def of(cls, h: FloatArray) -> _Candidates:
        n_cand, _, p = h.shape
        ridge = 1e-9 * float(np.sum(h * h)) / p / n_cand
        return cls(h, ridge * np.eye(p), np.ascontiguousarray(h.reshape(-1, p).T))

    def times(self, a: FloatArray) -> FloatArray:
        """``Hᵢ a`` ``(N, 3, q)`` for one ``a`` ``(p, q)``."""
        n = self.h.shape[0]
        out: FloatArray = (a.T @ self.rows_t).reshape(a.shape[1], n, 3).transpose(1, 2, 0)
        return out

    def block(self, rows: int | NDArray[np.intp]) -> FloatArray:
        """``HᵢᵀHᵢ`` ``(p, p)`` of one pose, or ``(k, p, p)`` of several."""
        b = self.h[rows]
        out: FloatArray = np.swapaxes(b, -1, -2) @ b
        return out

    def logdet_gains(self, info: FloatArray, available: NDArray[np.bool_]) -> FloatArray:
        """log det(info + H_iᵀH_i) − log det(info) ``(N,)`` for all candidates (determinant
        lemma: ``log det(I + Hᵢ info⁻¹ Hᵢᵀ)``); −inf for those not ``available``."""
        inv: FloatArray = np.linalg.inv(info).astype(np.float64)
        hv = self.times(inv)  # (N, 3, p)
        m3 = block_products(hv, self.h) + np.eye(3)
        m3 = 0.5 * (m3 + m3.transpose(0, 2, 1))
        gains = spd3_logdet(m3)
        gains[~available] = -np.inf
        return gains


#: Once the chosen poses' information has full rank, the greedy selection updates every
#: candidate's ``Hᵢ info⁻¹ Hᵢᵀ`` by rank-3 steps (``N·9·p`` each, not ``N·3·p²``) and
#: recomputes it exactly this often (rounding). Before, the ridge alone holds the
#: unseen directions: ``info⁻¹`` is ~1e9 there and a rank-3 step would cancel every
#: digit, so those steps recompute it exactly.
GREEDY_REFRESH = 16


def _greedy(
    cands: _Candidates, k: int, index: str, shortlist: int
) -> tuple[list[int], NDArray[np.bool_], FloatArray]:
    """Greedy forward selection of ``k`` poses; for O2..O4 the first ceil(p/3) poses by O1
    (their indices are zero until the information matrix has full rank). The poses, the
    candidates still available ``(N,)`` and the information of the chosen ``(p, p)``.

    Each step adds the pose of largest ``log det(I + Sᵢ)``, ``Sᵢ = Hᵢ info⁻¹ Hᵢᵀ``
    ``(N, 3, 3)``; adding block ``b`` changes ``info⁻¹`` by ``−V K⁻¹ Vᵀ`` (``V = info⁻¹bᵀ``,
    ``K = I + b info⁻¹ bᵀ``), so ``Sᵢ`` by ``−Cᵢ K⁻¹ Cᵢᵀ`` with ``Cᵢ = Hᵢ V``."""
    h = cands.h
    p = h.shape[2]
    chosen: list[int] = []
    available = np.ones(len(h), dtype=bool)
    info = cands.ridge.copy()
    inv: FloatArray = np.linalg.inv(info).astype(np.float64)
    s = np.zeros((len(h), 3, 3))
    for step in range(k):
        if 3 * step <= p + 3 or step % GREEDY_REFRESH == 0:
            inv = np.linalg.inv(info).astype(np.float64)
            s = block_products(cands.times(inv), h)
        m3 = s + np.eye(3)
        score = spd3_logdet(0.5 * (m3 + m3.transpose(0, 2, 1)))
        score[~available] = -np.inf
        best = int(np.argmax(score))
        if index != "O1" and 3 * step >= p:
            short = _shortlist(score, shortlist)
            exact = _index_of_info(info + cands.block(short), step + 1, index)
            best = int(short[np.argmax(exact)])
        chosen.append(best)
        available[best] = False
        info = info + cands.block(best)
        v = inv @ h[best].T  # (p, 3)
        k_inv = np.linalg.inv(np.eye(3) + s[best])
        c = cands.times(v)  # (N, 3, 3)
        s = s - c @ k_inv @ c.transpose(0, 2, 1)
        inv = inv - v @ k_inv @ v.T
    return chosen, available, info


def _exchange_pass(
    cands: _Candidates,
    chosen: list[int],
    available: NDArray[np.bool_],
    info: FloatArray,
    index: str,
    shortlist: int,
) -> tuple[int, FloatArray]:
    """One exchange pass: each chosen pose in turn is swapped for the candidate that raises
    the index most, if any (``chosen`` and ``available`` in place). The swaps made and the
    new information ``(p, p)``."""
    k = len(chosen)
    swaps = 0
    for pos in range(k):
        out = chosen[pos]
        info_minus = info - cands.block(out)
        current = float(_index_of_info(info, k, index))
        gains = cands.logdet_gains(info_minus, available)
        if index == "O1":
            cand = int(np.argmax(gains))
            new = float(_index_of_info(info_minus + cands.block(cand), k, index))
        else:
            short = _shortlist(gains, shortlist)
            scores = _index_of_info(info_minus + cands.block(short), k, index)
            cand = int(short[np.argmax(scores)])
            new = float(np.max(scores))
        if new > current * (1.0 + 1e-9):
            chosen[pos] = cand
            available[cand] = False
            available[out] = True
            info = info_minus + cands.block(cand)
            swaps += 1
    return swaps, info


def _shortlist(score: FloatArray, size: int) -> NDArray[np.intp]:
    finite = np.flatnonzero(np.isfinite(score))
    if len(finite) <= size:
        return finite
    return finite[np.argpartition(score[finite], -size)[-size:]]


def scaled_candidate_jacobian(model: KinematicModel, q_rad: ArrayLike) -> FloatArray:
    """Column-scaled Jacobian blocks ``(N, 3, r)`` on the identifiable parameters."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    analysis = analyze_model(model, q)
    _, jac = identification_jacobian(model, q)
    return jac[:, :, analysis.free] / analysis.column_scale[analysis.free]


def select_poses_for_model(
    model: KinematicModel,
    q_candidates_rad: ArrayLike,
    k: int,
    *,
    index: str = "O1",
    exchange_passes: int = 3,
) -> PoseSelection:
    """Pick ``k`` of the candidate joint vectors ``(N, n)`` rad that maximize ``index``
    for ``model`` (the Jacobian is taken at the model's nominal geometry)."""
    jac = scaled_candidate_jacobian(model, q_candidates_rad)
    return select_poses(jac, k, index=index, exchange_passes=exchange_passes)
