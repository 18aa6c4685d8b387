"""Nonlinear shape parameters of effect terms, fitted on the linearized model.

Two effects of the library are not linear in all their parameters:

* **A thermal lag** ``A·(1 − e^(−t/τ))``: linear in ``A`` for a fixed time constant τ
  (variable projection). :func:`profile_time_constant` profiles τ on a log grid over the
  campaign's span, refines the minimum, and gives the 95 % profile-likelihood interval
  (``SSE(τ) ≤ SSE_min + χ²₁(0.95)·σ²``). As τ → ∞ the lag becomes a straight line, so an
  interval unbounded above means the data cannot tell the lag from a linear drift: the
  linear form is then kept (method.md §6: τ is identifiable only when the campaign spans
  a few τ).
* **The physical gravity form** ``Δθ_j = ρ_j·Σ_k Ŷ_jk·w_k``: bilinear in the compliance
  ratios ρ and the compliance-weighted moments w. :func:`fit_physical_gravity` starts from
  the linear form's free deflections ``p_jk`` (a rank-one factorization ``p_jk ≈ ρ_j·w_k``)
  and minimizes the residual over (ρ, w) with the model's span projected out
  (``scipy.optimize.least_squares``), ρ of the reference joint fixed at 1; a fit that fails
  with a negative ratio (a negative compliance) is made again with the ratios held ≥ 0.

Both work on :class:`~calibration.effects.candidate_scoring.LinearizedModel`: the identification's
weighted residual and Jacobian at the current solution, so the geometry is refitted
implicitly (projected out) and the result is the same to first order as a joint fit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import OptimizeResult, least_squares
from scipy.stats import chi2

from calibration.effects.candidate_scoring import LinearizedModel

FloatArray = NDArray[np.float64]

#: Grid of the τ profile, relative to the campaign's span.
TAU_GRID_RELATIVE = (1.0 / 50.0, 20.0)
TAU_GRID_POINTS = 60
#: Confidence of the τ interval (profile likelihood).
TAU_CONFIDENCE = 0.95


@dataclass(frozen=True, eq=False)
class TimeConstantProfile:
    """The profile of a lag's time constant over a grid, and what it decided."""

    tau_s: float | None  # None: the data cannot tell the lag from a linear drift
    best_tau_s: float  # the profile's minimum, even when the linear form is kept
    interval_s: tuple[float, float]  # 95 % interval; upper inf: unbounded
    sse_linear: float
    sse_lag: float
    sigma2: float
    grid_s: FloatArray
    sse_grid: FloatArray
    reason: str

    def as_dict(self) -> dict[str, object]:
        lo, hi = self.interval_s
        return {
            "time_constant_s": self.tau_s,
            "profile_minimum_s": self.best_tau_s,
            "interval_s": [lo, hi if math.isfinite(hi) else None],
            "confidence": TAU_CONFIDENCE,
            "sse_drop_vs_linear_sigma2": (self.sse_linear - self.sse_lag) / self.sigma2,
            "decision": self.reason,
        }


def _sse_one(lin: LinearizedModel, col: FloatArray) -> float:
    p = lin.perp(col[:, None])[:, 0]
    pp = float(p @ p)
    if pp <= 1e-300:
        return lin.sse0
    return lin.sse0 - float(p @ lin.fit0) ** 2 / pp


