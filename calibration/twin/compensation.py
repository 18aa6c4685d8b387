"""Accuracy compensation: the joint commands that put the calibrated robot's TCP on targets.

A robot program holds joint values computed with the nominal model (or taught); the
calibrated twin knows where the robot really goes for any joints, every modelled effect
included. :func:`compensate` inverts that: for each target position (tracker frame, mm)
it finds joints whose calibrated prediction is the target, keeping a tool orientation.

The orientation is the calibrated model's flange orientation at the programmed joints
(``q_programmed_deg``), or a stated one (``rpy_deg``: fixed-axis X-Y-Z in the tracker
frame). The solve is a Newton iteration over all targets at once, ``(m, 6, n)`` batched
least-squares solves (n joints): the position error comes from the full predictor
(:func:`calibration.effects.model_effects.predict_tcp`: geometry, base, tool and every effect),
the orientation error and the Jacobian from the calibrated geometry (the effects are
smooth and small against it: each step cuts the error by orders of magnitude). The start
is the programmed joints, or the calibrated model's inverse kinematics (the
shortest-travel branch) when only an orientation is given.

A process force on the tool (``force_n``) deflects the joints after their gratings
(:mod:`calibration.model.stiffness`, ``C·F``): the prediction the targets are met with then
includes it, so the compensated joints take it out. That needs the description's joint
stiffnesses (stated, or from a load test).

Assumption (docs/compensation.md): the controller servos on the grating angles, the
joint values of the calibration; a controller that servos on its motor encoders needs
the encoder-vs-grating relation in between.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.effect_kinds import split_values
from calibration.effects.model_effects import description_effects, predict_tcp
from calibration.errors import CompensationError, StiffnessError
from calibration.model.description import RobotDescription
from calibration.model.ik_results import JointLimits
from calibration.model.inverse_kinematics import flange_in_base, solve_ik
from calibration.model.kinematics import KinematicModel, flange_poses, geometric_jacobian
from calibration.model.numeric_ik import chosen_solution
from calibration.model.pieper_closed_form import has_spherical_approximation
from calibration.model.stiffness import force_deflection_mm, states_stiffness

FloatArray = NDArray[np.float64]

#: A target is reached when the calibrated prediction is this close (mm).
TOLERANCE_MM = 1e-6
MAX_ITERATIONS = 25


@dataclass(frozen=True)
class CompensationResult:
    """Per target (arrays over ``m`` targets).

    ``q_deg`` ``(m, n)``: the compensated joints (NaN where not ``ok``); ``residual_mm``
    ``(m,)``: calibrated prediction minus target, every effect applied; ``travel_deg``
    ``(m,)``: largest joint change from the programmed joints (NaN without them);
    ``branch`` ``(m,)``: the IK branch index (``-1``: started from the programmed joints);
    ``iterations`` ``(m,)``; ``ok`` ``(m,)`` and ``reason`` (why not, else ``""``);
    ``force_deflection_mm`` ``(m, 3)``: the process force's deflection at the compensated
    joints (None without a force).
    """

    q_deg: FloatArray
    residual_mm: FloatArray
    travel_deg: FloatArray
    branch: NDArray[np.int_]
    iterations: NDArray[np.int_]
    ok: NDArray[np.bool_]
    reason: tuple[str, ...]
    force_deflection_mm: FloatArray | None = None


def rotation_xyz(rpy_deg: ArrayLike) -> FloatArray:
    """Rotations ``(m, 3, 3)`` of fixed-axis X-Y-Z angles ``(m, 3)`` deg: ``Rz·Ry·Rx``."""
    a = np.radians(np.asarray(rpy_deg, dtype=float).reshape(-1, 3))
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones(len(a)), np.zeros(len(a))
    rx = np.stack([one, zero, zero, zero, c[:, 0], -s[:, 0], zero, s[:, 0], c[:, 0]], -1)
    ry = np.stack([c[:, 1], zero, s[:, 1], zero, one, zero, -s[:, 1], zero, c[:, 1]], -1)
    rz = np.stack([c[:, 2], -s[:, 2], zero, s[:, 2], c[:, 2], zero, zero, zero, one], -1)
    rot: FloatArray = rz.reshape(-1, 3, 3) @ ry.reshape(-1, 3, 3) @ rx.reshape(-1, 3, 3)
    return rot


def _rotation_error(r_target: FloatArray, r: FloatArray) -> FloatArray:
    """Rotation vectors ``(m, 3)`` taking ``r`` to ``r_target`` (small-angle exact enough
    for a Newton step; zero when equal)."""
    d = r_target @ np.swapaxes(r, -1, -2)
    return 0.5 * np.stack(
        [d[:, 2, 1] - d[:, 1, 2], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 0] - d[:, 0, 1]], -1
    )


def _limits(desc: RobotDescription) -> tuple[FloatArray, FloatArray]:
    lo = np.array([j.lower_deg for j in desc.joints], dtype=float)
    hi = np.array([j.upper_deg for j in desc.joints], dtype=float)
    return lo, hi


def compensate(
    description: RobotDescription,
    target_mm: ArrayLike,
    *,
    q_programmed_deg: ArrayLike | None = None,
    rpy_deg: ArrayLike | None = None,
    t_s: ArrayLike | None = None,
    force_n: ArrayLike | None = None,
    temp_c: ArrayLike | None = None,
    tol_mm: float = TOLERANCE_MM,
    max_iterations: int = MAX_ITERATIONS,
    skip_unreached: bool = False,
) -> CompensationResult:
    """Joints that put the calibrated ``description``'s TCP on ``target_mm`` ``(m, 3)``
    (tracker frame, mm), keeping the orientation of ``q_programmed_deg`` ``(m, n)`` or
    the stated ``rpy_deg`` ``(m, 3)``. ``t_s`` ``(m,)`` s and ``temp_c`` ``(m,)`` °C: for
    drift and temperature terms; ``force_n`` ``(m, 3)``: a process force on the tool (N,
    tracker frame).

    The targets are a program, in time order (``t_s``, else row order): a direction-
    dependent effect (lost motion) approaches each from the one before it. With
    ``skip_unreached`` the targets not reached are left out of that program and the rest
    solved again without them."""
    target = np.asarray(target_mm, dtype=float).reshape(-1, 3)
    m = len(target)
    if (q_programmed_deg is None) == (rpy_deg is None):
        raise CompensationError("give either the programmed joints or the orientation")
    if not np.all(np.isfinite(target)):
        raise CompensationError("target positions must be finite")
    force = _checked_force(description, force_n, m)
    model = KinematicModel.from_description(description)
    q_prog = None
    if q_programmed_deg is not None:
        q_prog = np.asarray(q_programmed_deg, dtype=float).reshape(m, description.n_joints)
        q, branch = np.radians(q_prog), np.full(m, -1)
        r_target = flange_poses(model, q)[:, :3, :3]
    else:
        r_target = rotation_xyz(np.asarray(rpy_deg, dtype=float).reshape(m, 3))
        q, branch = _ik_start(model, description, target, r_target)
    if not np.all(np.isfinite(q)) and q_prog is not None:
        raise CompensationError("programmed joints must be finite")
    times = None if t_s is None else np.asarray(t_s, dtype=float).reshape(m)
    predict = _Prediction(description, times, force, _checked_temperature(temp_c, m))
    iterations = _newton(model, predict, q, target, r_target, tol_mm, max_iterations)
    q_deg, residual, ok, reasons = _checked(description, predict, q, target, times, tol_mm)
    left_out = ~ok & np.all(np.isfinite(q), axis=1)
    if skip_unreached and left_out.any():
        # the program runs without them: the targets after one approach from another pose
        q[left_out] = np.nan
        iterations += _newton(model, predict, q, target, r_target, tol_mm, max_iterations)
        q_deg, residual, ok, again = _checked(description, predict, q, target, times, tol_mm)
        reasons = tuple(r if lo else a for r, a, lo in zip(reasons, again, left_out, strict=True))
    travel = np.max(np.abs(q_deg - q_prog), axis=1) if q_prog is not None else np.full(m, np.nan)
    deflection = None
    if force is not None:
        deflection = np.full((m, 3), np.nan)
        if ok.any():
            deflection[ok] = force_deflection_mm(description, q[ok], force[ok])
    q_deg[~ok] = np.nan
    return CompensationResult(q_deg, residual, travel, branch, iterations, ok, reasons, deflection)


def _checked(
    description: RobotDescription,
    predict: _Prediction,
    q: FloatArray,
    target: FloatArray,
    times: FloatArray | None,
    tol_mm: float,
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_], tuple[str, ...]]:
    """The solved joints ``q`` ``(m, n)`` rad checked in their sequence (rows with a finite
    ``q``): the joints in degrees, each target's residual (mm), whether it is reached within
    the limits, and why not."""
    q_deg = np.degrees(q)
    finite = np.all(np.isfinite(q_deg), axis=1)
    residual = np.full(len(q), np.nan)
    if finite.any():
        rows = np.flatnonzero(finite)
        residual[finite] = np.linalg.norm(predict(rows, q[finite]) - target[finite], axis=1)
    reasons, ok = _verdicts(q_deg, residual, finite, _limits(description), tol_mm)
    reasons = _lost_motion_reasons(description, q_deg, finite, times, ok, reasons)
    return q_deg, residual, ok, reasons


def _checked_temperature(temp_c: ArrayLike | None, m: int) -> FloatArray | None:
    """The temperatures ``(m,)`` °C (None without), finite."""
    temp = None if temp_c is None else np.asarray(temp_c, dtype=float).reshape(m)
    if temp is not None and not np.all(np.isfinite(temp)):
        raise CompensationError("temperatures must be finite")
    return temp


def _checked_force(
    description: RobotDescription, force_n: ArrayLike | None, m: int
) -> FloatArray | None:
    """The process forces ``(m, 3)`` N (None without), finite, and only on a model that
    states its joints' stiffness."""
    force = None if force_n is None else np.asarray(force_n, dtype=float).reshape(m, 3)
    if force is not None and not np.all(np.isfinite(force)):
        raise CompensationError("process forces must be finite")
    if force is not None and np.any(force) and not states_stiffness(description):
        raise StiffnessError(
            "a process force needs the joints' stiffness, and the model states none "
            "([[joint]] stiffness_nmm_per_rad; `twin stiffness --load-test` measures them)"
        )
    return force


