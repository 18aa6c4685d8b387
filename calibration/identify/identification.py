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
    NO_EFFECT,
    IdentifiabilityAnalysis,
    analyze_identifiability,
    arm_reach_mm,
    column_references,
    column_rms,
    default_priority,
)
from calibration.model.kinematics import (
    KinematicModel,
    identification_jacobian,
    tcp_positions,
)
from calibration.model.registration import rigid_registration

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

TERMINATION_MESSAGES = {
    -2: "the residuals were not finite at any damping: the iteration ran away",
    -1: "the step could not reduce the error: damping limit reached",
    0: "the maximum number of iterations was reached",
    1: "change of the error norm <= tol_mm",
    2: "the error norm is zero",
}

#: Two-sided probability beyond which a pose's 3-D residual marks it as an outlier.
OUTLIER_PROBABILITY = 1e-3


ProgressCallback = Callable[[int, float, float], None]  # (iteration, error norm mm, damping)

#: An effect regressor: (geometric model, slice of the poses) -> ∂TCP/∂c ``(rows, 3, k)``,
#: mm per unit of each effect parameter, for the poses the terms were built on.
EffectRegressor = Callable[[KinematicModel, slice], NDArray[np.float64]]


@dataclass(frozen=True, eq=False)
class EffectTerms:
    """Non-geometric terms linear in k parameters appended to the geometric vector.

    The twin predicts ``tcp(model, q) + regressor(model, poses) · c``. ``names`` carry the
    parameters' units (they are reported as they are); ``start`` defaults to zeros.
    """

    names: tuple[str, ...]
    regressor: EffectRegressor
    start: tuple[float, ...] | None = None

    @property
    def n_parameters(self) -> int:
        return len(self.names)

    def start_vector(self) -> NDArray[np.float64]:
        return np.zeros(len(self.names)) if self.start is None else np.asarray(self.start, float)


@dataclass(frozen=True)
class LMSettings:
    """Levenberg-Marquardt settings (the source's: μ ×10 on failure, ÷10 on success)."""

    mu0: float = 1e-3
    increase: float = 10.0
    decrease: float = 0.1
    mu_max: float = 1e12
    tol_mm: float = 1e-4  # stop when successive error norms (mm) differ by at most this
    max_iterations: int = 100


# -- pure residual functions --------------------------------------------------------------
def _full_vector(x_free: FloatArray, x_full: FloatArray, free_idx: NDArray[np.intp]) -> FloatArray:
    x = np.array(x_full, dtype=float)
    x[free_idx] = x_free
    return x


#: Poses per block when evaluating residuals and Jacobians: keeps temporaries small so the
#: cost stays linear in the number of poses.
CHUNK_POSES = 8192


def _split(x: FloatArray, template: KinematicModel) -> tuple[KinematicModel, FloatArray]:
    """Geometry and effect parameters of a full vector ``(5n + 9 + k,)``."""
    p = template.n_parameters
    return template.with_parameters(x[:p]), x[p:]


def position_residuals(
    x_free: ArrayLike,
    x_full: FloatArray,
    free_idx: NDArray[np.intp],
    template: KinematicModel,
    q_rad: FloatArray,
    measured_mm: FloatArray,
    sqrt_weights: FloatArray,
    effects: EffectTerms | None = None,
) -> FloatArray:
    """Weighted residuals ``(3m,)``: (predicted point − tracker point), mm times √weight.

    ``x_free`` replaces the entries ``free_idx`` of the full parameter vector ``x_full``,
    which is ``(5n + 9,)``, or ``(5n + 9 + k,)`` with ``effects`` appended.
    """
    model, c = _split(_full_vector(np.asarray(x_free), x_full, free_idx), template)
    pred = predicted_points(model, q_rad, effects, c)
    return ((pred - measured_mm) * sqrt_weights[:, None]).ravel()


def position_residual_jacobian(
    x_free: ArrayLike,
    x_full: FloatArray,
    free_idx: NDArray[np.intp],
    template: KinematicModel,
    q_rad: FloatArray,
    measured_mm: FloatArray,
    sqrt_weights: FloatArray,
    effects: EffectTerms | None = None,
) -> FloatArray:
    """Jacobian ``(3m, k_free)`` of :func:`position_residuals` with respect to ``x_free``.

    The effect regressors' own dependence on the geometry (second order in sub-mm
    effects) is left out.
    """
    model, _ = _split(_full_vector(np.asarray(x_free), x_full, free_idx), template)
    jac = stacked_jacobian(model, q_rad, effects)
    return (jac[:, :, free_idx] * sqrt_weights[:, None, None]).reshape(-1, len(free_idx))