def profile_time_constant(
    lin: LinearizedModel,
    column_at: Callable[[float | None], FloatArray],
    span_s: float,
) -> TimeConstantProfile:
    """Profile τ of a lag whose weighted column ``(3m,)`` is ``column_at(τ)`` (``None``:
    the linear drift), over a campaign spanning ``span_s`` seconds."""
    span = max(float(span_s), 1.0)
    grid = np.geomspace(span * TAU_GRID_RELATIVE[0], span * TAU_GRID_RELATIVE[1], TAU_GRID_POINTS)
    sse = np.array([_sse_one(lin, column_at(float(t))) for t in grid])
    i = int(np.argmin(sse))
    lo_t, hi_t = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    best_tau, best_sse = _golden(lambda t: _sse_one(lin, column_at(t)), lo_t, hi_t)
    if sse[i] < best_sse:
        best_tau, best_sse = float(grid[i]), float(sse[i])
    sse_lin = _sse_one(lin, column_at(None))
    dof = len(lin.residual) - lin.jacobian.shape[1] - 2
    sigma2 = best_sse / max(dof, 1)
    limit = best_sse + float(chi2.ppf(TAU_CONFIDENCE, 1)) * sigma2
    inside = sse <= limit
    lower = float(grid[np.argmax(inside)]) if inside.any() else best_tau
    upper = (
        math.inf if inside[-1] or sse_lin <= limit else float(grid[::-1][np.argmax(inside[::-1])])
    )
    lower = min(lower, best_tau)
    if math.isfinite(upper):
        upper = max(upper, best_tau)
        return TimeConstantProfile(
            best_tau, best_tau, (lower, upper), sse_lin, best_sse, sigma2, grid, sse,
            f"lag: the linear drift is {(sse_lin - best_sse) / sigma2:.1f} σ² worse",
        )  # fmt: skip
    return TimeConstantProfile(
        None, best_tau, (lower, upper), sse_lin, best_sse, sigma2, grid, sse,
        "linear: the data cannot tell the lag from a straight line "
        f"(τ interval unbounded; the campaign spans {span / 60.0:.0f} min)",
    )  # fmt: skip


def _golden(
    f: Callable[[float], float], lo: float, hi: float, iterations: int = 30
) -> tuple[float, float]:
    """Minimum of ``f`` over log τ in [lo, hi] by golden-section search."""
    a, b = math.log(lo), math.log(hi)
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(math.exp(c)), f(math.exp(d))
    for _ in range(iterations):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(math.exp(c))
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(math.exp(d))
    t = math.exp(0.5 * (a + b))
    return t, f(t)


#: Compliance ratios more than this factor apart are not bounded by the data: the fit is
#: running off to the limit form (:func:`fit_physical_gravity`). A real arm's joint
#: compliances differ by a factor of tens; 10³ is far past any, far short of a run-off
#: (10⁶–10⁸ when the fit stops).
LIMIT_RATIO_GAP = 1e3
#: A joint may part from its group's reference only when its deflection moves the TCP by
#: at most this fraction of the reference's (the linear form's shift): an unbounded ratio
#: is one the data hardly see (a wrist joint's, seen through few poses). A joint the data
#: see well whose ratio runs off says the one-ratio form is wrong for it (joints 2 and 3
#: coupled, say: docs/closed-loop.md), not that its ratio is unbounded: the fit is then
#: left unconverged and the form not offered, as before the limit form.
LIMIT_SHIFT_FRACTION = 0.25


@dataclass(frozen=True, eq=False)
class PhysicalGravityFit:
    """The physical gravity form fitted on the linearized model.

    ``ratios`` ``(J,)`` are the compliance ratios of ``joints`` (1 at ``reference``),
    ``moments`` ``(b,)`` the compliance-weighted base moments in the columns' units
    (µrad), with their standard errors; ``sse`` the weighted residual sum of squares.

    The **limit form** (``groups`` of more than one): joints whose ratios the data do not
    bound (they ran off by more than :data:`LIMIT_RATIO_GAP` against the others) form
    groups of their own. Each group shares the moments it owns (``moment_group[k]``: the
    index into ``groups`` of base moment k's owner, the group of the largest compliance
    among the joints it loads), its ratios relative to its own reference (the joint of
    ratio 1, the one whose deflection moves the TCP most); a moment loads no joint of
    another group (in the limit, ``ρ·w → 0`` there). A group of one joint is that joint's
    own free block, as a lag whose τ runs off is a linear drift. ``groups[0]`` holds
    ``reference``; empty ``groups``: one group (the physical form). A group whose ratios
    went to 0 against the others owns no moment and is left out of ``joints``.
    """

    joints: tuple[int, ...]
    reference: int
    ratios: FloatArray
    ratio_se: FloatArray
    moments: FloatArray
    moment_se: FloatArray
    sse: float
    success: bool
    groups: tuple[tuple[int, ...], ...] = ()
    moment_group: tuple[int, ...] = ()
    #: κ of the shoulder's coupled compliance when fitted beside (None: not), in units of
    #: the reference joint's compliance
    coupling_ratio: float | None = None
    #: beside κ, the counterbalance terms' torques as the coupling carries them ``(c,)``
    #: (µrad, the coupling's weights; :func:`~calibration.effects.gravity_form.physical_gravity`)
    coupled_counterbalance: FloatArray | None = None
    #: why κ was fitted beside (the report's words; empty when it was not)
    beside_why: str = ""


