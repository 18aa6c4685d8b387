"""The twin following the robot: a recursive fit of a few parameters to production checks.

Each check (a pose's joints ``q``, its time and the tracker's point) is first predicted
from everything before it (a priori), then learned from. The tracked parameters ``θ``
``(k,)`` move the calibrated parameter vector along a basis, ``x = x_cal + B·θ``: a native
parameter (``base.x_mm``) is a unit column, a link group's length scale
(``joint3.length_scale``) the column of that joint's ``a`` and ``d`` (θ the fractional
growth). The update is the recursive Levenberg-Marquardt of
:mod:`calibration.identify.recursive_identification` (variable forgetting factor, damping floor)
in columns scaled to mm at the TCP.

**Steps.** A CUSUM on the a-priori errors: with ``S = σ²I + H·R⁻¹·Hᵀ`` the predicted
error covariance and ``NIS = eᵀS⁻¹e`` (χ²₃ while the model holds), taken relative to the
recent error level ``L`` (an EWMA of NIS/3, at least 1: a tracker lagging a fast warm-up
is no step), the log-likelihood ratio of an error variance ``ρ_v`` times larger is
``ℓ = ½(1 − 1/ρ_v)·NIS/L − (3/2)·ln ρ_v``, capped at ``cap·h`` so one wild point cannot
decide alone;
``g(t) = max(0, g(t−1) + ℓ)`` and a step is declared when ``g > h``. A capped
(suspect) point is held, not learned from: confirmed by the next point, it is learned
after the memory reopens; otherwise it is dropped as an outlier. On a step the
information is multiplied by ``reopen`` and λ set to λ_min: the estimator forgets the
old robot. The test and its false-alarm rate: :mod:`calibration.twin.step_test`
(docs/tracking.md).

**Alarm.** The tracked model's TCP at the campaign's validation poses, against the
calibrated model's, linearised: ``max_r ‖J_r·B·θ‖ > alarm_mm``.

Everything here is a pure function of values: :func:`track_update` takes a state and one
check and returns the next state (the live twin can call it per dwell).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import OptionError, TrackingError
from calibration.identify.recursive_identification import ForgettingSettings, forgetting_step
from calibration.model.description import RobotDescription, TrackingDescription
from calibration.model.kinematics import KinematicModel, identification_jacobian
from calibration.model.point_jacobian import point_jacobian
from calibration.twin.step_test import StepTest

FloatArray = NDArray[np.float64]

STATES = ("following", "step", "alarm")
State = Literal["following", "step", "alarm"]

#: A link whose lengths (|a| + |d|) are at least this share of the arm's gets a scale.
LINK_SHARE = 0.1
SCALE_SUFFIX = ".length_scale"


@dataclass(frozen=True)
class TrackingSettings:
    """The tracker's forgetting, damping, step test and alarm (None: no alarm)."""

    forgetting: ForgettingSettings = field(
        default_factory=lambda: ForgettingSettings(
            lambda0=0.9, lambda_min=0.9, lambda_max=0.99, kappa=1.0, smoothing=0.8, damping=25.0
        )
    )
    step: StepTest = field(default_factory=StepTest)
    alarm_mm: float | None = None
    #: the campaign's information about θ kept at the start: the robot moves from the
    #: moment production starts, and all of it would hold the tracker back at warm-up
    prior_weight: float = 0.1


@dataclass(frozen=True)
class TrackingSetup:
    """What stays fixed while tracking: the calibrated geometry, the tracked parameters'
    basis and scaling, the prior information, the reference poses' Jacobian."""

    template: KinematicModel  # the calibrated geometry
    names: tuple[str, ...]  # (k,)
    basis: FloatArray  # (p, k): x = x_cal + basis @ θ
    column_scale: FloatArray  # (k,) mm at the TCP (RMS over the reference poses) per unit θ
    sigma_mm: float
    start_information: FloatArray  # (k, k) scaled, from the campaign's identification poses
    reference_jacobian: FloatArray  # (r, 3, k) TCP mm per unit θ at the validation poses
    settings: TrackingSettings = field(default_factory=TrackingSettings)

    @cached_property
    def x_calibrated(self) -> FloatArray:
        """The calibrated parameter vector ``(p,)`` (built once: every check uses it)."""
        return self.template.parameter_vector()

    def model(self, theta: ArrayLike) -> KinematicModel:
        """The geometry with tracked parameters ``θ`` ``(k,)``."""
        return self.template.with_parameters(self.x_calibrated + self.basis @ np.asarray(theta))

    def absolute(self, theta: ArrayLike) -> FloatArray:
        """Each tracked parameter's absolute value ``(k,)`` in the model's units (a length
        scale as 1 + growth)."""
        th = np.asarray(theta, dtype=float)
        out = np.empty(len(self.names))
        x = self.x_calibrated
        for i, name in enumerate(self.names):
            if name.endswith(SCALE_SUFFIX):
                out[i] = 1.0 + th[i]
            else:
                out[i] = x[int(np.flatnonzero(self.basis[:, i])[0])] + th[i]
        return out


