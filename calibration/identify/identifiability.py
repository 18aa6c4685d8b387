"""Which kinematic parameters the data can identify: column scaling, SVD, dropped set.

A parameter whose column is negligible in absolute terms has *no effect on the measured
positions* and is dropped first: a column in mm/rad below :data:`NO_EFFECT_TOL` of the
arm's reach (mm), or one in mm/mm below :data:`NO_EFFECT_TOL` (see
:func:`column_references`). Columns of other units (the closed loop's effect terms) only
count as no effect when they are exactly zero. This test comes before the scaling, which
would otherwise blow a column of rounding noise (e.g. ∂TCP/∂θ6 ≈ 1e-13 mm/rad with the
tool on axis 6) up to RMS 1 and let it pass the rank test as a parameter.

The stacked identification Jacobian ``(3m, 5n + 9)`` is scaled column by column (each
column divided by its RMS, so parameters in mm and rad compare) and reduced to a square
factor with the same Gram matrix (``S·Vᵀ`` of its SVD, through the eigen-decomposition of
JᵀJ, so the cost does not grow with the number of poses). The columns are then taken in a
fixed *priority order*: a column is kept if the part of it not explained by the columns
already kept is larger than ``rtol`` (relative); else the parameter is dropped, as
unidentifiable (its column is zero) or redundant (a combination of kept ones, which are
named). The order only decides *which* member of a redundant group is kept (the base pose
before joint 1, the tool before the last joint's offsets, the Hayati beta before the d of a
nearly parallel joint, ...); how many parameters are dropped is decided by the data. The
condition number is that of the scaled Jacobian restricted to the kept columns (ratio of
its extreme singular values).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import IdentifiabilityError
from calibration.model.kinematics import (
    PARAMETERS_PER_JOINT,
    KinematicModel,
    identification_jacobian,
    nearly_parallel_joints,
)

FloatArray = NDArray[np.float64]

#: Default relative tolerance below which a scaled column counts as dependent. Exactly
#: redundant parameters show ~1e-8 (the Gram matrix's resolution), the weakest identifiable
#: ones of a 100-pose campaign ~1e-2.
DEFAULT_RTOL = 1e-6

#: Absolute tolerance of the no-effect test: a column whose RMS is below this fraction of
#: its reference (:func:`column_references`) does not move the TCP. Rounding noise of a
#: vanishing column is ~1e-16 of the reach; a TCP 0.01 mm off an axis is ~2e-6 of it.
NO_EFFECT_TOL = 1e-9

#: Why a parameter whose column vanishes is dropped.
NO_EFFECT = "no effect on the measured positions"


@dataclass(frozen=True)
class DroppedParameter:
    """A parameter held at its start value, and why."""

    name: str
    index: int  # position in the full parameter vector
    reason: str  # NO_EFFECT, "redundant with ...", or why the caller excluded it
    redundant_with: tuple[str, ...] = ()


@dataclass(frozen=True)
class IdentifiabilityAnalysis:
    """Result of :func:`analyze_identifiability` over a full parameter vector of size p."""

    parameter_names: tuple[str, ...]
    free: NDArray[np.bool_]  # (p,) True for identified parameters
    column_scale: FloatArray  # (p,) RMS of each Jacobian column (1 where NO_EFFECT)
    singular_values: FloatArray  # (k,) of the scaled Jacobian on the kept columns
    dropped: tuple[DroppedParameter, ...]
    rtol: float

    @property
    def rank(self) -> int:
        return int(np.count_nonzero(self.free))

    @property
    def free_indices(self) -> NDArray[np.intp]:
        return np.flatnonzero(self.free)

    @property
    def condition_number(self) -> float:
        """σ_max / σ_min of the column-scaled Jacobian restricted to the kept parameters."""
        s = self.singular_values
        return float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf")

    @property
    def dropped_names(self) -> list[str]:
        return [d.name for d in self.dropped]

    def as_dict(self) -> dict[str, object]:
        return {
            "n_parameters": len(self.parameter_names),
            "n_identified": self.rank,
            "condition_number": self.condition_number,
            "relative_tolerance": self.rtol,
            "scaled_singular_values": [float(s) for s in self.singular_values],
            "dropped": [
                {"name": d.name, "reason": d.reason, "redundant_with": list(d.redundant_with)}
                for d in self.dropped
            ],
        }


def column_rms(jac: ArrayLike) -> FloatArray:
    """RMS ``(p,)`` of each column of a stacked Jacobian ``(M, p)``, in its own units."""
    a = np.asarray(jac, dtype=float)
    rms: FloatArray = np.sqrt(np.einsum("ij,ij->j", a, a) / max(a.shape[0], 1))
    return rms


def arm_reach_mm(model: KinematicModel) -> float:
    """Σ|a| + Σ|d| + |tool| (mm): a bound on the TCP's distance from the robot's base
    frame, hence on any ∂TCP/∂angle of the arm (mm/rad)."""
    links = np.sum(np.abs(model.a_mm)) + np.sum(np.abs(model.d_mm))
    return float(links + np.linalg.norm(model.tool_mm))


def column_references(model: KinematicModel, n_extra: int = 0) -> FloatArray:
    """Column RMS ``(5n + 9 + n_extra,)`` of a parameter with a full effect on the TCP.

    The arm's reach (mm/rad) for an angle, 1 (mm/mm) for a length; 0 for the ``n_extra``
    parameters appended after the geometry (effect terms, arbitrary units), so that only
    an exactly zero column of theirs counts as no effect.
    """
    reach = arm_reach_mm(model)
    geometric = [reach if name.endswith("_rad") else 1.0 for name in model.parameter_names()]
    return np.concatenate([geometric, np.zeros(n_extra)])


def default_priority(model: KinematicModel) -> list[int]:
    """Parameter indices in the order they are offered to the rank test.

    Base pose, tool, then joints 2..n with (a, alpha, theta_offset, and d or, on a nearly
    parallel joint, beta); then the usual suspects: d of nearly parallel joints, beta of the
    others; joint 1 last (it is fully coupled with the base pose).
    """
    n = model.n_joints
    per = len(PARAMETERS_PER_JOINT)
    ia, ial, i_d, ith, ibe = (PARAMETERS_PER_JOINT.index(k) for k in PARAMETERS_PER_JOINT)
    parallel = nearly_parallel_joints(model)
    order = list(range(per * n, per * n + 9))
    suspects: list[int] = []
    for j in range(1, n):
        base = per * j
        order += [base + ia, base + ial, base + ith]
        if parallel[j]:
            order.append(base + ibe)
            suspects.append(base + i_d)
        else:
            order.append(base + i_d)
            suspects.append(base + ibe)
    order += suspects
    order += [ia, ial, ith, i_d, ibe]
    return order


def analyze_identifiability(
    jac: ArrayLike,
    parameter_names: Sequence[str],
    *,
    priority: Sequence[int] | None = None,
    rtol: float = DEFAULT_RTOL,
    fixed: Sequence[int] = (),
    references: ArrayLike | None = None,
    excluded: Mapping[int, str] | None = None,
) -> IdentifiabilityAnalysis:
    """Decide the identifiable parameters from a Jacobian ``(m, 3, p)`` or ``(M, p)``.

    ``priority`` lists parameter indices in the order they should be kept (default: index
    order); ``fixed`` are indices the caller holds fixed whatever the data says.
    ``references`` ``(p,)`` gives the column RMS of a full effect per parameter
    (:func:`column_references`; default 0: only exactly zero columns have no effect); a
    column below :data:`NO_EFFECT_TOL` of it is dropped as :data:`NO_EFFECT`.
    ``excluded`` maps indices to the reason the caller drops them for (e.g. they ran away
    in an earlier fit); the rank test then decides the others without them.
    """
    p = len(parameter_names)
    a, order, ref_rms = _checked_inputs(jac, p, priority, references)
    rms = column_rms(a)
    no_effect = (rms == 0.0) | (rms < NO_EFFECT_TOL * ref_rms)
    scale = np.where(no_effect, 1.0, rms)
    scaled = a / scale
    scaled[:, no_effect] = 0.0  # rounding noise must not enter the Gram factor
    r = _gram_factor(scaled)
    held = {int(i): "held fixed by the caller" for i in fixed}
    held.update({int(i): str(why) for i, why in (excluded or {}).items() if int(i) not in held})
    kept, dropped = _rank_test(r, parameter_names, order, no_effect, held, rtol)
    if not kept:
        raise IdentifiabilityError("the data identifies no parameter at all")
    free = np.zeros(p, dtype=bool)
    free[kept] = True
    sv = np.linalg.svd(r[:, free], compute_uv=False)
    dropped.sort(key=lambda d: d.index)
    return IdentifiabilityAnalysis(
        parameter_names=tuple(parameter_names),
        free=free,
        column_scale=scale,
        singular_values=sv / np.sqrt(a.shape[0]),
        dropped=tuple(dropped),
        rtol=rtol,
    )


def _checked_inputs(
    jac: ArrayLike, p: int, priority: Sequence[int] | None, references: ArrayLike | None
) -> tuple[FloatArray, list[int], FloatArray]:
    """The Jacobian as ``(M, p)``, the priority order ``(p,)`` and the reference column
    RMS ``(p,)``, each checked."""
    a = np.asarray(jac, dtype=float)
    if a.ndim == 3:
        a = a.reshape(-1, a.shape[-1])
    if a.ndim != 2 or a.shape[1] != p:
        raise IdentifiabilityError(f"Jacobian must have {p} columns, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise IdentifiabilityError("Jacobian contains NaN or infinite values")
    order = list(range(p)) if priority is None else [int(i) for i in priority]
    if sorted(order) != list(range(p)):
        raise IdentifiabilityError("priority must be a permutation of the parameter indices")
    ref_rms = np.zeros(p) if references is None else np.asarray(references, dtype=float)
    if ref_rms.shape != (p,):
        raise IdentifiabilityError(f"references must have shape ({p},), got {ref_rms.shape}")
    return a, order, ref_rms


def _rank_test(
    r: FloatArray,
    parameter_names: Sequence[str],
    order: list[int],
    no_effect: NDArray[np.bool_],
    held: Mapping[int, str],
    rtol: float,
) -> tuple[list[int], list[DroppedParameter]]:
    """Keep the columns of the Gram factor ``r`` ``(p, p)`` in priority ``order`` while
    each adds a direction (its residual against the kept ones above ``rtol`` of its norm).
    ``held``: indices dropped whatever the data says, with the reason. The kept indices
    and the dropped parameters (in test order)."""
    norms = np.linalg.norm(r, axis=0)
    ref = max(float(norms.max(initial=0.0)), 1e-300)
    basis = np.zeros((r.shape[0], 0))
    kept: list[int] = []
    dropped: list[DroppedParameter] = []
    for j in order:
        col = r[:, j]
        if j in held:
            dropped.append(DroppedParameter(parameter_names[j], j, held[j]))
            continue
        if no_effect[j] or norms[j] <= rtol * ref:
            dropped.append(DroppedParameter(parameter_names[j], j, NO_EFFECT))
            continue
        resid = col - basis @ (basis.T @ col)
        resid = resid - basis @ (basis.T @ resid)  # re-orthogonalize
        if np.linalg.norm(resid) <= rtol * norms[j]:
            partners = _partners(r, kept, j, parameter_names)
            why = "redundant with " + ", ".join(partners)
            dropped.append(DroppedParameter(parameter_names[j], j, why, tuple(partners)))
            continue
        basis = np.column_stack([basis, resid / np.linalg.norm(resid)])
        kept.append(j)
    return kept, dropped


def _gram_factor(scaled: FloatArray) -> FloatArray:
    """A ``(p, p)`` matrix with the same Gram matrix as ``scaled`` ``(M, p)``.

    ``S·Vᵀ`` from the eigen-decomposition of ``scaledᵀ·scaled``: column norms and the
    residuals of a column against others are the same as on ``scaled`` itself, at a cost
    independent of M after one ``(p, p)`` product. Forming the Gram matrix limits the
    resolution of a column residual to about √eps ≈ 1e-8 relative, far below
    :data:`DEFAULT_RTOL` and far below what any identifiable parameter shows (≥ 1e-3).
    """
    gram = scaled.T @ scaled
    w, v = np.linalg.eigh(gram)
    factor: FloatArray = np.sqrt(np.clip(w, 0.0, None))[:, None] * v.T
    return factor


def _partners(r: FloatArray, kept: list[int], j: int, names: Sequence[str]) -> list[str]:
    """The kept parameters that column ``j`` is (mostly) a combination of, largest first."""
    if not kept:
        return []
    coef, *_ = np.linalg.lstsq(r[:, kept], r[:, j], rcond=None)
    contrib = np.abs(coef) * np.linalg.norm(r[:, kept], axis=0)
    top = np.argsort(contrib)[::-1]
    big = [kept[i] for i in top if contrib[i] >= 0.05 * contrib[top[0]]][:4]
    return [names[i] for i in big]


def analyze_model(
    model: KinematicModel, q_rad: ArrayLike, *, rtol: float = DEFAULT_RTOL
) -> IdentifiabilityAnalysis:
    """Identifiability of ``model``'s parameters from TCP positions at joint vectors ``q``."""
    _, jac = identification_jacobian(model, np.atleast_2d(np.asarray(q_rad, dtype=float)))
    return analyze_identifiability(
        jac,
        model.parameter_names(),
        priority=default_priority(model),
        rtol=rtol,
        references=column_references(model),
    )