def fit_physical_gravity(
    lin: LinearizedModel,
    blocks: dict[int, FloatArray],
    coupling: FloatArray | None = None,
) -> PhysicalGravityFit:
    """Fit ``Σ_j ρ_j·C_j·w`` to the model's residual, ``C_j`` ``(3m, b)`` the weighted
    columns of joint j per base moment (zero where a moment does not act on it); with
    ``coupling`` ``(3m, b)`` (the shoulder pair's coupled compliance per base moment,
    :func:`~calibration.effects.effect_coupling.coupling_moment_columns`), ``+ κ·D·w``
    with one more ratio κ, fitted and left out of the result (the loop offers the
    coupling as its own term once gravity is in).

    The residual convention is the identification's (model − tracker), so the effect
    explains ``−residual``. The reference joint (ρ = 1) is the one whose linear-form
    deflection moves the TCP most. When ratios run off (the data do not bound a joint's
    ratio: its moments go to 0 while it goes to ∞), the fit is split into the limit form
    (:class:`PhysicalGravityFit`) and refitted, until no group's ratios run off.

    A fit that fails with a negative ratio (a negative compliance: joints' deflections
    cancelled against each other, ratios of ±10⁶–10¹⁰ on an emulated Barrett WAM's
    planned poses) is made again with the ratios bounded at 0; a ratio at 0 is a joint
    whose deflection the data do not show. A fit that succeeds is kept as it is, a small
    negative ratio within its error included (a counterbalanced joint's, near 0).
    """
    fit = _fit_physical_gravity(lin, blocks, coupling, bounded=False)
    if fit.success or not np.any(fit.ratios < 0.0):
        return fit
    bounded = _fit_physical_gravity(lin, blocks, coupling, bounded=True)
    return bounded if bounded.success else fit


def _fit_physical_gravity(
    lin: LinearizedModel,
    blocks: dict[int, FloatArray],
    coupling: FloatArray | None,
    *,
    bounded: bool,
) -> PhysicalGravityFit:
    """:func:`fit_physical_gravity`'s fit, the ratios ``bounded`` at 0 or free."""
    joints = tuple(sorted(blocks))
    y = -lin.fit0
    perp = {j: lin.perp(blocks[j]) for j in joints}
    coupled = None if coupling is None else lin.perp(coupling)
    kappa = np.zeros(0 if coupling is None else 1)
    p, acting = _linear_form(blocks, perp, y)
    shift = np.array([float(np.linalg.norm(perp[j] @ p[i])) for i, j in enumerate(joints)])
    ref = int(np.argmax(shift))
    rho, w = _rank_one(p, acting, joints, ref)
    # a moment with no column left once the model is projected out (one whose effect the
    # geometry takes up entirely) is not determined: it starts and stays at 0, else it would
    # be held at an arbitrary value
    raw = sum(np.linalg.norm(blocks[j], axis=0) for j in joints)
    seen = sum(np.linalg.norm(perp[j], axis=0) for j in joints)
    undetermined = seen <= 1e-6 * raw  # the relative tolerance of the loop's rank test
    w[undetermined] = 0.0
    loads = np.array([[k in acting[j] for k in range(len(w))] for j in joints])  # (J, b)
    groups = [list(range(len(joints)))]  # positions in ``joints``, reference first
    groups[0].sort(key=lambda i: (i != ref, -shift[i]))
    owner = np.zeros(len(w), dtype=np.intp)
    for attempt in range(len(joints)):  # each split adds a group: at most J − 1 of them
        form = _PhysicalForm(
            {j: perp[j] * (owner == _group_of(groups, i))[None, :] for i, j in enumerate(joints)},
            joints,
            [i for g in groups for i in g[1:]],
            np.flatnonzero(~undetermined),
            y,
            coupled,
        )
        x0 = np.concatenate([rho[form.free], kappa, w[form.keep]])
        sol = _solve(form, x0, bounded)
        rho, w = form.unpack(sol.x)
        kappa = form.coupling_of(sol.x)
        split = _split_runaway(groups, rho, shift)
        if split is None or attempt == len(joints) - 1:
            break
        groups, owner, rho, w = _limit_groups(split, groups, owner, rho, w, loads)
    return _result(lin, form, sol, joints, groups, owner, shift)