def stacked_jacobian(
    model: KinematicModel, q_rad: FloatArray, effects: EffectTerms | None = None
) -> FloatArray:
    """∂TCP/∂(geometry, effect parameters) ``(m, 3, 5n + 9 + k)``, in blocks of poses."""
    k = 0 if effects is None else effects.n_parameters
    p = model.n_parameters
    out = np.empty((len(q_rad), 3, p + k))
    for s in range(0, len(q_rad), CHUNK_POSES):
        e = slice(s, min(s + CHUNK_POSES, len(q_rad)))
        out[e, :, :p] = identification_jacobian(model, q_rad[e])[1]
        if effects is not None:
            out[e, :, p:] = effects.regressor(model, e)
    return out


def predicted_points(
    model: KinematicModel,
    q_rad: FloatArray,
    effects: EffectTerms | None = None,
    effect_values: ArrayLike | None = None,
) -> FloatArray:
    """Predicted tracker points ``(m, 3)`` mm: geometric TCP plus the effect terms."""
    tcp = tcp_positions(model, q_rad)
    if effects is None or effects.n_parameters == 0:
        return tcp
    c = np.asarray(effect_values, dtype=float)
    out = np.empty_like(tcp)
    for s in range(0, len(q_rad), CHUNK_POSES):
        e = slice(s, min(s + CHUNK_POSES, len(q_rad)))
        out[e] = tcp[e] + effects.regressor(model, e) @ c
    return out


# -- the solver ------------------------------------------------------------------------
#: A check of each accepted iterate: (iteration, x, residuals, Jacobian) -> None. It may
#: raise to end the iteration (identify() drops parameters that ran away through it).
IterateWatch = Callable[[int, FloatArray, FloatArray, FloatArray], None]


def levenberg_marquardt(
    fun: Callable[..., FloatArray],
    jac: Callable[..., FloatArray],
    x0: ArrayLike,
    *,
    args: tuple[object, ...] = (),
    x_scale: ArrayLike | None = None,
    settings: LMSettings = LMSettings(),
    progress: ProgressCallback | None = None,
    watch: IterateWatch | None = None,
) -> OptimizeResult:
    """Minimize ``½‖fun(x, *args)‖²`` by the source's Levenberg-Marquardt iteration.

    ``x_scale`` (k,) gives the characteristic size of each variable; the damping acts on
    ``x / x_scale``. ``watch`` sees the start point and every accepted iterate; what it
    raises ends the iteration and propagates. Returns a :class:`scipy.optimize.OptimizeResult`
    with x, cost, fun, jac, grad, optimality, nfev, njev, nit, status, message, success and
    ``mu``. ``success``: converged (status 1 or 2), or status −1 (no step of any damping
    lowers the error) at a finite error norm: the last accepted point has the smallest
    norm seen and no descent step is left at the solver's resolution. Status 0 (iteration
    limit) and −2 (non-finite residuals at every damping) are failures.
    """
    x = np.array(x0, dtype=float)
    scale = np.ones_like(x) if x_scale is None else np.asarray(x_scale, dtype=float)
    f = fun(x, *args)
    j = jac(x, *args)
    nfev, njev = 1, 1
    norm = float(np.linalg.norm(f))
    mu = settings.mu0
    status = 0
    nit = 0
    if watch is not None:
        watch(0, x, f, j)
    if progress is not None:
        progress(0, norm, mu)
    for nit in range(1, settings.max_iterations + 1):
        if norm == 0.0:
            status = 2
            break
        trial = _damped_step(fun, args, x, f, norm, j * scale, scale, mu, settings)
        nfev += trial.nfev
        mu = trial.mu
        if not trial.accepted:
            status = _rejected_status(norm, trial.norm, settings.tol_mm)
            break
        change = norm - trial.norm
        x, f, norm = trial.x, trial.f, trial.norm
        j = jac(x, *args)
        njev += 1
        if watch is not None:
            watch(nit, x, f, j)
        if progress is not None:
            progress(nit, norm, mu)
        if change <= settings.tol_mm:
            status = 1
            break
    return _lm_result(x, f, j, norm, mu, status, nit=nit, nfev=nfev, njev=njev)