@dataclass(frozen=True)
class PendingPoint:
    """A suspect check held until the next one says step or outlier."""

    q_rad: FloatArray
    measured_mm: FloatArray
    offset_mm: FloatArray
    row: int
    cusum_before: float = 0.0  # the CUSUM without it (restored when it proves an outlier)


@dataclass(frozen=True)
class TrackerState:
    """The tracker after some checks (immutable; :func:`track_update` returns a new one)."""

    theta: FloatArray  # (k,) tracked parameters relative to the calibrated model
    information: FloatArray  # (k, k) R(t), scaled
    forgetting: float  # λ(t)
    normalized_error: float  # ν̄(t)
    cusum: float = 0.0
    #: L(t), the recent a-priori error level: an EWMA of NIS/3 (1 while the model holds);
    #: the test looks for errors sudden against it, so a lag while drifting is no step
    error_level: float = 1.0
    onset_row: int | None = None  # where the CUSUM last left zero
    pending: PendingPoint | None = None
    settling: int = 0  # > 0: in the 'step' state, this many fitting points still wanted
    alarm: bool = False
    rows: int = 0

    def covariance(self, setup: TrackingSetup) -> FloatArray:
        """Covariance ``(k, k)`` of θ in its own units."""
        d = 1.0 / setup.column_scale
        cov: FloatArray = np.linalg.inv(self.information) * np.outer(d, d)
        return cov


@dataclass(frozen=True)
class TrackStep:
    """What one check saw: the a-priori prediction, its error, the state, and news."""

    predicted_mm: FloatArray  # (3,)
    error_mm: float
    nis: float
    state: State
    forgetting: float
    step_detected: bool = False
    onset_row: int | None = None  # the step's first row (the CUSUM's change point)
    displacement_mm: float = 0.0  # the tracked TCP's largest move at the reference poses


# -- setup ------------------------------------------------------------------------------
def scale_groups(model: KinematicModel, identified: tuple[str, ...]) -> dict[str, list[int]]:
    """Length-scale name -> its columns in the parameter vector: each joint whose lengths
    are at least :data:`LINK_SHARE` of the arm's and of which an ``a`` or ``d`` was
    identified (a length the campaign could not see cannot be scaled honestly)."""
    x = model.parameter_vector()
    length = np.abs(model.a_mm) + np.abs(model.d_mm)
    total = float(length.sum())
    groups: dict[str, list[int]] = {}
    for j in range(model.n_joints):
        cols = [
            5 * j + k
            for k, key in ((0, "a_mm"), (2, "d_mm"))
            if x[5 * j + k] != 0.0 and f"joint{j + 1}.{key}" in identified
        ]
        if cols and length[j] >= LINK_SHARE * total:
            groups[f"joint{j + 1}{SCALE_SUFFIX}"] = cols
    return groups


def trackable_names(model: KinematicModel, identified: tuple[str, ...]) -> list[str]:
    """Every name ``--params`` accepts: the identified geometric parameters and the
    length scales of :func:`scale_groups`."""
    return [*identified, *scale_groups(model, identified)]


def default_names(model: KinematicModel, identified: tuple[str, ...]) -> list[str]:
    """The default set: the identified base and tool parameters and the length scales."""
    native = [n for n in identified if n.startswith(("base.", "tool."))]
    return [*native, *scale_groups(model, identified)]