def _ik_start(
    model: KinematicModel, description: RobotDescription, target: FloatArray, r_target: FloatArray
) -> tuple[FloatArray, NDArray[np.int_]]:
    """The nominal IK's chosen joints ``(m, n)`` rad for TCPs at ``target`` ``(m, 3)`` with
    the flange rotations ``r_target`` ``(m, 3, 3)``, and the branch of each (−1: none)."""
    m = len(target)
    pose = np.zeros((m, 4, 4))
    pose[:, :3, :3], pose[:, :3, 3], pose[:, 3, 3] = r_target, target, 1.0
    limits = JointLimits.from_description(description)
    if not has_spherical_approximation(model):  # no closed form to seed from: numeric
        rot, pos = flange_in_base(model, pose, "world", "tcp")
        sel = chosen_solution(model, rot, pos, limits)
        return sel.q_rad.copy(), sel.index
    ik = solve_ik(model, pose, frame="world", target="tcp", limits=limits, branches="chosen")
    return ik.chosen_rad.copy(), np.where(ik.selection.found, ik.selection.index, -1)


@dataclass(frozen=True)
class _Prediction:
    """Where the calibrated model puts the TCP ``(r, 3)`` mm for joints ``(r, n)`` rad of
    the rows ``rows`` of the problem: effects at their times, deflected by their force."""

    description: RobotDescription
    times: FloatArray | None  # (m,) s
    force: FloatArray | None  # (m, 3) N
    temp: FloatArray | None = None  # (m,) °C

    def __call__(self, rows: NDArray[np.intp], q_rad: FloatArray) -> FloatArray:
        times = None if self.times is None else self.times[rows]
        temp = None if self.temp is None else self.temp[rows]
        p = predict_tcp(self.description, q_rad, times, temp_c=temp)
        if self.force is not None:
            p = p + force_deflection_mm(self.description, q_rad, self.force[rows])
        return p


