"""Kinematic parameter identification from tracker TCP points: Levenberg-Marquardt.

The method of the primary source (docs/identification.md): linearize the TCP position error
``ΔP = J·ΔX`` with the analytic identification Jacobian, stack all poses and iterate

    ΔX_k = −(JᵀJ + μ_k I)⁻¹ Jᵀ ΔP(X_k),   X_{k+1} = X_k + ΔX_k,

raising the damping μ when the error norm grows (the step is then rejected) and lowering it
when it falls, and stop when successive error norms differ by at most ``tol_mm`` (1e-4). The
iteration runs on the identifiable parameters only (see
:mod:`calibration.identify.identifiability`),
in column-scaled units so that one μ suits mm and rad alike.

Every accepted iterate is watched: a free parameter whose column collapses or that runs
away (non-finite, an angle beyond ±π from its start, a length beyond the arm's reach) is
dropped with its reason and the fit starts again from the start point without it, at most
:data:`MAX_RESTARTS` times; what cannot be resolved raises :class:`IdentificationError`.

Non-geometric effect terms (the closed loop's, :mod:`calibration.effects.closed_loop`) join the
problem as :class:`EffectTerms`: k parameters ``c`` appended to the geometric vector, the
predicted point being ``tcp(model, q) + R(model, q, ...)·c`` with the effects' analytic
regressor ``R`` ``(m, 3, k)``. They go through the same identifiability test (offered after
every geometric parameter) and the same LM, covariance and outlier test.

Residuals are ``model − tracker`` (mm, shape ``(3m,)``), written as pure functions of the
parameter vector and the data. A robust loss (Huber, soft-L1, Cauchy) is applied by
iteratively reweighting whole poses; poses whose 3-D residual is improbably large for the
estimated noise are reported as outliers whatever the loss.

This module sets the problem up and runs it (:func:`identify`); the pieces live in modules
of their own: the residuals (:mod:`~calibration.identify.position_residuals`), the solver
(:mod:`~calibration.identify.levenberg_marquardt`), the watch over its iterates
(:mod:`~calibration.identify.runaway_watch`) and the result
(:mod:`~calibration.identify.identification_result`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import IdentifiabilityError, IdentificationError

if TYPE_CHECKING:  # scipy loads when a fit runs: a command that only reads a model is quick
    from scipy.optimize import OptimizeResult
from calibration.identify.identifiability import (
    DEFAULT_RTOL,
    IdentifiabilityAnalysis,
    analyze_identifiability,
    column_references,
    default_priority,
)
from calibration.identify.identification_result import IdentificationResult, effect_unit
from calibration.identify.levenberg_marquardt import (
    DEFAULT_LM_SETTINGS,
    LMSettings,
    ProgressCallback,
    levenberg_marquardt,
)
from calibration.identify.position_residuals import (
    EffectTerms,
    full_vector,
    position_residual_jacobian,
    position_residuals,
    predicted_points,
    stacked_jacobian,
)
from calibration.identify.runaway_watch import RAN_AWAY, RunAway, RunawayWatch, credible_moves
from calibration.model.kinematics import (
    KinematicModel,
    tcp_positions,
)
from calibration.model.registration import rigid_registration

#: Re-exported where the closed loop, its report, ``twin identify``, ``twin run`` and the
#: recursive identification import them from (those modules are being edited on another
#: branch; new code imports them from the modules that define them).
__all__ = [
    "LOSSES",
    "RAN_AWAY",
    "START_METHODS",
    "EffectTerms",
    "IdentificationResult",
    "LMSettings",
    "ProgressCallback",
    "base_start_from_registration",
    "effect_unit",
    "identify",
    "predicted_points",
    "tracker_sigma_mm",
]

FloatArray = NDArray[np.float64]


#: Robust losses: name -> per-pose IRLS weight as a function of (3-D residual / f_scale).
LOSSES: dict[str, Callable[[FloatArray], FloatArray]] = {
    "linear": lambda z: np.ones_like(z),
    "huber": lambda z: np.where(z <= 1.0, 1.0, 1.0 / np.maximum(z, 1e-300)),
    "soft_l1": lambda z: 1.0 / np.sqrt(1.0 + z * z),
    "cauchy": lambda z: 1.0 / (1.0 + z * z),
}


#: Where the start value of the base pose came from.
START_METHODS = ("description", "registration")


#: Two-sided probability beyond which a pose's 3-D residual marks it as an outlier.
OUTLIER_PROBABILITY = 1e-3


def tracker_sigma_mm(
    points_mm: ArrayLike,
    mpe_um: float = 15.0,
    mpe_um_per_m: float = 6.0,
    mpe_sigmas: float = 2.0,
    tracker_mm: ArrayLike = (0.0, 0.0, 0.0),
) -> FloatArray:
    """Per-axis σ ``(m,)`` mm of tracker points from a data-sheet MPE ±(A µm + B µm/m · d),
    taken as ``mpe_sigmas`` σ, d the distance from the tracker (the frame origin)."""
    d_m = np.linalg.norm(np.atleast_2d(points_mm) - np.asarray(tracker_mm), axis=1) / 1000.0
    sigma: FloatArray = 1e-3 * (mpe_um + mpe_um_per_m * d_m) / mpe_sigmas
    return sigma


def base_start_from_registration(
    model: KinematicModel, q_rad: ArrayLike, measured_mm: ArrayLike
) -> KinematicModel:
    """``model`` with its base pose from a rigid registration of base-frame TCPs on points."""
    local = tcp_positions(model, q_rad, world=False)
    reg = rigid_registration(np.atleast_2d(local), np.atleast_2d(measured_mm))
    x = model.parameter_vector()
    off = 5 * model.n_joints
    x[off : off + 3] = reg.translation_mm
    x[off + 3 : off + 6] = reg.fixed_xyz_rad()
    return model.with_parameters(x)


#: Restarts from the start point after dropping parameters that ran away, before giving up.
MAX_RESTARTS = 3


@dataclass(frozen=True, eq=False)
class _Problem:
    """The identification data at its start point, where every (re)start begins."""

    nominal: KinematicModel
    q: FloatArray  # (m, n) rad
    meas: FloatArray  # (m, 3) mm
    prior: FloatArray  # (m,) relative point weights, mean 1
    effects: EffectTerms | None
    x_start: FloatArray  # (p,) full start vector, geometry then effects (mm, rad, ...)
    jac_start: FloatArray  # (m, 3, p) unweighted Jacobian at the start point
    column_sq_start: FloatArray  # (m, p) per pose, Σ over x, y, z of jac_start²
    max_move: FloatArray  # (p,) largest credible |x − x_start| (see credible_moves)

    @classmethod
    def at_start(
        cls,
        nominal: KinematicModel,
        start_model: KinematicModel,
        q: FloatArray,
        meas: FloatArray,
        prior: FloatArray,
        effects: EffectTerms | None,
    ) -> _Problem:
        """The problem with its start vector and Jacobian at ``start_model``."""
        x_start = start_model.parameter_vector()
        n_effects = 0
        if effects is not None:
            x_start = np.concatenate([x_start, effects.start_vector()])
            n_effects = effects.n_parameters
        jac_start = stacked_jacobian(start_model, q, effects)
        return cls(
            nominal=nominal,
            q=q,
            meas=meas,
            prior=prior,
            effects=effects,
            x_start=x_start,
            jac_start=jac_start,
            column_sq_start=np.einsum("mip,mip->mp", jac_start, jac_start),
            max_move=credible_moves(start_model, meas, n_effects),
        )

    def residual_args(self, free_idx: NDArray[np.intp], sw: FloatArray) -> tuple[object, ...]:
        """The data arguments of :func:`position_residuals` and its Jacobian, the poses
        weighted by ``sw`` ``(m,)``."""
        return (self.x_start, free_idx, self.nominal, self.q, self.meas, sw, self.effects)


@dataclass(frozen=True)
class _Fit:
    """One LM fit with its robust-loss reweighting (IRLS)."""

    result: OptimizeResult  # of the last LM run (x: free parameters)
    weights: FloatArray  # (m,) final robust-loss weights
    sw_last: FloatArray  # (m,) √(prior · weights) of the last LM run
    f_scale_mm: float | None
    irls: int


def _robust_fit(
    problem: _Problem,
    analysis: IdentifiabilityAnalysis,
    *,
    loss: str,
    f_scale_mm: float | None,
    max_irls: int,
    settings: LMSettings,
    record: ProgressCallback,
) -> _Fit:
    """LM on the free parameters of ``analysis`` from the start point, reweighted by the
    robust loss; raises :class:`RunAway` through the watch."""
    m = len(problem.q)
    free_idx = analysis.free_indices
    x_scale = 1.0 / analysis.column_scale[free_idx]
    names = tuple(analysis.parameter_names[i] for i in free_idx)
    column_sq = problem.column_sq_start[:, free_idx]
    weights = np.ones(m)
    x = problem.x_start[free_idx]
    sw_last = np.ones(m)
    result: OptimizeResult | None = None
    scale_used = f_scale_mm
    irls = 0
    while irls < (max_irls if loss != "linear" else 1):
        irls += 1
        sw = np.sqrt(problem.prior * weights)
        start_rms = np.sqrt(sw**2 @ column_sq / (3 * m))  # same weights as this run
        watch = RunawayWatch(
            names, free_idx, problem.x_start[free_idx], problem.max_move[free_idx], start_rms
        )
        result = levenberg_marquardt(
            position_residuals,
            position_residual_jacobian,
            x,
            args=problem.residual_args(free_idx, sw),
            x_scale=x_scale,
            settings=settings,
            progress=record,
            watch=watch,
        )
        if result.status == -2:
            raise IdentificationError(result.message)
        x = result.x
        sw_last = sw
        if loss == "linear":
            break
        new_w, scale_used = _robust_weights(result.fun, weights, loss, f_scale_mm, scale_used)
        converged = np.max(np.abs(new_w - weights)) < 1e-3
        weights = new_w
        if converged:
            break
    assert result is not None
    return _Fit(result, weights, sw_last, scale_used, irls)


def _robust_weights(
    residuals: FloatArray,
    weights: FloatArray,
    loss: str,
    f_scale_mm: float | None,
    scale_used: float | None,
) -> tuple[FloatArray, float | None]:
    """The robust loss's next pose weights ``(m,)`` from the weighted residuals ``(3m,)`` of
    a run with ``weights``, and the scale they used (``f_scale_mm``, or estimated from the
    residuals when it is None)."""
    # 3-D residuals in units of the reference σ's pose (prior-weighted, not robust)
    dist = np.linalg.norm(residuals.reshape(-1, 3), axis=1) / np.sqrt(np.maximum(weights, 1e-300))
    if f_scale_mm is None:
        # 3 σ per axis, σ from the median 3-D distance (median of Maxwell = 1.538 σ)
        scale_used = 3.0 * float(np.median(dist)) / 1.538
    return LOSSES[loss](dist / max(scale_used or 1e-12, 1e-12)), scale_used


def _fit_dropping_runaways(
    analyze: Callable[[dict[int, str]], IdentifiabilityAnalysis],
    fit: Callable[[IdentifiabilityAnalysis], _Fit],
) -> tuple[IdentifiabilityAnalysis, _Fit]:
    """Fit; while parameters run away or lose their effect, drop them (named, with the
    reason) and fit again from the start point, at most :data:`MAX_RESTARTS` times."""
    excluded: dict[int, str] = {}
    for _ in range(MAX_RESTARTS + 1):
        analysis = analyze(excluded)
        try:
            return analysis, fit(analysis)
        except RunAway as exc:
            excluded.update(exc.reasons)
            last = exc
    names = analysis.parameter_names
    detail = "; ".join(f"{names[i]} {why}" for i, why in last.reasons.items())
    raise IdentificationError(
        f"the fit ran away, still after {MAX_RESTARTS} restart(s) without the parameters "
        f"concerned: {detail}"
    )


def _scaled_covariance(js: FloatArray) -> FloatArray:
    """``(JsᵀJs)⁻¹`` ``(k, k)`` of a column-scaled Jacobian ``(3m, k)`` from the Gram
    matrix's eigen-decomposition: symmetric with a non-negative diagonal even where
    rounding leaves the Gram matrix slightly indefinite (a pseudo-inverse can then give a
    negative variance, hence a NaN standard error). Directions whose eigenvalue is below
    1e-15 of the largest are left out, as ``pinv`` does."""
    w, v = np.linalg.eigh(js.T @ js)
    keep = w > 1e-15 * max(float(w.max(initial=0.0)), 0.0)
    cov: FloatArray = (v[:, keep] / w[keep]) @ v[:, keep].T
    return cov


def identify(
    nominal: KinematicModel,
    q_rad: ArrayLike,
    measured_mm: ArrayLike,
    *,
    start: str | None = None,
    loss: str = "linear",
    f_scale_mm: float | None = None,
    settings: LMSettings = DEFAULT_LM_SETTINGS,
    rtol: float = DEFAULT_RTOL,
    fixed: tuple[str, ...] = (),
    max_irls: int = 10,
    point_sigma_mm: ArrayLike | None = None,
    progress: ProgressCallback | None = None,
    effects: EffectTerms | None = None,
) -> IdentificationResult:
    """Identify the kinematic parameters from joint vectors ``q`` ``(m, n)`` rad and tracker
    points ``(m, 3)`` mm.

    ``nominal`` carries the nominal geometry and tool. Its base pose is the start value when
    ``start="description"``; with ``start="registration"`` the base pose comes from a rigid
    registration of the nominal TCPs onto the points. ``fixed`` names parameters held at
    their nominal value whatever the data says. ``point_sigma_mm`` ``(m,)`` gives each
    point's per-axis measurement σ (e.g. :func:`tracker_sigma_mm`): the poses are then
    weighted by 1/σ² (without it, all poses weigh the same). ``effects`` adds non-geometric
    terms built on these poses; their parameters are identified with the geometry.

    Long for its options and its result's fields; each step is a function of its own.
    """
    started = time.perf_counter()
    q, meas = _checked_poses(nominal, q_rad, measured_mm)
    start = _checked_options(loss, start)
    names = _parameter_names(nominal, effects, fixed)
    p_geo = nominal.n_parameters
    if len(q) < 4:
        raise IdentificationError(f"need at least 4 poses, got {len(q)}")
    prior, reference_sigma = _prior_weights(point_sigma_mm, len(q))
    start_model = (
        base_start_from_registration(nominal, q, meas) if start == "registration" else nominal
    )
    problem = _Problem.at_start(nominal, start_model, q, meas, prior, effects)
    analyze = _Analyzer(
        jac_start=problem.jac_start,
        names=names,
        priority=default_priority(nominal) + list(range(p_geo, len(names))),
        rtol=rtol,
        fixed=[names.index(f) for f in fixed],
        references=column_references(nominal, len(names) - p_geo),
    )
    record = _Recorder(progress)

    def fit(analysis: IdentifiabilityAnalysis) -> _Fit:
        return _robust_fit(
            problem,
            analysis,
            loss=loss,
            f_scale_mm=f_scale_mm,
            max_irls=max_irls,
            settings=settings,
            record=record,
        )

    analysis, done = _fit_dropping_runaways(analyze, fit)
    final = full_vector(done.result.x, problem.x_start, analysis.free_indices)
    model = nominal.with_parameters(final[:p_geo])
    effect_values = final[p_geo:]
    spread = _spread(problem, analysis, done, model, effect_values)
    return IdentificationResult(
        model=model,
        start_model=start_model,
        start_method=start,
        identifiability=analysis,
        covariance=spread.covariance,
        sigma_mm=spread.sigma_mm,
        pose_weights=done.weights,
        outliers=spread.outliers,
        loss=loss,
        f_scale_mm=done.f_scale_mm if loss != "linear" else None,
        optimize_result=done.result,
        elapsed_s=time.perf_counter() - started,
        irls_iterations=done.irls,
        history=record.history,
        reference_sigma_mm=reference_sigma,
        effects=effects,
        effect_values=effect_values,
    )


def _checked_poses(
    nominal: KinematicModel, q_rad: ArrayLike, measured_mm: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Joint vectors ``(m, n)`` rad and points ``(m, 3)`` mm as float arrays, their shapes
    and finiteness checked."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    meas = np.atleast_2d(np.asarray(measured_mm, dtype=float))
    if q.ndim != 2 or q.shape[1] != nominal.n_joints:
        raise IdentificationError(f"joint array must be (m, {nominal.n_joints}), got {q.shape}")
    if meas.shape != (len(q), 3):
        raise IdentificationError(f"points must be ({len(q)}, 3), got {meas.shape}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(meas))):
        raise IdentificationError("joint angles and points must be finite")
    return q, meas


def _parameter_names(
    nominal: KinematicModel, effects: EffectTerms | None, fixed: tuple[str, ...]
) -> list[str]:
    """The full vector's parameter names, geometry then effects; ``fixed`` must be among them."""
    names = nominal.parameter_names()
    if effects is not None:
        names = names + list(effects.names)
    unknown = [f for f in fixed if f not in names]
    if unknown:
        raise IdentificationError(f"unknown parameter(s) to fix: {', '.join(unknown)}")
    return names