def tracking_setup(
    description: RobotDescription,
    names: list[str] | None = None,
    settings: TrackingSettings = TrackingSettings(),
) -> TrackingSetup:
    """The setup of a calibrated description carrying ``[tracking]``; ``names`` None: the
    default set. Unknown names raise :class:`OptionError` listing the valid ones."""
    tr = description.tracking
    if tr is None:
        raise TrackingError(
            "has no [tracking] table (the identified parameters and reference poses): "
            "calibrate it again with this version's twin identify or twin run"
        )
    model = KinematicModel.from_description(description)
    all_names = model.parameter_names()
    unknown = [n for n in tr.identified if n not in all_names]
    if unknown:
        raise TrackingError(f"[tracking]: key 'identified': {unknown[0]!r} is no model parameter")
    valid = trackable_names(model, tr.identified)
    chosen = default_names(model, tr.identified) if names is None else names
    for n in chosen:
        if n not in valid:
            raise OptionError(
                f"--params: {n!r} is not a tracked parameter of this model "
                f"(valid: {', '.join(valid)})"
            )
    if not chosen and names is None:
        raise TrackingError(
            "[tracking]: key 'identified': no identified base, tool or link length to track "
            "(name parameters with --params)"
        )
    if not chosen:
        raise OptionError("--params: no parameter to track")
    return _setup_of(model, tr, chosen, settings)


def _setup_of(
    model: KinematicModel,
    tr: TrackingDescription,
    chosen: list[str],
    settings: TrackingSettings,
) -> TrackingSetup:
    """The basis, column scales and start information of the chosen tracked parameters."""
    all_names = model.parameter_names()
    groups = scale_groups(model, tr.identified)
    x = model.parameter_vector()
    basis = np.zeros((len(x), len(chosen)))
    for i, n in enumerate(chosen):
        if n in groups:
            basis[groups[n], i] = x[groups[n]]
        else:
            basis[all_names.index(n), i] = 1.0
    ref = np.radians(np.asarray(tr.reference_deg, dtype=float))
    _, jac_ref = identification_jacobian(model, ref)
    ref_jac = jac_ref @ basis  # (r, 3, k)
    scale = np.sqrt(np.mean(ref_jac**2, axis=(0, 1)))
    scale = np.where(scale > 0.0, scale, 1.0)
    _, jac_id = identification_jacobian(model, np.radians(np.asarray(tr.identify_deg, float)))
    h = (jac_id @ basis / scale).reshape(-1, len(chosen))
    info = settings.prior_weight * (
        h.T @ h
    ) / tr.sigma_mm**2 + settings.forgetting.damping * np.eye(len(chosen))
    return TrackingSetup(
        template=model,
        names=tuple(chosen),
        basis=basis,
        column_scale=scale,
        sigma_mm=tr.sigma_mm,
        start_information=info,
        reference_jacobian=ref_jac,
        settings=settings,
    )


def start_tracking(setup: TrackingSetup) -> TrackerState:
    """The state before the first check: the calibrated model, the campaign's information."""
    return TrackerState(
        theta=np.zeros(len(setup.names)),
        information=setup.start_information,
        forgetting=setup.settings.forgetting.lambda_max,
        normalized_error=1.0,
    )