@dataclass(frozen=True)
class _Trial:
    """One LM iteration's search over the damping: the trial point it ended on."""

    accepted: bool  # the error norm fell: x, f, norm are the new iterate
    x: FloatArray  # (k,) the accepted point (the current one when not accepted)
    f: FloatArray  # (3m,) its residuals
    norm: float  # error norm of the last trial step (inf: non-finite residuals)
    mu: float  # damping after the search
    nfev: int  # residual evaluations spent


def _damped_step(
    fun: Callable[..., FloatArray],
    args: tuple[object, ...],
    x: FloatArray,
    f: FloatArray,
    norm: float,
    js: FloatArray,
    scale: FloatArray,
    mu: float,
    settings: LMSettings,
) -> _Trial:
    """Raise the damping μ from ``mu`` until a step on the column-scaled Jacobian ``js``
    ``(3m, k)`` lowers the error norm, the step changes it by <= tol_mm (at the minimum),
    or μ passes ``mu_max``."""
    a = js.T @ js
    g = js.T @ f
    norm_new = math.inf
    nfev = 0
    while mu <= settings.mu_max:
        try:
            step = -np.linalg.solve(a + mu * np.eye(len(x)), g) * scale
        except np.linalg.LinAlgError:
            mu *= settings.increase
            continue
        x_new = x + step
        f_new = fun(x_new, *args)
        nfev += 1
        norm_new = float(np.linalg.norm(f_new)) if np.all(np.isfinite(f_new)) else math.inf
        if norm_new < norm:
            return _Trial(True, x_new, f_new, norm_new, max(mu * settings.decrease, 1e-12), nfev)
        if norm_new - norm <= settings.tol_mm:
            break  # at the minimum: a step changes the error norm by <= tol_mm
        mu *= settings.increase
    return _Trial(False, x, f, norm_new, mu, nfev)


def _lm_result(
    x: FloatArray,
    f: FloatArray,
    j: FloatArray,
    norm: float,
    mu: float,
    status: int,
    *,
    nit: int,
    nfev: int,
    njev: int,
) -> OptimizeResult:
    """The solver's end point as scipy reports it (see :func:`levenberg_marquardt`)."""
    grad = j.T @ f
    from scipy.optimize import OptimizeResult

    return OptimizeResult(
        x=x,
        cost=0.5 * norm**2,
        fun=f,
        jac=j,
        grad=grad,
        optimality=float(np.max(np.abs(grad))) if grad.size else 0.0,
        nfev=nfev,
        njev=njev,
        nit=nit,
        mu=mu,
        status=status,
        message=TERMINATION_MESSAGES[status],
        success=status > 0 or (status == -1 and math.isfinite(norm)),
    )


def _rejected_status(norm: float, norm_new: float, tol_mm: float) -> int:
    """Status when no trial step was accepted: 1 at the minimum (the last trial changed
    the norm by <= tol_mm), −2 when its residuals were not finite, else −1."""
    if norm_new - norm <= tol_mm:
        return 1
    return -1 if math.isfinite(norm_new) else -2


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