def _newton(
    model: KinematicModel,
    predict: Callable[[NDArray[np.intp], FloatArray], FloatArray],
    q: FloatArray,
    target: FloatArray,
    r_target: FloatArray,
    tol_mm: float,
    max_iterations: int,
) -> NDArray[np.int_]:
    """Newton steps on the joints ``q`` ``(m, n)`` rad in place, every unfinished target at
    once, until each predicted TCP is within ``tol_mm``; the iterations per target.

    Every target is predicted in the whole sequence, finished ones included: a lost-motion
    term takes each joint's approach direction from the target before it in the program,
    so predicting only the unfinished ones would give each a different predecessor (on a
    KR500 with 0.05° of lost motion that left ~15 % of targets 2-6 mm off)."""
    finite = np.flatnonzero(np.all(np.isfinite(q), axis=1))
    active = np.zeros(len(q), dtype=bool)
    active[finite] = True
    iterations = np.zeros(len(q), dtype=int)
    for _ in range(max_iterations):
        if not active.any():
            break
        in_finite = active[finite]
        idx = finite[in_finite]
        qa = q[idx]
        e_p = target[idx] - predict(finite, q[finite])[in_finite]
        e_r = _rotation_error(r_target[idx], flange_poses(model, qa)[:, :3, :3])
        done = np.linalg.norm(e_p, axis=1) < tol_mm
        active[idx[done]] = False
        step = ~done
        if not step.any():
            break
        jac = geometric_jacobian(model, qa[step], point="tcp", frame="world")
        rhs = np.concatenate([e_p[step], e_r[step]], axis=1)[..., None]
        q[idx[step]] = qa[step] + _solve(jac, rhs)[..., 0]
        iterations[idx[step]] += 1
    return iterations