@dataclass(frozen=True)
class _Recorder:
    """Keeps every LM iteration's (iteration, error norm mm, damping) across the runs of one
    identification, and passes each on to ``progress``."""

    progress: ProgressCallback | None
    history: list[tuple[int, float, float]] = field(default_factory=list)

    def __call__(self, it: int, norm: float, mu: float) -> None:
        self.history.append((it, norm, mu))
        if self.progress is not None:
            self.progress(it, norm, mu)


def _checked_options(loss: str, start: str | None) -> str:
    """Check the loss against :data:`LOSSES`; the start method (default: the description's)."""
    if loss not in LOSSES:
        raise IdentificationError(f"unknown loss {loss!r} (valid: {', '.join(LOSSES)})")
    start = start or "description"
    if start not in START_METHODS:
        raise IdentificationError(f"unknown start {start!r} (valid: {', '.join(START_METHODS)})")
    return start


def _prior_weights(point_sigma_mm: ArrayLike | None, m: int) -> tuple[FloatArray, float | None]:
    """Relative pose weights ``(m,)`` (mean 1) from per-point σ ``(m,)`` mm, and the σ they
    are relative to (their harmonic RMS); all ones and None without σ."""
    if point_sigma_mm is None:
        return np.ones(m), None
    ps = np.broadcast_to(np.asarray(point_sigma_mm, dtype=float), (m,))
    if not np.all(np.isfinite(ps) & (ps > 0)):
        raise IdentificationError("point sigmas must be finite and positive")
    reference_sigma = float(1.0 / np.sqrt(np.mean(1.0 / ps**2)))
    return (reference_sigma / ps) ** 2, reference_sigma