# -- the problem and its result ----------------------------------------------------------
@dataclass(frozen=True)
class IdentificationResult:
    """Identified model, its uncertainty, what was dropped, and the solver's own result."""

    model: KinematicModel  # identified geometry, base and tool
    start_model: KinematicModel  # nominal geometry with the start base pose
    start_method: str  # one of START_METHODS
    identifiability: IdentifiabilityAnalysis
    covariance: FloatArray  # (k, k) of the identified parameters, model units (mm, rad)
    sigma_mm: float  # per-axis noise estimated from the residuals (of a reference pose)
    pose_weights: FloatArray  # (m,) final robust-loss weights (1 with the linear loss)
    outliers: NDArray[np.bool_]  # (m,) poses whose residual is improbably large
    loss: str
    f_scale_mm: float | None
    optimize_result: OptimizeResult  # of the last LM run (x: free parameters)
    elapsed_s: float
    irls_iterations: int = 1
    history: list[tuple[int, float, float]] = field(default_factory=list)
    #: with per-point σ: the σ the weights are relative to (their harmonic RMS); sigma_mm
    #: over it is how the data compare with the stated σ (1: as stated). None: unweighted.
    reference_sigma_mm: float | None = None
    #: effect terms identified with the geometry (None: the geometric model alone)
    effects: EffectTerms | None = None
    effect_values: FloatArray = field(default_factory=lambda: np.zeros(0))  # (k,)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Geometric parameter names, then the effect parameters' (with their units)."""
        return self.identifiability.parameter_names

    @property
    def free(self) -> NDArray[np.bool_]:
        return self.identifiability.free

    @property
    def success(self) -> bool:
        return bool(self.optimize_result.success)

    @property
    def n_geometric(self) -> int:
        return self.model.n_parameters

    def parameter_vector(self) -> FloatArray:
        """Identified geometry then effect parameters ``(5n + 9 + k,)``."""
        return np.concatenate([self.model.parameter_vector(), self.effect_values])

    def start_vector(self) -> FloatArray:
        start = np.zeros(0) if self.effects is None else self.effects.start_vector()
        return np.concatenate([self.start_model.parameter_vector(), start])

    def deviations(self) -> FloatArray:
        """Identified minus start parameters, full vector ``(5n + 9 [+ k],)`` (mm, rad)."""
        return self.parameter_vector() - self.start_vector()

    def standard_errors(self) -> FloatArray:
        """Standard errors, full vector (mm, rad, effect units); NaN exactly for the dropped
        parameters (held at their start value), finite for every identified one."""
        se = np.full(len(self.parameter_names), np.nan)
        se[self.free] = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return se

    def residuals_mm(self, q_rad: ArrayLike, measured_mm: ArrayLike) -> FloatArray:
        """Errors ``tracker − twin`` ``(N, 3)`` mm of the identified *geometric* model
        (effect terms need their own per-pose data: see :mod:`calibration.effects.closed_loop`)."""
        return np.asarray(measured_mm, dtype=float) - tcp_positions(self.model, q_rad)

    def prediction_covariance(self, q_rad: ArrayLike) -> FloatArray:
        """Covariance ``(N, 3, 3)`` mm² of the predicted geometric TCP at ``q`` from the
        geometric parameters."""
        _, jac = identification_jacobian(self.model, np.atleast_2d(q_rad))
        p = self.n_geometric
        geo = self.free[:p]
        n_geo = int(np.count_nonzero(geo))
        jf = jac[:, :, geo]
        cov = self.covariance[:n_geo, :n_geo]
        return jf @ cov @ jf.transpose(0, 2, 1)

    def parameter_table(self) -> list[dict[str, object]]:
        """One row per parameter, in human units (mm and degrees; effect parameters in the
        units their names carry)."""
        start = self.start_vector()
        final = self.parameter_vector()
        se = self.standard_errors()
        dropped = {d.name: d.reason for d in self.identifiability.dropped}
        rows = []
        for i, name in enumerate(self.parameter_names):
            if i >= self.n_geometric:
                rows.append(
                    {
                        "name": name,
                        "unit": effect_unit(name),
                        "start": float(start[i]),
                        "identified": float(final[i]),
                        "deviation": float(final[i] - start[i]),
                        "standard_error": None if np.isnan(se[i]) else float(se[i]),
                        "identified_from_data": bool(self.free[i]),
                        "dropped_reason": dropped.get(name),
                    }
                )
                continue
            to_deg = name.endswith("_rad")
            k = math.degrees(1.0) if to_deg else 1.0
            unit = "deg" if to_deg else "mm"
            rows.append(
                {
                    "name": name.removesuffix("_rad").removesuffix("_mm") + f"_{unit}",
                    "unit": unit,
                    "start": float(start[i] * k),
                    "identified": float(final[i] * k),
                    "deviation": float((final[i] - start[i]) * k),
                    "standard_error": None if np.isnan(se[i]) else float(se[i] * k),
                    "identified_from_data": bool(self.free[i]),
                    "dropped_reason": dropped.get(name),
                }
            )
        return rows


#: Unit suffixes of effect parameter names (longest first) -> unit for people.
EFFECT_UNITS = (
    ("_urad_per_knm", "µrad/(kN·m)"),
    ("_mm_per_h2", "mm/h²"),
    ("_ppm_per_h", "ppm/h"),
    ("_mm_per_h", "mm/h"),
    ("_ppm", "ppm"),
    ("_deg", "deg"),
    ("_mm", "mm"),
)


def effect_unit(name: str) -> str:
    """The unit an effect parameter's name ends with (``''`` when none is known)."""
    return next((u for suffix, u in EFFECT_UNITS if name.endswith(suffix)), "")


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

