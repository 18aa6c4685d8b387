"""Recursive Levenberg-Marquardt with a variable forgetting factor, for online updating.

As tracker points stream in, each new pose updates the identified parameters without
re-solving the batch problem (method.md section 3, second source). With H the scaled
identification Jacobian of the pose (3 × k, identifiable parameters only), e the a-priori
error (tracker − twin) and σ the per-axis noise:

    ν̄(t) = 0.9·ν̄(t−1) + 0.1·‖e‖² / (3σ²)                     smoothed normalized error
    μ(t) = λ_min + (λ_max − λ_min)·exp(−max(ν̄(t) − 1, 0) / κ)  ∈ [λ_min, λ_max]
    λ(t) = λ0·λ(t−1) + μ(t)·(1 − λ0)                           λ0 = 0.99 (the source's)
    R(t) = λ(t)·R(t−1) + HᵀH/σ² + (1 − λ(t))·ρ·I
    x(t) = x(t−1) + R(t)⁻¹·Hᵀe/σ²

While errors match the noise, μ → λ_max and the memory is long (1/(1 − λ_max) poses); when
the model starts to drift, the errors grow, μ falls and old poses are forgotten faster. The
ρ·I term is the Levenberg-Marquardt damping of the recursive form: it keeps a floor of
information in directions the recent poses do not excite, so forgetting cannot blow up the
step there ("covariance wind-up").

The estimator state is an immutable value: :func:`recursive_update` returns a new state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import RecursiveIdentificationError
from calibration.identify.identification import IdentificationResult
from calibration.model.kinematics import KinematicModel, identification_jacobian

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ForgettingSettings:
    """Variable forgetting factor and damping of the recursive LM."""

    lambda0: float = 0.99  # the source's λ0 in λ(t) = λ0·λ(t−1) + μ(t)(1 − λ0)
    lambda_min: float = 0.95  # memory of ~20 poses while the model is drifting
    lambda_max: float = 0.998  # memory of ~500 poses while it matches the data
    kappa: float = 1.0  # how fast μ falls as the normalized error exceeds 1
    smoothing: float = 0.9  # of the normalized error ν̄
    damping: float = 1.0  # ρ, information floor per scaled parameter (1/σ² units)

    def __post_init__(self) -> None:
        if not 0.0 < self.lambda0 < 1.0:
            raise RecursiveIdentificationError("lambda0 must be in (0, 1)")
        if not 0.0 < self.lambda_min <= self.lambda_max <= 1.0:
            raise RecursiveIdentificationError("need 0 < lambda_min <= lambda_max <= 1")


@dataclass(frozen=True)
class RecursiveState:
    """The recursive estimator after t poses (immutable)."""

    template: KinematicModel  # carries the joint count; parameters come from x
    x: FloatArray  # (p,) full parameter vector (mm, rad)
    free_idx: NDArray[np.intp]  # (k,) identified parameters
    column_scale: FloatArray  # (k,) scaling: scaled parameter = x · column_scale
    information: FloatArray  # (k, k) R(t) in scaled units
    sigma_mm: float  # per-axis measurement noise
    forgetting: float  # λ(t)
    normalized_error: float  # ν̄(t)
    t: int = 0  # poses processed

    @property
    def model(self) -> KinematicModel:
        return self.template.with_parameters(self.x)

    def covariance(self) -> FloatArray:
        """Covariance ``(k, k)`` of the identified parameters (mm, rad) from R(t)."""
        inv = np.linalg.inv(self.information)
        d = 1.0 / self.column_scale
        return inv * np.outer(d, d)


@dataclass(frozen=True)
class RecursiveStep:
    """What one update saw: the a-priori error (mm), μ(t) and λ(t)."""

    error_mm: FloatArray  # (3,) tracker − twin before the update
    mu: float
    forgetting: float


def start_recursive(
    result: IdentificationResult, settings: ForgettingSettings = ForgettingSettings()
) -> RecursiveState:
    """Start from a batch identification: its estimate, free set and information."""
    free_idx = result.identifiability.free_indices
    scale = result.identifiability.column_scale[free_idx]
    cov_scaled = result.covariance * np.outer(scale, scale)
    return RecursiveState(
        template=result.model,
        x=result.model.parameter_vector(),
        free_idx=free_idx,
        column_scale=scale,
        # numpy's stubs type inv() of a float64 array as floating[Any]
        information=cast(FloatArray, np.linalg.inv(cov_scaled)),
        sigma_mm=result.sigma_mm,
        forgetting=settings.lambda_max,
        normalized_error=1.0,
    )


def recursive_update(
    state: RecursiveState,
    q_rad: ArrayLike,
    measured_mm: ArrayLike,
    settings: ForgettingSettings = ForgettingSettings(),
) -> tuple[RecursiveState, RecursiveStep]:
    """One pose ``q`` ``(n,)`` rad with its tracker point ``(3,)`` mm: the new state."""
    q = np.asarray(q_rad, dtype=float)
    meas = np.asarray(measured_mm, dtype=float)
    if q.shape != (state.template.n_joints,) or meas.shape != (3,):
        raise RecursiveIdentificationError(
            f"need q of shape ({state.template.n_joints},) and a point of shape (3,)"
        )
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(meas))):
        raise RecursiveIdentificationError("joint angles and point must be finite")
    pred, jac = identification_jacobian(state.model, q)
    h = jac[:, state.free_idx] / state.column_scale  # (3, k) scaled
    err = meas - pred
    lm = forgetting_step(
        state.information,
        state.forgetting,
        state.normalized_error,
        h,
        err,
        state.sigma_mm,
        settings,
    )
    x = state.x.copy()
    x[state.free_idx] += lm.step_scaled / state.column_scale
    new = replace(
        state,
        x=x,
        information=lm.information,
        forgetting=lm.forgetting,
        normalized_error=lm.normalized_error,
        t=state.t + 1,
    )
    return new, RecursiveStep(error_mm=err, mu=lm.mu, forgetting=lm.forgetting)


@dataclass(frozen=True)
class ForgettingStep:
    """One step of the recursive LM in scaled units: R(t), the step, ν̄(t), μ(t), λ(t)."""

    information: FloatArray  # (k, k)
    step_scaled: FloatArray  # (k,)
    normalized_error: float
    mu: float
    forgetting: float


def forgetting_step(
    information: FloatArray,
    forgetting: float,
    normalized_error: float,
    h_scaled: FloatArray,
    error_mm: FloatArray,
    sigma_mm: float,
    settings: ForgettingSettings = ForgettingSettings(),
) -> ForgettingStep:
    """The module's equations for one point: ``h_scaled`` ``(3, k)``, the a-priori error
    ``(3,)`` mm, R(t−1) ``(k, k)``, λ(t−1) and ν̄(t−1) -> R(t), the step, ν̄, μ, λ.

    Shared by :func:`recursive_update` and the tracker (:mod:`calibration.twin.tracking`)."""
    err = error_mm
    s2 = sigma_mm**2
    nu = settings.smoothing * normalized_error + (1.0 - settings.smoothing) * float(err @ err) / (
        3.0 * s2
    )
    span = settings.lambda_max - settings.lambda_min
    mu = settings.lambda_min + span * math.exp(-max(nu - 1.0, 0.0) / settings.kappa)
    lam = settings.lambda0 * forgetting + mu * (1.0 - settings.lambda0)
    k = information.shape[0]
    h = h_scaled
    info = lam * information + (h.T @ h) / s2 + (1.0 - lam) * settings.damping * np.eye(k)
    # numpy's stubs type solve() of float64 arrays as floating[Any]
    step_scaled = cast(FloatArray, np.linalg.solve(info, h.T @ err / s2))
    return ForgettingStep(info, step_scaled, nu, mu, lam)


@dataclass(frozen=True)
class RecursiveTrack:
    """A streamed run: the final state and per-pose histories."""

    state: RecursiveState
    x_history: FloatArray  # (T, p) parameters after each pose
    error_mm: FloatArray  # (T, 3) a-priori errors
    forgetting: FloatArray  # (T,) λ(t)
    mu: FloatArray  # (T,) μ(t)


def track(
    start: RecursiveState,
    q_rad: ArrayLike,
    measured_mm: ArrayLike,
    settings: ForgettingSettings = ForgettingSettings(),
) -> RecursiveTrack:
    """Stream poses ``(T, n)`` rad and points ``(T, 3)`` mm through :func:`recursive_update`."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    pts = np.atleast_2d(np.asarray(measured_mm, dtype=float))
    if len(q) != len(pts):
        raise RecursiveIdentificationError(f"{len(q)} joint vectors but {len(pts)} points")
    state = start
    xs, errs, lams, mus = [], [], [], []
    for qi, pi in zip(q, pts, strict=True):
        state, step = recursive_update(state, qi, pi, settings)
        xs.append(state.x)
        errs.append(step.error_mm)
        lams.append(step.forgetting)
        mus.append(step.mu)
    return RecursiveTrack(
        state=state,
        x_history=np.array(xs).reshape(len(q), -1),
        error_mm=np.array(errs).reshape(len(q), 3),
        forgetting=np.array(lams),
        mu=np.array(mus),
    )
