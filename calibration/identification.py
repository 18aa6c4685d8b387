"""Kinematic parameter identification from tracker TCP points: Levenberg-Marquardt.

The method of the primary source (docs/identification.md): linearize the TCP position error
``ΔP = J·ΔX`` with the analytic identification Jacobian, stack all poses and iterate

    ΔX_k = −(JᵀJ + μ_k I)⁻¹ Jᵀ ΔP(X_k),   X_{k+1} = X_k + ΔX_k,

raising the damping μ when the error norm grows (the step is then rejected) and lowering it
when it falls, and stop when successive error norms differ by at most ``tol_mm`` (1e-4). The
iteration runs on the identifiable parameters only (see :mod:`calibration.identifiability`),
in column-scaled units so that one μ suits mm and rad alike.

Non-geometric effect terms (the closed loop's, :mod:`calibration.closed_loop`) join the
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

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import OptimizeResult
from scipy.stats import chi2

from calibration.errors import CalibrationError
from calibration.identifiability import (
    DEFAULT_RTOL,
    IdentifiabilityAnalysis,
    analyze_identifiability,
    default_priority,
)
from calibration.kinematics import (
    KinematicModel,
    identification_jacobian,
    tcp_positions,
)
from calibration.registration import rigid_registration

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
    -1: "the step could not reduce the error: damping limit reached",
    0: "the maximum number of iterations was reached",
    1: "change of the error norm <= tol_mm",
    2: "the error norm is zero",
}

#: Two-sided probability beyond which a pose's 3-D residual marks it as an outlier.
OUTLIER_PROBABILITY = 1e-3


class IdentificationError(CalibrationError, ValueError):
    """The identification cannot run: too few poses, bad shapes, unknown option."""


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
def levenberg_marquardt(
    fun: Callable[..., FloatArray],
    jac: Callable[..., FloatArray],
    x0: ArrayLike,
    *,
    args: tuple[object, ...] = (),
    x_scale: ArrayLike | None = None,
    settings: LMSettings = LMSettings(),
    progress: ProgressCallback | None = None,
) -> OptimizeResult:
    """Minimize ``½‖fun(x, *args)‖²`` by the source's Levenberg-Marquardt iteration.

    ``x_scale`` (k,) gives the characteristic size of each variable; the damping acts on
    ``x / x_scale``. Returns a :class:`scipy.optimize.OptimizeResult` with x, cost, fun,
    jac, grad, optimality, nfev, njev, nit, status, message, success and ``mu``.
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
    if progress is not None:
        progress(0, norm, mu)
    for nit in range(1, settings.max_iterations + 1):
        if norm == 0.0:
            status = 2
            break
        js = j * scale
        a = js.T @ js
        g = js.T @ f
        accepted = False
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
                accepted = True
                mu = max(mu * settings.decrease, 1e-12)
                break
            if norm_new - norm <= settings.tol_mm:
                break  # at the minimum: a step changes the error norm by <= tol_mm
            mu *= settings.increase
        if not accepted:
            status = 1 if norm_new - norm <= settings.tol_mm else -1
            break
        change = norm - norm_new
        x, f, norm = x_new, f_new, norm_new
        j = jac(x, *args)
        njev += 1
        if progress is not None:
            progress(nit, norm, mu)
        if change <= settings.tol_mm:
            status = 1
            break
    grad = j.T @ f
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
        success=status > 0,
    )


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
    return 1e-3 * (mpe_um + mpe_um_per_m * d_m) / mpe_sigmas


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
        """Standard errors, full vector (mm, rad); NaN for dropped parameters."""
        se = np.full(len(self.parameter_names), np.nan)
        se[self.free] = np.sqrt(np.diag(self.covariance))
        return se

    def residuals_mm(self, q_rad: ArrayLike, measured_mm: ArrayLike) -> FloatArray:
        """Errors ``tracker − twin`` ``(N, 3)`` mm of the identified *geometric* model
        (effect terms need their own per-pose data: see :mod:`calibration.closed_loop`)."""
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
    """
    started = time.perf_counter()
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    meas = np.atleast_2d(np.asarray(measured_mm, dtype=float))
    if q.ndim != 2 or q.shape[1] != nominal.n_joints:
        raise IdentificationError(f"joint array must be (m, {nominal.n_joints}), got {q.shape}")
    if meas.shape != (len(q), 3):
        raise IdentificationError(f"points must be ({len(q)}, 3), got {meas.shape}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(meas))):
        raise IdentificationError("joint angles and points must be finite")
    if loss not in LOSSES:
        raise IdentificationError(f"unknown loss {loss!r} (valid: {', '.join(LOSSES)})")
    start = start or "description"
    if start not in START_METHODS:
        raise IdentificationError(f"unknown start {start!r} (valid: {', '.join(START_METHODS)})")
    names = nominal.parameter_names()
    p_geo = len(names)
    if effects is not None:
        names = names + list(effects.names)
    unknown = [f for f in fixed if f not in names]
    if unknown:
        raise IdentificationError(f"unknown parameter(s) to fix: {', '.join(unknown)}")
    if len(q) < 4:
        raise IdentificationError(f"need at least 4 poses, got {len(q)}")
    prior = np.ones(len(q))
    reference_sigma = None
    if point_sigma_mm is not None:
        ps = np.broadcast_to(np.asarray(point_sigma_mm, dtype=float), (len(q),))
        if not np.all(np.isfinite(ps) & (ps > 0)):
            raise IdentificationError("point sigmas must be finite and positive")
        reference_sigma = float(1.0 / np.sqrt(np.mean(1.0 / ps**2)))
        prior = (reference_sigma / ps) ** 2  # mean 1

    start_model = (
        base_start_from_registration(nominal, q, meas) if start == "registration" else nominal
    )
    jac0 = stacked_jacobian(start_model, q, effects)
    analysis = analyze_identifiability(
        jac0,
        names,
        priority=default_priority(nominal) + list(range(p_geo, len(names))),
        rtol=rtol,
        fixed=[names.index(f) for f in fixed],
    )
    free_idx = analysis.free_indices
    k = len(free_idx)
    if 3 * len(q) <= k:
        raise IdentificationError(
            f"{len(q)} poses give {3 * len(q)} equations for {k} identifiable parameters"
        )
    x_full = start_model.parameter_vector()
    if effects is not None:
        x_full = np.concatenate([x_full, effects.start_vector()])
    x_scale = 1.0 / analysis.column_scale[free_idx]

    weights = np.ones(len(q))
    history: list[tuple[int, float, float]] = []

    def record(it: int, norm: float, mu: float) -> None:
        history.append((it, norm, mu))
        if progress is not None:
            progress(it, norm, mu)

    x = x_full[free_idx]
    sw_last = np.ones(len(q))
    result: OptimizeResult | None = None
    scale_used = f_scale_mm
    irls = 0
    while irls < (max_irls if loss != "linear" else 1):
        irls += 1
        sw = np.sqrt(prior * weights)
        args = (x_full, free_idx, nominal, q, meas, sw, effects)
        result = levenberg_marquardt(
            position_residuals,
            position_residual_jacobian,
            x,
            args=args,
            x_scale=x_scale,
            settings=settings,
            progress=record,
        )
        x = result.x
        sw_last = sw
        if loss == "linear":
            break
        # 3-D residuals in units of the reference σ's pose (prior-weighted, not robust)
        dist = np.linalg.norm(result.fun.reshape(-1, 3), axis=1) / np.sqrt(
            np.maximum(weights, 1e-300)
        )
        if f_scale_mm is None:
            # 3 σ per axis, σ from the median 3-D distance (median of Maxwell = 1.538 σ)
            scale_used = 3.0 * float(np.median(dist)) / 1.538
        new_w = LOSSES[loss](dist / max(scale_used or 1e-12, 1e-12))
        if np.max(np.abs(new_w - weights)) < 1e-3:
            weights = new_w
            break
        weights = new_w
    assert result is not None

    final = _full_vector(x, x_full, free_idx)
    model = nominal.with_parameters(final[:p_geo])
    effect_values = final[p_geo:]
    sw = np.sqrt(prior * weights)
    resid = predicted_points(model, q, effects, effect_values) - meas
    # the solver's last Jacobian is at x, weighted with the weights of its last run
    jw = result.jac * (sw / np.maximum(sw_last, 1e-300)).repeat(3)[:, None]
    dof = max(3 * len(q) - k, 1)
    wsum = float(np.sum((resid * sw[:, None]) ** 2))
    sigma2 = wsum / dof * len(q) / max(float(np.sum(weights)), 1e-300)
    js = jw / analysis.column_scale[free_idx]
    cov_s = np.linalg.pinv(js.T @ js)
    d = 1.0 / analysis.column_scale[free_idx]
    covariance = sigma2 * cov_s * np.outer(d, d)
    sigma = math.sqrt(sigma2)
    dist = np.linalg.norm(resid, axis=1) * np.sqrt(prior)
    # robust per-axis σ for the outlier test: the median of a Maxwell distance is 1.538 σ,
    # and fitted residuals are smaller than the noise by √(1 − k/3m) on average
    robust_sigma = float(np.median(dist)) / 1.538 / math.sqrt(max(1.0 - k / (3 * len(q)), 0.1))
    threshold = robust_sigma * math.sqrt(chi2.ppf(1.0 - OUTLIER_PROBABILITY, 3))
    return IdentificationResult(
        model=model,
        start_model=start_model,
        start_method=start,
        identifiability=analysis,
        covariance=covariance,
        sigma_mm=sigma,
        pose_weights=weights,
        outliers=dist > threshold,
        loss=loss,
        f_scale_mm=scale_used if loss != "linear" else None,
        optimize_result=result,
        elapsed_s=time.perf_counter() - started,
        irls_iterations=irls,
        history=history,
        reference_sigma_mm=reference_sigma,
        effects=effects,
        effect_values=effect_values,
    )