def _solve(form: _PhysicalForm, x0: FloatArray, bounded: bool) -> OptimizeResult:
    """``form``'s least squares from ``x0``; ``bounded``: the free ratios held ≥ 0 (started
    from their magnitudes), a ratio ending at the bound set to 0."""
    if not bounded:
        return least_squares(
            form.residual, x0, jac=form.jacobian, method="lm", xtol=1e-12, ftol=1e-12
        )
    n = len(form.free)
    lower = np.concatenate([np.zeros(n), np.full(len(x0) - n, -np.inf)])
    start = np.concatenate([np.maximum(np.abs(x0[:n]), _RATIO_START_FLOOR), x0[n:]])
    sol = least_squares(
        form.residual, start, jac=form.jacobian, method="trf", bounds=(lower, np.inf),
        x_scale="jac", xtol=1e-12, ftol=1e-12,
    )  # fmt: skip
    at_bound = np.flatnonzero(sol.x[:n] < _RATIO_AT_BOUND)
    sol.x[at_bound] = 0.0  # the interior method stops a hair inside its bound
    return sol


#: A bounded refit starts every ratio at least this far inside its bound at 0, and a ratio
#: it ends below the second is at the bound (ratios are relative to the reference's 1).
_RATIO_START_FLOOR = 1e-6
_RATIO_AT_BOUND = 1e-12


def _result(
    lin: LinearizedModel,
    form: _PhysicalForm,
    sol: OptimizeResult,
    joints: tuple[int, ...],
    groups: list[list[int]],
    owner: NDArray[np.intp],
    shift: FloatArray,
) -> PhysicalGravityFit:
    """The fit ``sol`` of ``form`` (``groups`` of positions in ``joints``, each moment's
    ``owner``) with its standard errors; a group that owns no moment moves nothing (its
    ratios went to 0 against the others) and is left out."""
    rho, w = form.unpack(sol.x)
    sse = float(sol.fun @ sol.fun)
    dof = max(len(form.y) - lin.jacobian.shape[1] - len(sol.x), 1)
    jac = form.jacobian(sol.x)
    cov = (sse / dof) * np.linalg.pinv(jac.T @ jac)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    ratio_se, moment_se = form.unpack(se, held=0.0)  # an undetermined moment is held at 0
    live = [g for gi, g in enumerate(groups) if gi == 0 or np.any(owner == gi)]
    renumber = {groups.index(g): n for n, g in enumerate(live)}
    kept = sorted(i for g in live for i in g)
    return PhysicalGravityFit(
        tuple(joints[i] for i in kept),
        joints[groups[0][0]],
        rho[kept],
        ratio_se[kept],
        w,
        moment_se,
        sse,
        bool(sol.success) and not _runs_off(groups, rho),
        tuple(tuple(joints[i] for i in sorted(g)) for g in live) if len(live) > 1 else (),
        tuple(renumber.get(int(o), 0) for o in owner) if len(live) > 1 else (),
        None if form.coupled is None else float(form.coupling_of(sol.x)[0]),
    )