#: A free column whose RMS falls below this fraction of its start value has collapsed.
COLLAPSE_RATIO = 1e-6

#: Why a parameter is dropped during the iterations (details follow in parentheses).
COLLAPSED = NO_EFFECT + " during the iterations"
RAN_AWAY = "ran away during the iterations"


class _RunAway(Exception):
    """Raised by :class:`_Watch`: free parameters (full-vector index -> reason) to drop."""

    def __init__(self, reasons: dict[int, str]) -> None:
        super().__init__("; ".join(reasons.values()))
        self.reasons = reasons


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
    max_move: FloatArray  # (p,) largest credible |x − x_start| (see _credible_moves)

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
            max_move=_credible_moves(start_model, meas, n_effects),
        )

    def residual_args(self, free_idx: NDArray[np.intp], sw: FloatArray) -> tuple[object, ...]:
        """The data arguments of :func:`position_residuals` and its Jacobian, the poses
        weighted by ``sw`` ``(m,)``."""
        return (self.x_start, free_idx, self.nominal, self.q, self.meas, sw, self.effects)


def _credible_moves(start: KinematicModel, meas: FloatArray, n_effects: int) -> FloatArray:
    """Largest credible |identified − start| ``(5n + 9 + n_effects,)`` (rad, mm).

    π for an angle; the arm's reach for a length of the arm or tool; for the base
    translation the reach plus the farthest point from the start base (every point lies
    within reach of the true base); no limit for effect parameters (arbitrary units).
    """
    reach = arm_reach_mm(start)
    far = float(np.max(np.linalg.norm(meas - start.base_mm, axis=1)))
    moves = [
        math.pi if n.endswith("_rad") else reach + far if n.startswith("base.") else reach
        for n in start.parameter_names()
    ]
    return np.concatenate([moves, np.full(n_effects, np.inf)])


@dataclass(frozen=True)
class _Watch:
    """Checks every accepted LM iterate of one run for free parameters that ran away
    (non-finite, or moved beyond credibility) or whose column collapsed."""

    names: tuple[str, ...]  # (k,) free parameter names
    index: NDArray[np.intp]  # (k,) their positions in the full vector
    x_start: FloatArray  # (k,) at the start point
    max_move: FloatArray  # (k,)
    start_rms: FloatArray  # (k,) column RMS of this run's weighted Jacobian at the start

    def __call__(self, nit: int, x: FloatArray, f: FloatArray, j: FloatArray) -> None:
        why = self.reasons(nit, x, j)
        if not why and not np.all(np.isfinite(f)):
            raise IdentificationError(f"the residuals are not finite at iteration {nit}")
        if why:
            raise _RunAway({int(self.index[i]): r for i, r in why.items()})

    def reasons(self, nit: int, x: FloatArray, j: FloatArray) -> dict[int, str]:
        """Free position -> why it must go, for the iterate ``x`` ``(k,)`` with the
        weighted Jacobian ``j`` ``(3m, k)``."""
        why: dict[int, str] = {}
        bad = ~np.isfinite(x) | ~np.all(np.isfinite(j), axis=0)
        for i in np.flatnonzero(bad).tolist():
            why[i] = f"{RAN_AWAY} (non-finite value or column at iteration {nit})"
        move = np.abs(x - self.x_start)
        for i in np.flatnonzero(move > self.max_move).tolist():
            why.setdefault(i, _moved(self.names[i], move[i], self.max_move[i], nit))
        ratio = column_rms(j) / self.start_rms
        for i in np.flatnonzero(ratio < COLLAPSE_RATIO).tolist():
            why.setdefault(
                i,
                f"{COLLAPSED} (its column fell to {ratio[i]:.1e} of its start RMS by "
                f"iteration {nit})",
            )
        return why


def _moved(name: str, move: float, limit: float, nit: int) -> str:
    if name.endswith("_rad"):
        return (
            f"{RAN_AWAY} (moved {math.degrees(move):.3g}° from its start by iteration "
            f"{nit}, beyond ±180°)"
        )
    return (
        f"{RAN_AWAY} (moved {move:.4g} mm from its start by iteration {nit}, beyond {limit:.0f} mm)"
    )


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
    robust loss; raises :class:`_RunAway` through the watch."""
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
        watch = _Watch(
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
        except _RunAway as exc:
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
    settings: LMSettings = LMSettings(),
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
    final = _full_vector(done.result.x, problem.x_start, analysis.free_indices)
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