# -- one check --------------------------------------------------------------------------
def _predict(
    setup: TrackingSetup, state: TrackerState, q_rad: FloatArray, offset_mm: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The a-priori point ``(3,)`` and the scaled Jacobian ``(3, k)`` of θ there."""
    p, jac = point_jacobian(setup.model(state.theta), q_rad)
    h: FloatArray = (jac @ setup.basis) / setup.column_scale
    return p + offset_mm, h


def _learn(
    setup: TrackingSetup,
    state: TrackerState,
    point: PendingPoint,
    seen: tuple[FloatArray, FloatArray] | None = None,
) -> TrackerState:
    """The recursive LM step with one point; ``seen``: its prediction and scaled Jacobian
    at ``state``'s θ when already computed (one Jacobian per check)."""
    pred, h = seen if seen is not None else _predict(setup, state, point.q_rad, point.offset_mm)
    lm = forgetting_step(
        state.information,
        state.forgetting,
        state.normalized_error,
        h,
        point.measured_mm - pred,
        setup.sigma_mm,
        setup.settings.forgetting,
    )
    return replace(
        state,
        theta=state.theta + lm.step_scaled / setup.column_scale,
        information=lm.information,
        forgetting=lm.forgetting,
        normalized_error=lm.normalized_error,
    )


def _reopened(setup: TrackingSetup, state: TrackerState) -> TrackerState:
    test = setup.settings.step
    k = len(setup.names)
    floor = setup.settings.forgetting.damping * np.eye(k)
    return replace(
        state,
        information=test.reopen * state.information + floor,
        forgetting=setup.settings.forgetting.lambda_min,
        normalized_error=1.0,
        cusum=0.0,
        error_level=1.0,
        settling=test.settle_rows,
    )


def track_update(
    setup: TrackingSetup,
    state: TrackerState,
    q_rad: ArrayLike,
    measured_mm: ArrayLike,
    offset_mm: ArrayLike = (0.0, 0.0, 0.0),
) -> tuple[TrackerState, TrackStep]:
    """One check: joints ``(n,)`` rad, the tracker's point ``(3,)`` mm, and the calibrated
    model's effect terms at this pose ``(3,)`` mm (:func:`effect_offsets`). Predicts
    first (from ``state`` only), then runs the step test and learns. Pure.

    Long because it is one function, not split: predict → test → learn → settle → alarm is
    the method's order, read top to bottom (the per-check hot path of the live twin too)."""
    q = np.asarray(q_rad, dtype=float)
    meas = np.asarray(measured_mm, dtype=float)
    off = np.asarray(offset_mm, dtype=float)
    if q.shape != (setup.template.n_joints,) or meas.shape != (3,) or off.shape != (3,):
        raise TrackingError(
            f"need q of shape ({setup.template.n_joints},) and points of shape (3,)"
        )
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(meas)) and np.all(np.isfinite(off))):
        raise TrackingError("joint angles and points must be finite")
    test = setup.settings.step
    pred, h = _predict(setup, state, q, off)
    err = meas - pred
    cov = setup.sigma_mm**2 * np.eye(3) + h @ np.linalg.solve(state.information, h.T)
    nis = float(err @ np.linalg.solve(cov, err))
    # while the reopened memory refills the test rests: the large errors of a model still
    # learning the new robot are no second step
    llr = test.llr(nis / max(state.error_level, 1.0)) if state.settling == 0 else -math.inf
    pending = state.pending
    suspect = llr >= test.suspect_llr
    base = state.cusum
    if pending is not None and not suspect:  # the held suspect was an outlier: its share goes
        base = pending.cusum_before
    cusum = max(0.0, base + llr)
    onset = state.onset_row if base > 0.0 else state.rows
    row = state.rows
    state = replace(state, cusum=cusum, onset_row=onset if cusum > 0.0 else None)
    detected = cusum > test.threshold
    point = PendingPoint(q, meas, off, row, base)
    if detected:
        state = _reopened(setup, replace(state, pending=None))
        if pending is not None:
            state = _learn(setup, state, pending)
        state = _learn(setup, state, point, None if pending is not None else (pred, h))
    elif suspect and pending is None:
        state = replace(state, pending=point)
    else:  # a held suspect not confirmed was an outlier: dropped
        state = _learn(setup, replace(state, pending=None), point, (pred, h))
    if not (detected or suspect):
        a = test.level_smoothing
        level = a * state.error_level + (1.0 - a) * min(nis / 3.0, test.level_max)
        state = replace(state, error_level=level)
    if not detected and state.settling > 0:
        settling = state.settling - 1 if nis < test.settle_nis else test.settle_rows
        state = replace(state, settling=settling)
    disp = float(np.max(np.linalg.norm(setup.reference_jacobian @ state.theta, axis=1)))
    alarm_mm = setup.settings.alarm_mm
    state = replace(state, alarm=alarm_mm is not None and disp > alarm_mm, rows=row + 1)
    label: State = "alarm" if state.alarm else ("step" if state.settling > 0 else "following")
    return state, TrackStep(
        predicted_mm=pred,
        error_mm=float(np.linalg.norm(err)),
        nis=nis,
        state=label,
        forgetting=state.forgetting,
        step_detected=detected,
        onset_row=onset if detected else None,
        displacement_mm=disp,
    )


# -- a whole file -----------------------------------------------------------------------
@dataclass(frozen=True)
class TrackingRun:
    """Every check of a run: predictions, errors, states, λ, parameters with their σ."""

    state: TrackerState  # after the last check
    predicted_mm: FloatArray  # (m, 3) a priori
    error_mm: FloatArray  # (m,)
    states: tuple[State, ...]
    forgetting: FloatArray  # (m,)
    theta: FloatArray  # (m, k) after each check, relative to the calibrated model
    absolute: FloatArray  # (m, k) the same as absolute values (TrackingSetup.absolute)
    theta_se: FloatArray  # (m, k) standard errors
    displacement_mm: FloatArray  # (m,)
    steps: tuple[tuple[int, int], ...]  # (detected row, onset row) per step