def _group_of(groups: list[list[int]], i: int) -> int:
    return next(gi for gi, g in enumerate(groups) if i in g)


def _ratio_parts(g: list[int], rho: FloatArray) -> list[list[int]]:
    """Group ``g``'s joints split where their ratios (sorted) jump by more than
    :data:`LIMIT_RATIO_GAP`; a joint whose ratio a bounded fit left at 0 (its deflection
    not seen) stays with the group's reference ``g[0]``: 0 is its value, not a run-off."""
    zero = [i for i in g if rho[i] == 0.0 and i != g[0]]
    rest = [i for i in g if i not in zero]
    size = np.log10(np.maximum(np.abs(rho[rest]), 1e-300))
    order = np.argsort(size)
    parts: list[list[int]] = [[rest[order[0]]]]
    for a, b in pairwise(order):
        if size[b] - size[a] > np.log10(LIMIT_RATIO_GAP):
            parts.append([])
        parts[-1].append(rest[b])
    home = next(part for part in parts if g[0] in part)
    home.extend(zero)
    return parts


def _runs_off(groups: list[list[int]], rho: FloatArray) -> bool:
    return any(len(_ratio_parts(g, rho)) > 1 for g in groups)


def _split_runaway(
    groups: list[list[int]], rho: FloatArray, shift: FloatArray
) -> list[list[list[int]]] | None:
    """Each group's joints split where their ratios run off (:func:`_ratio_parts`), each
    part its reference (largest ``shift``) first; None when no group may split: none runs
    off, or a part away from its group's reference (``g[0]``) holds a joint whose shift
    is over :data:`LIMIT_SHIFT_FRACTION` of the reference's (seen, so not unbounded)."""
    out, split = [], False
    for g in groups:
        parts = _ratio_parts(g, rho)
        seen = [
            part
            for part in parts
            if g[0] not in part and max(shift[i] for i in part) > LIMIT_SHIFT_FRACTION * shift[g[0]]
        ]
        if len(parts) > 1 and not seen:
            split = True
            out.append([sorted(part, key=lambda i: -shift[i]) for part in parts])
        else:
            out.append([g])
    return out if split else None


def _limit_groups(
    split: list[list[list[int]]],
    groups: list[list[int]],
    owner: NDArray[np.intp],
    rho: FloatArray,
    w: FloatArray,
    loads: NDArray[np.bool_],
) -> tuple[list[list[int]], NDArray[np.intp], FloatArray, FloatArray]:
    """The limit form of ``groups`` split into ``split`` (per group, its parts by rising
    ratio): a moment a split group owned goes to the part of the largest ratio among the
    joints it loads; ratios become relative to each part's reference, the moments scale
    the other way, so every product ``ρ_j·w_k`` a part keeps is unchanged (the start of
    the refit). The part holding the overall reference stays first."""
    new_groups: list[list[int]] = []
    new_owner = owner.copy()
    rho, w = rho.copy(), w.copy()
    for gi, parts in enumerate(split):
        first = len(new_groups)
        for k in np.flatnonzero(owner == gi):
            loaded = [pi for pi, part in enumerate(parts) if loads[part, k].any()]
            new_owner[k] = first + (max(loaded) if loaded else len(parts) - 1)
        for pi, part in enumerate(parts):
            scale = rho[part[0]] if abs(rho[part[0]]) > 1e-300 else 1.0
            rho[part] = rho[part] / scale
            w[new_owner == first + pi] *= scale
        new_groups.extend(parts)
    head = _group_of(new_groups, groups[0][0])
    if head:
        new_groups.insert(0, new_groups.pop(head))
        remap = np.array([0 if g == head else g + (g < head) for g in range(len(new_groups))])
        new_owner = remap[new_owner]
    return new_groups, new_owner, rho, w


