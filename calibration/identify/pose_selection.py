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


@dataclass(frozen=True, eq=False)
class _Candidates:
    """The candidate poses' Jacobian blocks ``h`` ``(N, 3, p)`` and their information
    ``HᵢᵀHᵢ`` ``(N, p, p)``; a tiny ridge ``(p, p)`` keeps the first steps' information
    invertible."""

    h: FloatArray
    blocks: FloatArray
    ridge: FloatArray

    @classmethod
    def of(cls, h: FloatArray) -> _Candidates:
        n_cand, _, p = h.shape
        blocks = np.einsum("nip,niq->npq", h, h)
        ridge = 1e-9 * float(np.trace(blocks.sum(axis=0))) / p / n_cand
        return cls(h, blocks, ridge * np.eye(p))

    def logdet_gains(self, info: FloatArray, available: NDArray[np.bool_]) -> FloatArray:
        """log det(info + H_iᵀH_i) − log det(info) ``(N,)`` for all candidates (determinant
        lemma); −inf for those not ``available``."""
        hv = self.h @ np.linalg.inv(info)  # (N, 3, p)
        m3 = hv @ self.h.transpose(0, 2, 1) + np.eye(3)
        gains: FloatArray = np.linalg.slogdet(m3)[1]
        gains[~available] = -np.inf
        return gains


def _greedy(
    cands: _Candidates, k: int, index: str, shortlist: int
) -> tuple[list[int], NDArray[np.bool_], FloatArray]:
    """Greedy forward selection of ``k`` poses; for O2..O4 the first ceil(p/3) poses by O1
    (their indices are zero until the information matrix has full rank). The poses, the
    candidates still available ``(N,)`` and the information of the chosen ``(p, p)``."""
    p = cands.h.shape[2]
    chosen: list[int] = []
    available = np.ones(len(cands.h), dtype=bool)
    info = cands.ridge.copy()
    for step in range(k):
        score = cands.logdet_gains(info, available)
        best = int(np.argmax(score))
        if index != "O1" and 3 * step >= p:
            short = _shortlist(score, shortlist)
            exact = _index_of_info(info + cands.blocks[short], step + 1, index)
            best = int(short[np.argmax(exact)])
        chosen.append(best)
        available[best] = False
        info = info + cands.blocks[best]
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
        info_minus = info - cands.blocks[out]
        current = float(_index_of_info(info, k, index))
        gains = cands.logdet_gains(info_minus, available)
        if index == "O1":
            cand = int(np.argmax(gains))
            new = float(_index_of_info(info_minus + cands.blocks[cand], k, index))
        else:
            short = _shortlist(gains, shortlist)
            scores = _index_of_info(info_minus + cands.blocks[short], k, index)
            cand = int(short[np.argmax(scores)])
            new = float(np.max(scores))
        if new > current * (1.0 + 1e-9):
            chosen[pos] = cand
            available[cand] = False
            available[out] = True
            info = info_minus + cands.blocks[cand]
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