def _verdicts(
    q_deg: FloatArray,
    residual: FloatArray,
    finite: NDArray[np.bool_],
    limits: tuple[FloatArray, FloatArray],
    tol_mm: float,
) -> tuple[tuple[str, ...], NDArray[np.bool_]]:
    """Per target: why it is refused (``""`` when reached within the limits) and ``ok``."""
    lo, hi = limits
    reasons: list[str] = []
    ok = np.zeros(len(q_deg), dtype=bool)
    for i in range(len(q_deg)):
        if not finite[i]:
            reasons.append("unreachable: no inverse-kinematics solution within the limits")
        elif not residual[i] < max(10 * tol_mm, 1e-4):
            reasons.append(f"unreachable: the solve ends {residual[i]:.3g} mm from the target")
        else:
            out = np.flatnonzero((q_deg[i] < lo - 1e-9) | (q_deg[i] > hi + 1e-9))
            if out.size:
                k = int(out[0])
                reasons.append(
                    f"joint {k + 1} would be at {q_deg[i, k]:.3f}°, outside its limits "
                    f"[{lo[k]:g}, {hi[k]:g}]°"
                )
            else:
                reasons.append("")
                ok[i] = True
    return tuple(reasons), ok


def _lost_motion_reasons(
    description: RobotDescription,
    q_deg: FloatArray,
    finite: NDArray[np.bool_],
    times: FloatArray | None,
    ok: NDArray[np.bool_],
    reasons: tuple[str, ...],
) -> tuple[str, ...]:
    """``reasons`` with a target the solve missed explained by lost motion where it is one:
    a joint standing off by ``h`` in its direction of motion cannot end within ``h`` of
    where the move starts (moving up it ends above ``p + h``, down below ``p − h``), so a
    target that close to the one before it on that joint has no direct move."""
    specs, values = description_effects(description)
    half = {
        s.joint: abs(float(v[0]))
        for s, v in zip(specs, split_values(specs, values), strict=True)
        if s.kind == "lost_motion"
    }
    rows = np.flatnonzero(finite)
    if not half or rows.size == 0:
        return reasons
    if times is not None:
        rows = rows[np.argsort(times[rows], kind="stable")]
    start = np.asarray(description.home, dtype=float)
    before = dict(zip(rows.tolist(), [start, *q_deg[rows[:-1]]], strict=True))
    out = list(reasons)
    for i in np.flatnonzero(~ok & finite).tolist():
        if not out[i].startswith("unreachable: the solve ends"):
            continue
        moves = {j: abs(q_deg[i, j - 1] - before[i][j - 1]) for j in sorted(half)}
        close = [j for j, move in moves.items() if move < 2 * half[j]]
        if close:
            j = close[0]
            out[i] = (
                f"unreachable from the target before it: joint {j} would move "
                f"{moves[j]:.3g}°, inside its lost motion (half-width {half[j]:.3g}°); "
                "approach it from one side (a via pose before it)"
            )
    return tuple(out)


def _solve(jac: FloatArray, rhs: FloatArray) -> FloatArray:
    """Least-squares steps ``(k, n, 1)`` of ``(k, 6, n)`` Jacobians (damped near a
    singularity so a step never explodes)."""
    jt = np.swapaxes(jac, 1, 2)
    jtj = jt @ jac
    damping = 1e-9 * np.trace(jtj, axis1=1, axis2=2)[:, None, None] * np.eye(jac.shape[2])
    return np.linalg.solve(jtj + damping, jt @ rhs)