def _linear_form(
    blocks: dict[int, FloatArray], perp: dict[int, FloatArray], y: FloatArray
) -> tuple[FloatArray, dict[int, NDArray[np.intp]]]:
    """The linear form: free ``p_jk`` ``(J, b)`` on the moments acting on each joint j,
    least squares on the columns with the model projected out ``perp``; the moments
    acting on each joint."""
    joints = tuple(sorted(blocks))
    b = next(iter(blocks.values())).shape[1]
    acting = {j: np.flatnonzero(np.any(blocks[j] != 0.0, axis=0)) for j in joints}
    design = np.hstack([perp[j][:, acting[j]] for j in joints])
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    p = np.zeros((len(joints), b))
    pos = 0
    for i, j in enumerate(joints):
        p[i, acting[j]] = coef[pos : pos + len(acting[j])]
        pos += len(acting[j])
    return p, acting


@dataclass(frozen=True, eq=False)
class _PhysicalForm:
    """``Σ_j ρ_j·C_j·w (+ κ·D·w) − y`` over the parameters ``x``: the ratios of the
    ``free`` joints (the reference's is 1), with ``coupled`` the coupling's κ, then the
    moments ``keep`` (the others are held)."""

    perp: dict[int, FloatArray]  # joint -> (3m, b) columns, the model projected out
    joints: tuple[int, ...]
    free: list[int]  # positions in ``joints`` (the others: group references, ρ = 1)
    keep: NDArray[np.intp]  # the determined moments
    y: FloatArray  # (3m,)
    coupled: FloatArray | None = None  # (3m, b) the coupling's columns, projected

    @property
    def n_ratios(self) -> int:
        return len(self.free) + (self.coupled is not None)

    def coupling_of(self, x: FloatArray) -> FloatArray:
        """The coupling's κ in ``x``: ``(1,)``, or ``(0,)`` without ``coupled``."""
        return x[len(self.free) : self.n_ratios]

    def unpack(self, x: FloatArray, held: float = 1.0) -> tuple[FloatArray, FloatArray]:
        """Ratios ``(J,)`` and moments ``(b,)`` of ``x``: the reference joint's ratio is
        ``held`` (1; 0 when ``x`` holds standard errors), a held moment's 0."""
        r = np.full(len(self.joints), held)
        r[self.free] = x[: len(self.free)]
        ww = np.zeros(next(iter(self.perp.values())).shape[1])
        ww[self.keep] = x[self.n_ratios :]
        return r, ww

    def _joined(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``Σ_j ρ_j·C_j (+ κ·D)`` ``(3m, b)`` at ``x``, and the moments."""
        r, ww = self.unpack(x)
        total = sum(r[i] * self.perp[j] for i, j in enumerate(self.joints))
        if self.coupled is not None:
            total = total + self.coupling_of(x)[0] * self.coupled
        return total, ww

    def residual(self, x: FloatArray) -> FloatArray:
        total, ww = self._joined(x)
        res: FloatArray = total @ ww - self.y
        return res

    def jacobian(self, x: FloatArray) -> FloatArray:
        total, ww = self._joined(x)
        shapes = [self.perp[self.joints[i]] @ ww for i in self.free]
        if self.coupled is not None:
            shapes.append(self.coupled @ ww)
        d_ratio = np.column_stack(shapes) if shapes else np.zeros((len(self.y), 0))
        return np.hstack([d_ratio, total[:, self.keep]])


def _rank_one(
    p: FloatArray,
    acting: dict[int, NDArray[np.intp]],
    joints: tuple[int, ...],
    ref: int,
) -> tuple[FloatArray, FloatArray]:
    """``p_jk ≈ ρ_j·w_k`` over the acting entries (alternating least squares, ρ_ref = 1)."""
    rho = np.ones(len(joints))
    w = np.zeros(p.shape[1])
    for _ in range(50):
        for k in range(p.shape[1]):
            rows = [i for i, j in enumerate(joints) if k in acting[j]]
            if rows:
                rr = rho[rows]
                w[k] = float(rr @ p[rows, k]) / max(float(rr @ rr), 1e-300)
        for i, j in enumerate(joints):
            if i == ref:
                continue
            wk = w[acting[j]]
            rho[i] = float(wk @ p[i, acting[j]]) / max(float(wk @ wk), 1e-300)
    return rho, w