def track_checks(
    setup: TrackingSetup,
    q_rad: ArrayLike,
    measured_mm: ArrayLike,
    offsets_mm: ArrayLike,
    state: TrackerState | None = None,
) -> TrackingRun:
    """Checks ``(m, n)`` rad, ``(m, 3)`` mm, effect offsets ``(m, 3)`` mm, in time order,
    through :func:`track_update`."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    pts = np.atleast_2d(np.asarray(measured_mm, dtype=float))
    off = np.atleast_2d(np.asarray(offsets_mm, dtype=float))
    st = start_tracking(setup) if state is None else state
    m, k = len(q), len(setup.names)
    pred, err = np.empty((m, 3)), np.empty(m)
    lam, disp = np.empty(m), np.empty(m)
    theta, se = np.empty((m, k)), np.empty((m, k))
    labels: list[State] = []
    steps: list[tuple[int, int]] = []
    for i in range(m):
        st, step = track_update(setup, st, q[i], pts[i], off[i])
        pred[i], err[i], lam[i], disp[i] = (
            step.predicted_mm,
            step.error_mm,
            step.forgetting,
            (step.displacement_mm),
        )
        theta[i] = st.theta
        se[i] = np.sqrt(np.diag(st.covariance(setup)))
        labels.append(step.state)
        if step.step_detected:
            steps.append((i, i if step.onset_row is None else step.onset_row))
    absolute = np.array([setup.absolute(th) for th in theta]).reshape(m, k)
    return TrackingRun(st, pred, err, tuple(labels), lam, theta, absolute, se, disp, tuple(steps))


def static_errors_mm(
    setup: TrackingSetup, q_rad: ArrayLike, measured_mm: ArrayLike, offsets_mm: ArrayLike
) -> FloatArray:
    """The calibrated (static) model's error ``(m,)`` mm at every check."""
    from calibration.model.kinematics import tcp_positions

    pred = tcp_positions(setup.template, q_rad) + np.asarray(offsets_mm, dtype=float)
    out: FloatArray = np.linalg.norm(np.asarray(measured_mm, dtype=float) - pred, axis=1)
    return out


def window_refit_errors(
    setup: TrackingSetup,
    q_rad: ArrayLike,
    measured_mm: ArrayLike,
    offsets_mm: ArrayLike,
    window: int,
    breaks: ArrayLike = (),
) -> FloatArray:
    """A hindsight reference ``(m,)`` mm: each check predicted by a batch least-squares
    refit of the same parameters over the ``window`` checks before it, told the rows where
    the robot changed (``breaks``: a window never reaches back past one). Linearised at
    the calibrated model, with the tracker's damping as a ridge."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    pts = np.asarray(measured_mm, dtype=float)
    p0, jac = identification_jacobian(setup.template, q)
    h = (jac @ setup.basis) / setup.column_scale  # (m, 3, k)
    resid = pts - p0 - np.asarray(offsets_mm, dtype=float)  # (m, 3)
    k = len(setup.names)
    ridge = setup.settings.forgetting.damping * setup.sigma_mm**2 * np.eye(k)
    cuts = np.sort(np.asarray(breaks, dtype=int))
    out = np.empty(len(q))
    for i in range(len(q)):
        before = cuts[cuts <= i]
        lo = max(i - window, int(before[-1]) if before.size else 0)
        hw, rw = h[lo:i].reshape(-1, k), resid[lo:i].reshape(-1)
        theta = np.linalg.solve(hw.T @ hw + ridge, hw.T @ rw)
        out[i] = float(np.linalg.norm(resid[i] - h[i] @ theta))
    return out


def effect_offsets(
    description: RobotDescription,
    q_rad: ArrayLike,
    t_s: ArrayLike,
    temp_c: ArrayLike | None = None,
) -> FloatArray:
    """The calibrated description's effect terms ``(m, 3)`` mm at checks in time order
    (its prediction minus its geometry's, the learned residual stage included, as
    ``twin predict`` has it; at the checks' temperatures ``temp_c`` ``(m,)`` °C where
    given): held fixed while the geometry is tracked. Row k's uses rows up to k only (a
    lost-motion term's approach direction from row k − 1)."""
    from calibration.effects.model_effects import predict_tcp
    from calibration.model.kinematics import tcp_positions

    learned = description.residual is not None and description.residual.learned is not None
    if not description.effects and not learned:  # the geometry alone: nothing held
        return np.zeros((len(np.atleast_2d(q_rad)), 3))
    model = KinematicModel.from_description(description)
    predicted = predict_tcp(description, q_rad, t_s, temp_c=temp_c)
    out: FloatArray = predicted - tcp_positions(model, q_rad)
    return out