@dataclass(frozen=True, eq=False)
class _Analyzer:
    """The identifiability test at the start point, without the parameters excluded so far."""

    jac_start: FloatArray  # (m, 3, p)
    names: list[str]  # (p,)
    priority: list[int]
    rtol: float
    fixed: list[int]
    references: FloatArray  # (p,)

    def __call__(self, excluded: dict[int, str]) -> IdentifiabilityAnalysis:
        try:
            analysis = analyze_identifiability(
                self.jac_start,
                self.names,
                priority=self.priority,
                rtol=self.rtol,
                fixed=self.fixed,
                references=self.references,
                excluded=excluded,
            )
        except IdentifiabilityError as exc:
            if not excluded:
                raise
            raise IdentificationError(
                f"nothing left to identify without the parameters that ran away: {exc}"
            ) from None
        m = len(self.jac_start)
        if 3 * m <= analysis.rank:
            raise IdentificationError(
                f"{m} poses give {3 * m} equations for {analysis.rank} identifiable parameters"
            )
        return analysis


@dataclass(frozen=True)
class _Spread:
    """How far the identified parameters and the poses can be trusted."""

    covariance: FloatArray  # (k, k) of the free parameters, model units
    sigma_mm: float  # per-axis noise from the weighted residuals
    outliers: NDArray[np.bool_]  # (m,)


def _spread(
    problem: _Problem,
    analysis: IdentifiabilityAnalysis,
    done: _Fit,
    model: KinematicModel,
    effect_values: FloatArray,
) -> _Spread:
    """Covariance, noise and outlier poses of the fit ``done`` at its solution."""
    result, weights, prior, q = done.result, done.weights, problem.prior, problem.q
    free_idx = analysis.free_indices
    k = len(free_idx)
    sw = np.sqrt(prior * weights)
    resid = predicted_points(model, q, problem.effects, effect_values) - problem.meas
    # the solver's last Jacobian is at x, weighted with the weights of its last run
    jw = result.jac * (sw / np.maximum(done.sw_last, 1e-300)).repeat(3)[:, None]
    dof = max(3 * len(q) - k, 1)
    wsum = float(np.sum((resid * sw[:, None]) ** 2))
    sigma2 = wsum / dof * len(q) / max(float(np.sum(weights)), 1e-300)
    d = 1.0 / analysis.column_scale[free_idx]
    covariance = sigma2 * _scaled_covariance(jw * d) * np.outer(d, d)
    dist = np.linalg.norm(resid, axis=1) * np.sqrt(prior)
    # robust per-axis σ for the outlier test: the median of a Maxwell distance is 1.538 σ,
    # and fitted residuals are smaller than the noise by √(1 − k/3m) on average
    robust_sigma = float(np.median(dist)) / 1.538 / math.sqrt(max(1.0 - k / (3 * len(q)), 0.1))
    from scipy.stats import chi2

    threshold = robust_sigma * math.sqrt(chi2.ppf(1.0 - OUTLIER_PROBABILITY, 3))
    return _Spread(covariance, math.sqrt(sigma2), dist > threshold)
