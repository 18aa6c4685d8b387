"""Inverse kinematics of spherical-wrist 6R arms: closed form (Pieper), numeric polish.

Conventions are those of :mod:`calibration.model.kinematics` (modified D-H with Hayati beta,
radians and mm). A target is a flange pose, or a TCP pose (the tracker target's position
with the flange orientation; the tool offset is removed here), given in the robot *base*
frame or in the *world* (tracker) frame through the model's base pose.

Every call returns all eight branches of the arm, one row per branch, in the order of
:data:`BRANCHES` (shoulder, elbow, wrist signs; index ``4·s + 2·e + w`` with 0 = "+"):

* shoulder: the wrist centre in front of (+) or behind (−) axis 1, i.e. the sign of its
  distance from axis 1 along the arm plane's x axis (``a2`` side);
* elbow: the sign of sin(psi), psi the angle from the upper arm to the forearm
  (0 = stretched, ±π = folded);
* wrist: the sign of sin(q5 + offset5); the flip is q4 + π, −q5, q6 + π.

The closed form needs a *Pieper* geometry (:func:`is_spherical_wrist`): joints 2 and 3
parallel (alpha3 = 0), alpha 2, 4, 5, 6 = ±90°, a5 = a6 = d5 = 0 (the wrist axes meet in
one point) and every beta = 0, as in the shipped presets; a lateral offset d2 + d3 is
allowed. It reproduces the pose to about 1e-11 mm and 1e-14 rad.

A calibrated model is not exactly spherical. For it the closed form of its nominal
geometry (:func:`spherical_approximation`, or an explicit ``nominal`` model) seeds a
Levenberg-Marquardt solve on the calibrated model's geometric Jacobian (plain Newton
unless a step fails to reduce the error). With millimetre / tenth-of-a-degree deviations
from nominal, typically 3 Jacobian evaluations reach the default tolerance of 1e-9 mm and
1e-11 rad; each solution's residual is reported. Inside the singularity margins a branch
may converge slowly or not at all, and is then reported unreachable.

Solutions are then mapped, joint by joint, to the 2π-equivalent inside the joint limits
that is nearest a reference joint vector (the current one when known, else zero): a
joint whose range spans more than 360° can take q ± 2π. :func:`select_solution` applies
the shortest-travel rule of the method (within limits, away from singularities, least
weighted travel, the wrist moving rather than the main axes).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import KinematicsError
from calibration.model.description import RobotDescription
from calibration.model.kinematics import (
    FloatArray,
    KinematicModel,
    flange_poses,
    geometric_jacobian,
    rot_x,
)

BoolArray = NDArray[np.bool_]

N_BRANCHES = 8
BRANCH_SIGNS: NDArray[np.int_] = np.array(
    [[s, e, w] for s in (1, -1) for e in (1, -1) for w in (1, -1)], dtype=int
)
"""Signs (shoulder, elbow, wrist) of each branch, shape ``(8, 3)``."""
BRANCHES: tuple[str, ...] = tuple(
    "shoulder{} elbow{} wrist{}".format(*("+" if v > 0 else "-" for v in row))
    for row in BRANCH_SIGNS
)

# Travel weights of the shortest-travel rule: the main axes move the arm's mass and swing
# the TCP by the whole reach, the wrist only by the flange distance, so a radian of a main
# axis costs more than a radian of the wrist.
DEFAULT_TRAVEL_WEIGHTS: tuple[float, ...] = (3.0, 3.0, 2.0, 1.0, 1.0, 1.0)

# Slack on the joint limits for values that round to just past a limit (rad).
LIMIT_SLACK_RAD = 1e-9
# A 2-vector shorter than this (unitless, the rows of a rotation matrix) has no direction:
# the wrist is exactly singular and q4 is taken from the reference vector.
_WRIST_DEGENERATE = 1e-12
# Wrist centre closer than this to axis 1 (mm) with no lateral offset: q1 from the reference.
_SHOULDER_DEGENERATE_MM = 1e-9
# Relative slack on the elbow's law-of-cosines argument before a pose counts unreachable.
_ELBOW_SLACK = 1e-12
# Seeding a calibrated model: the nominal law-of-cosines argument may exceed 1 by this much
# (a few mm beyond the nominal reach), the seed elbow stays 2° off stretched/folded and the
# seed wrist centre 1 mm off the shoulder-singular surface, so that branches stay apart.
_SEED_ELBOW_SLACK = 0.02
_SEED_SHOULDER_MM = 1.0
_SEED_ELBOW_COS = float(np.cos(np.radians(2.0)))
# With branches="chosen" the seeds are ranked allowing them this far past a joint limit.
_SEED_LIMIT_SLACK_RAD = float(np.radians(5.0))
# Smallest Levenberg damping, relative to the trace of the normal matrix: keeps the solve
# defined at an exact singularity without slowing Newton's convergence elsewhere.
_MU_MIN = 1e-12
# Damping after a rejected step: skip the useless decades between _MU_MIN and real damping.
_MU_REJECTED = 1e-6
# Length (mm) that makes one radian of orientation error weigh like this many mm.
_ORIENTATION_SCALE_MM = 1000.0
_ANGLE_TOL = 1e-9  # tolerance on the structural angles of a Pieper geometry (rad)


# -- small value types ------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class JointLimits:
    """Joint limits in rad, arrays of shape ``(n,)``; ``±inf`` means unlimited."""

    lower_rad: FloatArray
    upper_rad: FloatArray

    @classmethod
    def from_description(cls, desc: RobotDescription) -> JointLimits:
        return cls(
            lower_rad=np.radians([j.lower_deg for j in desc.joints]),
            upper_rad=np.radians([j.upper_deg for j in desc.joints]),
        )

    @classmethod
    def unlimited(cls, n_joints: int) -> JointLimits:
        return cls(np.full(n_joints, -np.inf), np.full(n_joints, np.inf))

    def contains(self, q_rad: ArrayLike, slack_rad: float = LIMIT_SLACK_RAD) -> BoolArray:
        """Whether each joint vector of ``q_rad`` (``(..., n)``) is within limits."""
        q = np.asarray(q_rad, dtype=float)
        inside = (q >= self.lower_rad - slack_rad) & (q <= self.upper_rad + slack_rad)
        ok: BoolArray = np.all(inside, axis=-1)
        return ok


@dataclass(frozen=True)
class SingularityMargins:
    """How close to a singularity a solution is flagged (and avoided by the selection).

    ``shoulder_mm``: wrist centre within this distance of the surface where the two
    shoulder branches meet (on axis 1 when there is no lateral offset);
    ``elbow_rad``: upper arm and forearm within this angle of stretched or folded;
    ``wrist_rad``: q5 within this angle of 0 (or ±180°), axes 4 and 6 aligned.
    """

    shoulder_mm: float = 10.0
    elbow_rad: float = float(np.radians(1.0))
    wrist_rad: float = float(np.radians(1.0))


@dataclass(frozen=True, eq=False)
class Selection:
    """One chosen solution per pose, by :func:`select_solution`.

    ``q_rad`` ``(N, 6)`` (NaN where nothing qualified), ``index`` ``(N,)`` branch index or
    -1, ``found`` ``(N,)``, ``singular`` ``(N,)`` (the chosen solution is flagged
    singular), ``travel`` ``(N,)`` weighted travel from the current vector (rad, inf if
    none).
    """

    q_rad: FloatArray
    index: NDArray[np.int_]
    found: BoolArray
    singular: BoolArray
    travel: FloatArray


@dataclass(frozen=True, eq=False)
class IKResult:
    """All branches of the inverse kinematics of N poses, and the chosen one per pose.

    Arrays (``B`` = 8 branches, in the order of :data:`BRANCHES`):

    * ``solutions_rad`` ``(N, B, 6)``: joint vectors, each joint at its in-limits
      2π-equivalent nearest the reference; NaN where the branch does not exist;
    * ``reachable`` ``(N, B)``: the branch exists (and, for a refined model, converged);
    * ``within_limits`` ``(N, B)``: every joint has an equivalent inside its limits;
    * ``shoulder_singular``, ``elbow_singular``, ``wrist_singular`` ``(N, B)``: flags per
      :class:`SingularityMargins` (False where not reachable);
    * ``residual_mm``, ``residual_rad`` ``(N, B)``: flange position and orientation error
      of each solution, by forward kinematics of the model (NaN where not reachable);
    * ``iterations`` ``(N, B)``: Levenberg-Marquardt steps taken (0 for an exact closed
      form);
    * ``selection``: the shortest-travel choice (:func:`select_solution`).
    """

    solutions_rad: FloatArray
    reachable: BoolArray
    within_limits: BoolArray
    shoulder_singular: BoolArray
    elbow_singular: BoolArray
    wrist_singular: BoolArray
    residual_mm: FloatArray
    residual_rad: FloatArray
    iterations: NDArray[np.int_]
    selection: Selection

    @property
    def valid(self) -> BoolArray:
        """Reachable and within limits, ``(N, B)``."""
        return self.reachable & self.within_limits

    @property
    def singular(self) -> BoolArray:
        """Any singularity flag, ``(N, B)``."""
        return self.shoulder_singular | self.elbow_singular | self.wrist_singular

    @property
    def chosen_rad(self) -> FloatArray:
        """The selected joint vector per pose, ``(N, 6)`` (NaN where none qualified)."""
        return self.selection.q_rad

    @property
    def n_poses(self) -> int:
        return int(self.solutions_rad.shape[0])


# -- geometry ---------------------------------------------------------------------------
def _turn_z(x: FloatArray, angle: FloatArray) -> FloatArray:
    """``Rz(angle)ᵀ · x`` for stacked 3×3 ``x`` ``(..., 3, 3)`` and ``angle`` ``(...)``.

    Row arithmetic instead of stacked matmuls: several times faster for 3×3 stacks.
    """
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    x0, x1, x2 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
    return np.stack(np.broadcast_arrays(c * x0 + s * x1, c * x1 - s * x0, x2), axis=-2)


def _turn_x(x: FloatArray, angle: float) -> FloatArray:
    """``Rx(angle)ᵀ · x`` for stacked 3×3 ``x`` ``(..., 3, 3)``."""
    c, s = np.cos(angle), np.sin(angle)
    x0, x1, x2 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
    return np.stack([x0, c * x1 + s * x2, c * x2 - s * x1], axis=-2)


def _pieper_violations(model: KinematicModel) -> list[str]:
    """Why ``model`` is not a Pieper arm (empty list when it is)."""
    if model.n_joints != 6:
        return [f"needs 6 joints, has {model.n_joints}"]
    out = []
    al, a, d = model.alpha_rad, model.a_mm, model.d_mm
    if np.any(np.abs(model.beta_rad) > _ANGLE_TOL):
        out.append("every beta must be 0")
    if abs(np.sin(al[2])) > _ANGLE_TOL or np.cos(al[2]) < 0:
        out.append("alpha3 must be 0 (joints 2 and 3 parallel)")
    for i in (1, 3, 4, 5):
        if abs(np.cos(al[i])) > _ANGLE_TOL:
            out.append(f"alpha{i + 1} must be ±90°")
    if abs(a[4]) > 0 or abs(a[5]) > 0 or abs(d[4]) > 0:
        out.append("a5, a6 and d5 must be 0 (wrist axes must meet in one point)")
    if a[2] <= 0 or np.hypot(a[3], d[3]) <= 0:
        out.append("upper arm a3 and forearm (a4, d4) must have length")
    return out


def is_spherical_wrist(model: KinematicModel) -> bool:
    """Whether the closed form applies exactly to ``model`` (see the module docstring)."""
    return not _pieper_violations(model)


def spherical_approximation(model: KinematicModel) -> KinematicModel:
    """The nearest Pieper geometry: betas, a5, a6, d5 zeroed, alphas snapped to 0/±90°.

    Used as the nominal geometry of a calibrated model whose own geometry is not exactly
    spherical; base and tool are kept.
    """
    if model.n_joints != 6:
        raise KinematicsError(f"closed-form IK needs 6 joints, model has {model.n_joints}")
    x = model.parameter_vector().copy()
    per_joint = x[:30].reshape(6, 5)
    per_joint[:, 1] = np.round(per_joint[:, 1] / (np.pi / 2)) * (np.pi / 2)
    per_joint[:, 4] = 0.0
    per_joint[4, 0] = per_joint[5, 0] = per_joint[4, 2] = 0.0
    approx = model.with_parameters(x)
    problems = _pieper_violations(approx)
    if problems:
        raise KinematicsError("no spherical-wrist approximation: " + "; ".join(problems))
    return approx


@dataclass(frozen=True, eq=False)
class _Pieper:
    """Constants of the closed form, derived from a Pieper model (mm, rad)."""

    pre_rot: FloatArray  # Rx(alpha1), (3, 3)
    a0: float
    d0: float
    s1: float  # sin(alpha2) = ±1
    a1: float
    h: float  # lateral offset of the wrist centre from the arm plane
    a2: float
    forearm: float  # L: distance axis 3 -> wrist centre, projected on the arm plane
    phi: float  # angle of the forearm in frame 3
    sigma4: float  # sin(alpha5) = ±1
    kappa: float  # +1 when alpha5 + alpha6 = 0, -1 when it is ±180°
    post_rot: FloatArray  # Rx(alpha5 + alpha6)
    d_flange: float
    offsets: FloatArray  # (6,)
    alpha: FloatArray  # (6,)

    @classmethod
    def of(cls, model: KinematicModel) -> _Pieper:
        problems = _pieper_violations(model)
        if problems:
            raise KinematicsError("not a spherical-wrist geometry: " + "; ".join(problems))
        al, a, d = model.alpha_rad, model.a_mm, model.d_mm
        w3 = np.array([a[3], -np.sin(al[3]) * d[3], np.cos(al[3]) * d[3]])
        return cls(
            pre_rot=rot_x(al[0]),
            a0=float(a[0]),
            d0=float(d[0]),
            s1=float(np.round(np.sin(al[1]))),
            a1=float(a[1]),
            h=float(d[1] + d[2] + w3[2]),
            a2=float(a[2]),
            forearm=float(np.hypot(w3[0], w3[1])),
            phi=float(np.arctan2(w3[1], w3[0])),
            sigma4=float(np.round(np.sin(al[4]))),
            kappa=1.0 if np.cos(al[4] + al[5]) > 0 else -1.0,
            post_rot=rot_x(al[4] + al[5]),
            d_flange=float(d[5]),
            offsets=model.theta_offset_rad.copy(),
            alpha=model.alpha_rad.copy(),
        )

    def elbow_angle(self, q3: FloatArray) -> FloatArray:
        """psi: angle between upper arm and the forearm's projection (0 = stretched)."""
        elbow: FloatArray = q3 + self.offsets[2] + self.phi
        return elbow

    def shoulder_distance(self, q2: FloatArray, psi: FloatArray) -> FloatArray:
        """Signed distance r of the wrist centre from axis 1 in the arm plane (mm)."""
        w2x = self.a2 + self.forearm * np.cos(psi)
        w2y = self.forearm * np.sin(psi)
        t2 = q2 + self.offsets[1]
        dist: FloatArray = self.a1 + np.cos(t2) * w2x - np.sin(t2) * w2y
        return dist


def _closed_form(
    geo: _Pieper, rot: FloatArray, pos: FloatArray, q_ref: FloatArray, *, seed: bool = False
) -> tuple[FloatArray, BoolArray]:
    """All 8 branches for flange poses in the base frame.

    ``rot`` ``(N, 3, 3)``, ``pos`` ``(N, 3)`` mm, ``q_ref`` ``(N, 6)`` rad (used only where
    q1 or q4 is undetermined). Returns joint angles ``(N, 8, 6)`` in [-π, π) and the
    reachable mask ``(N, 8)``. With ``seed`` the result starts a numeric solve on a
    slightly different geometry: poses just out of the nominal reach still get a start,
    and the elbow is kept off stretched/folded so that both elbow branches stay apart.
    """
    sh, el, wr = (BRANCH_SIGNS[None, :, k].astype(float) for k in range(3))
    # Wrist centre, in the frame after Rx(alpha1)·Trans_x(a1) and before Rot_z(theta1).
    w = pos - geo.d_flange * rot[:, :, 2]
    v = w @ geo.pre_rot - np.array([geo.a0, 0.0, geo.d0])
    t1, ux, uy, shoulder_ok = _shoulder(geo, v, sh, q_ref, seed=seed)
    t2, t3, elbow_ok = _elbow(geo, ux, uy, el, seed=seed)
    t4, t5, t6 = _wrist(geo, rot, (t1, t2, t3), wr, q_ref)
    theta = np.stack(np.broadcast_arrays(t1, t2, t3, t4, t5, t6), axis=-1)
    q = _wrap(theta - geo.offsets)
    reachable = shoulder_ok & elbow_ok & np.all(np.isfinite(q), axis=-1)
    return np.where(reachable[..., None], q, np.nan), reachable


def _shoulder(
    geo: _Pieper, v: FloatArray, sh: FloatArray, q_ref: FloatArray, *, seed: bool
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """θ1 ``(N, 8)`` from the wrist centre ``v`` ``(N, 3)`` mm (frame of
    :func:`_closed_form`) for the shoulder signs ``sh`` ``(1, 8)``: Rz(t1)·(r, -s1·h) =
    (vx, vy), two signs of r. Also the wrist centre in the arm plane ``(ux, uy)`` mm
    and whether the shoulder reaches it."""
    vx, vy, vz = (v[:, k, None] for k in range(3))
    rho2 = vx**2 + vy**2
    r2 = rho2 - geo.h**2
    shoulder_ok = r2 >= -1e-9 * max(geo.h**2, 1.0)
    if seed:  # a lateral offset may differ on the real geometry: keep the branches apart
        r2 = np.maximum(r2, _SEED_SHOULDER_MM**2)
        shoulder_ok = np.ones_like(shoulder_ok)
    r = sh * np.sqrt(np.maximum(r2, 0.0))
    t1 = np.arctan2(vy, vx) - np.arctan2(-geo.s1 * geo.h, r)
    t1 = np.where(np.sqrt(rho2) < _SHOULDER_DEGENERATE_MM, q_ref[:, :1] + geo.offsets[0], t1)
    c1, s1 = np.cos(t1), np.sin(t1)
    r = c1 * vx + s1 * vy  # consistent with the t1 actually used
    ux, uy = r - geo.a1, np.broadcast_to(geo.s1 * vz, r.shape)
    return t1, ux, uy, shoulder_ok


def _elbow(
    geo: _Pieper, ux: FloatArray, uy: FloatArray, el: FloatArray, *, seed: bool
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """θ2, θ3 ``(N, 8)`` for the elbow signs ``el`` ``(1, 8)``: the law of cosines in the
    arm plane, psi = t3 + phi; and whether the elbow reaches."""
    cpsi = (ux**2 + uy**2 - geo.a2**2 - geo.forearm**2) / (2.0 * geo.a2 * geo.forearm)
    elbow_ok = np.abs(cpsi) <= 1.0 + (_SEED_ELBOW_SLACK if seed else _ELBOW_SLACK)
    cpsi = np.clip(cpsi, -1.0, 1.0)
    if seed:
        cpsi = np.clip(cpsi, -_SEED_ELBOW_COS, _SEED_ELBOW_COS)
    spsi = el * np.sqrt(1.0 - cpsi**2)
    t3 = np.arctan2(spsi, cpsi) - geo.phi
    w2x, w2y = geo.a2 + geo.forearm * cpsi, geo.forearm * spsi
    t2 = np.arctan2(uy, ux) - np.arctan2(w2y, w2x)
    return t2, t3, elbow_ok


def _wrist(
    geo: _Pieper,
    rot: FloatArray,
    arm: tuple[FloatArray, FloatArray, FloatArray],
    wr: FloatArray,
    q_ref: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """θ4, θ5, θ6 ``(N, 8)`` for the flange rotations ``rot`` ``(N, 3, 3)``, the arm's θ1–θ3
    ``arm`` and the wrist signs ``wr`` ``(1, 8)``:

        E = (R03·Rx(alpha4))ᵀ · R · Rx(alpha5 + alpha6)ᵀ
          = Rz(t4) · Ry(-sigma4·t5) · Rz(kappa·t6)   (ZYZ Euler angles),

    with R03 = Rx(alpha1)·Rz(t1)·Rx(alpha2)·Rz(t2 + t3) since alpha3 = 0.
    """
    t1, t2, t3 = arm
    e = geo.pre_rot.T @ rot @ geo.post_rot.T
    e = _turn_z(e[:, None], t1)
    e = _turn_x(e, geo.alpha[1])
    e = _turn_z(e, t2 + t3)
    e = _turn_x(e, geo.alpha[3])
    e02, e12 = e[..., 0, 2], e[..., 1, 2]
    flip = -geo.sigma4 * wr  # sign of B = -sigma4·t5 that makes sign(sin t5) = wr
    t4 = np.arctan2(flip * e12, flip * e02)
    t4 = np.where(np.hypot(e02, e12) < _WRIST_DEGENERATE, q_ref[:, 3:4] + geo.offsets[3], t4)
    f = _turn_z(e, t4)  # = Ry(B)·Rz(G), exact for any t4
    b = np.arctan2(f[..., 0, 2], f[..., 2, 2])
    g = np.arctan2(f[..., 1, 0], f[..., 1, 1])
    return t4, -geo.sigma4 * b, geo.kappa * g


def _wrap(q: FloatArray) -> FloatArray:
    """Angles to [-π, π)."""
    return (q + np.pi) % (2.0 * np.pi) - np.pi


def nearest_equivalent(
    q_rad: ArrayLike, q_ref_rad: ArrayLike, limits: JointLimits | None = None
) -> tuple[FloatArray, BoolArray]:
    """Per joint, the 2π-equivalent of ``q_rad`` within limits nearest ``q_ref_rad``.

    Shapes broadcast (``(..., n)``). Returns the joint vectors and, per vector, whether
    every joint has an equivalent within the limits (joints without one keep the
    equivalent nearest the reference, outside the limits).
    """
    q = np.asarray(q_rad, dtype=float)
    ref = np.asarray(q_ref_rad, dtype=float)
    two_pi = 2.0 * np.pi
    k = np.round((ref - q) / two_pi)
    if limits is None:
        return q + two_pi * k, np.all(np.isfinite(q), axis=-1)
    k_min = np.ceil((limits.lower_rad - LIMIT_SLACK_RAD - q) / two_pi)
    k_max = np.floor((limits.upper_rad + LIMIT_SLACK_RAD - q) / two_pi)
    inside = k_min <= k_max
    k = np.where(inside, np.clip(k, k_min, k_max), k)
    return q + two_pi * k, np.all(inside, axis=-1)


# -- selection --------------------------------------------------------------------------
def select_solution(
    solutions_rad: ArrayLike,
    q_current_rad: ArrayLike,
    *,
    valid: ArrayLike | None = None,
    singular: ArrayLike | None = None,
    limits: JointLimits | None = None,
    weights: ArrayLike = DEFAULT_TRAVEL_WEIGHTS,
    singular_penalty: float = np.inf,
) -> Selection:
    """Shortest-travel choice among IK solutions (method section 5).

    ``solutions_rad`` ``(N, B, 6)``; ``q_current_rad`` ``(N, 6)`` or ``(6,)``; ``valid``
    and ``singular`` ``(N, B)`` (default: all valid where finite, none singular).
    Each joint is first moved to its 2π-equivalent within ``limits`` nearest the current
    value; candidates outside the limits or invalid are dropped. The rest are ranked by
    weighted travel ``Σ w_j·|Δq_j|`` (rad; the default weights make the main axes dearer
    than the wrist) plus ``singular_penalty`` for a singular one. The default infinite
    penalty is the method's order: any non-singular candidate beats every singular one,
    singular ones are chosen only when nothing else is left. A finite penalty (rad of
    weighted travel) trades a near-singular wrist against large main-axis moves instead.
    """
    sol = np.asarray(solutions_rad, dtype=float)
    if sol.ndim != 3:
        raise KinematicsError(f"solutions must have shape (N, B, n), got {sol.shape}")
    n_pose, n_branch, n = sol.shape
    cur = np.asarray(q_current_rad, dtype=float)
    if cur.shape not in ((n,), (n_pose, n)):
        raise KinematicsError(f"q_current must have shape ({n},) or ({n_pose}, {n})")
    cur = np.broadcast_to(cur, (n_pose, n))
    w = np.asarray(weights, dtype=float)
    if w.shape != (n,) or np.any(w < 0):
        raise KinematicsError(f"weights must be {n} non-negative numbers, got {w.tolist()}")
    if not singular_penalty >= 0:
        raise KinematicsError(f"singular_penalty must be >= 0, got {singular_penalty}")
    ok = np.ones((n_pose, n_branch), bool) if valid is None else np.asarray(valid, bool)
    sing = np.zeros((n_pose, n_branch), bool) if singular is None else np.asarray(singular)
    moved, inside = nearest_equivalent(sol, cur[:, None, :], limits)
    ok = ok & inside & np.all(np.isfinite(moved), axis=-1)
    with np.errstate(invalid="ignore"):
        travel = np.sum(w * np.abs(moved - cur[:, None, :]), axis=-1)
    key = np.where(ok, travel, np.inf)
    if np.isinf(singular_penalty):
        # Lexicographic: drop singular candidates wherever a non-singular one exists.
        has_regular = np.any(ok & ~sing, axis=1, keepdims=True)
        key = np.where(has_regular & sing, np.inf, key)
    else:
        key = key + singular_penalty * sing
    index = np.argmin(key, axis=1)
    rows = np.arange(n_pose)
    found = np.isfinite(key[rows, index])
    return Selection(
        q_rad=np.where(found[:, None], moved[rows, index], np.nan),
        index=np.where(found, index, -1),
        found=found,
        singular=found & sing[rows, index],
        travel=np.where(found, travel[rows, index], np.inf),
    )


# -- driver -----------------------------------------------------------------------------
def _as_poses(poses: ArrayLike) -> FloatArray:
    t = np.asarray(poses, dtype=float)
    if t.shape == (4, 4):
        t = t[None]
    if t.ndim != 3 or t.shape[1:] != (4, 4):
        raise KinematicsError(f"poses must have shape (N, 4, 4) or (4, 4), got {t.shape}")
    return t


def _rotation_error(r_target: FloatArray, r: FloatArray) -> FloatArray:
    """Rotation vector of ``r_target · rᵀ`` (rad), shape ``(..., 3)``."""
    m = r_target @ np.swapaxes(r, -1, -2)
    v = 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )
    sin_a = np.linalg.norm(v, axis=-1)
    angle = np.arctan2(sin_a, 0.5 * (np.trace(m, axis1=-2, axis2=-1) - 1.0))
    scale = np.where(sin_a > 1e-300, angle / np.maximum(sin_a, 1e-300), 1.0)
    return v * scale[..., None]


def _pose_error(
    model: KinematicModel, q: FloatArray, rot: FloatArray, pos: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Flange position error (mm) and rotation error vector (rad), each ``(M, 3)``."""
    t = flange_poses(model, q, world=False)
    return pos - t[:, :3, 3], _rotation_error(rot, t[:, :3, :3])


def _refine(
    model: KinematicModel,
    q: FloatArray,
    rot: FloatArray,
    pos: FloatArray,
    *,
    tol_mm: float,
    tol_rad: float,
    max_iterations: int,
) -> tuple[FloatArray, BoolArray, NDArray[np.int_]]:
    """Levenberg-Marquardt on the model's geometric Jacobian, flattened solutions ``(M, 6)``.

    The damping starts negligible (plain Newton, quadratic convergence) and grows only
    where a step fails to reduce the error, which near a singularity keeps the step
    inside the region where the linearization holds. Returns the polished vectors,
    whether each met the tolerance, and the Jacobian evaluations taken.
    """
    q = q.copy()
    steps = np.zeros(q.shape[0], dtype=int)
    converged = np.zeros(q.shape[0], dtype=bool)
    active = np.all(np.isfinite(q), axis=1)
    weight = np.array([1.0, 1.0, 1.0] + [_ORIENTATION_SCALE_MM**2] * 3)
    mu = np.full(q.shape[0], _MU_MIN)
    err = np.zeros((q.shape[0], 6))
    idx = np.flatnonzero(active)
    err[idx] = _stacked_error(model, q[idx], rot[idx], pos[idx])
    for step in range(max_iterations + 1):
        idx = np.flatnonzero(active)
        e = err[idx]
        done = (np.linalg.norm(e[:, :3], axis=1) <= tol_mm) & (
            np.linalg.norm(e[:, 3:], axis=1) <= tol_rad
        )
        converged[idx[done]] = True
        active[idx[done]] = False
        idx, e = idx[~done], e[~done]
        if idx.size == 0 or step == max_iterations:
            break
        jac = geometric_jacobian(model, q[idx], point="flange", frame="base")
        jtw = np.swapaxes(jac, 1, 2) * weight
        normal = jtw @ jac
        normal += (mu[idx] * np.trace(normal, axis1=1, axis2=2))[:, None, None] * np.eye(6)
        q_try = q[idx] + np.linalg.solve(normal, (jtw @ e[:, :, None]))[:, :, 0]
        e_try = _stacked_error(model, q_try, rot[idx], pos[idx])
        better = np.sum(weight * e_try**2, axis=1) < np.sum(weight * e**2, axis=1)
        good, bad = idx[better], idx[~better]
        q[good], err[good] = q_try[better], e_try[better]
        mu[good] = np.maximum(mu[good] * 0.1, _MU_MIN)
        mu[bad] = np.maximum(mu[bad] * 10.0, _MU_REJECTED)
        steps[idx] += 1
    return q, converged, steps


def _stacked_error(
    model: KinematicModel, q: FloatArray, rot: FloatArray, pos: FloatArray
) -> FloatArray:
    """Position (mm) and rotation-vector (rad) error stacked, ``(M, 6)``."""
    dp, dr = _pose_error(model, q, rot, pos)
    return np.concatenate([dp, dr], axis=1)


def _flange_in_base(
    model: KinematicModel, poses: FloatArray, frame: str, target: str
) -> tuple[FloatArray, FloatArray]:
    """Flange rotations ``(N, 3, 3)`` and origins ``(N, 3)`` (mm) in the base frame."""
    rot, pos = poses[:, :3, :3], poses[:, :3, 3]
    if frame == "world":
        rb = model.base_rotation()
        rot, pos = rb.T @ rot, (pos - model.base_mm) @ rb
    if target == "tcp":  # the tool is a pure offset in the flange frame
        pos = pos - rot @ model.tool_mm
    return rot, pos


def solve_ik(
    model: KinematicModel,
    poses: ArrayLike,
    *,
    frame: Literal["base", "world"] = "base",
    target: Literal["flange", "tcp"] = "flange",
    limits: JointLimits | None = None,
    q_current_rad: ArrayLike | None = None,
    weights: ArrayLike = DEFAULT_TRAVEL_WEIGHTS,
    singular_penalty: float = np.inf,
    margins: SingularityMargins | None = None,
    nominal: KinematicModel | None = None,
    branches: Literal["all", "chosen"] = "all",
    tol_mm: float = 1e-9,
    tol_rad: float = 1e-11,
    max_iterations: int = 30,
) -> IKResult:
    """Inverse kinematics of ``poses`` ``(N, 4, 4)`` (or one ``(4, 4)``; mm) for ``model``.

    ``frame``: the poses are in the robot base frame or in the world (tracker) frame, the
    model's base pose converting. ``target``: ``"flange"`` poses, or ``"tcp"`` poses whose
    origin is the tool point (the model's ``tool_mm``) with the flange orientation.
    ``limits``: joint limits (none when omitted). ``q_current_rad`` ``(6,)`` or ``(N, 6)``:
    reference for the 2π-equivalents, for q1/q4 at an exact singularity and for the
    selection (zeros when omitted). ``weights``, ``singular_penalty``: the selection rule
    (:func:`select_solution`); ``margins``: the singularity flags.

    If ``model`` is a Pieper geometry the closed form is used as is. Otherwise the closed
    form of ``nominal`` (default :func:`spherical_approximation` of ``model``) seeds up to
    ``max_iterations`` Levenberg-Marquardt steps on ``model``; a branch that does not reach
    ``tol_mm`` (flange position) and ``tol_rad`` (flange orientation) is reported
    unreachable. Singularity flags are evaluated on the Pieper geometry of the closed form.
    ``branches="chosen"`` (numeric path only) polishes just the three branches the
    selection rule ranks best among the seeds (:meth:`_Rule.candidates`), under half the
    work, and selects among them; the other branches are then not solved (NaN,
    ``reachable`` False), except for poses where all three fail or end outside the
    limits, which fall back to all branches. The pick can differ from that of ``"all"``
    when the seeds rank the branches wrongly (in tests, under 1 % of random poses).

    Long for its options and their documentation; each step is a function of its own.
    """
    t = _as_poses(poses)
    _check_options(model, frame, target, branches)
    n_pose = t.shape[0]
    ref = _reference(q_current_rad, n_pose)
    rule = _Rule(ref, limits, weights, singular_penalty, margins or SingularityMargins())

    rot, pos = _flange_in_base(model, t, frame, target)
    exact = nominal is None and is_spherical_wrist(model)
    if exact:
        geo = _Pieper.of(model)
    else:
        geo = _Pieper.of(nominal if nominal is not None else spherical_approximation(model))
    q, reachable = _closed_form(geo, rot, pos, ref, seed=not exact)

    iterations = np.zeros((n_pose, N_BRANCHES), dtype=int)
    if not exact:
        polish = partial(
            _refine_branches,
            model,
            rot=rot,
            pos=pos,
            tol_mm=tol_mm,
            tol_rad=tol_rad,
            max_iterations=max_iterations,
        )
        todo = reachable.copy()
        if branches == "chosen":
            todo = rule.widened(_SEED_LIMIT_SLACK_RAD).candidates(geo, q, reachable)
        q, reachable, iterations = _polished(polish, q, reachable, todo, rule)

    residual_mm, residual_rad = _checked_by_forward(model, q, reachable, rot, pos)
    q, within, shoulder, elbow, wrist, selection = rule.assess(geo, q, reachable)
    return IKResult(
        solutions_rad=q,
        reachable=reachable,
        within_limits=within,
        shoulder_singular=shoulder,
        elbow_singular=elbow,
        wrist_singular=wrist,
        residual_mm=residual_mm,
        residual_rad=residual_rad,
        iterations=iterations,
        selection=selection,
    )


def _check_options(model: KinematicModel, frame: str, target: str, branches: str) -> None:
    if model.n_joints != 6:
        raise KinematicsError(f"closed-form IK needs 6 joints, model has {model.n_joints}")
    if frame not in ("base", "world") or target not in ("flange", "tcp"):
        raise KinematicsError(
            f"frame must be 'base' or 'world' and target 'flange' or 'tcp', got {frame!r}, "
            f"{target!r}"
        )
    if branches not in ("all", "chosen"):
        raise KinematicsError(f"branches must be 'all' or 'chosen', got {branches!r}")


def _reference(q_current_rad: ArrayLike | None, n_pose: int) -> FloatArray:
    """The reference joint vector of every pose ``(N, 6)`` rad (zeros when none is given)."""
    if q_current_rad is None:
        return np.zeros((n_pose, 6))
    cur = np.asarray(q_current_rad, dtype=float)
    if cur.shape not in ((6,), (n_pose, 6)):
        raise KinematicsError(f"q_current_rad must be (6,) or ({n_pose}, 6), got {cur.shape}")
    return np.broadcast_to(cur, (n_pose, 6)).copy()


#: Polishes the seeds ``(N, B, 6)`` of the branches in a mask ``(N, B)``: the joint angles,
#: whether each converged, and its iterations (see :func:`_refine_branches`).
_Polish = Callable[[FloatArray, BoolArray], tuple[FloatArray, BoolArray, NDArray[np.int_]]]


def _polished(
    polish: _Polish, seeds: FloatArray, reachable: BoolArray, todo: BoolArray, rule: _Rule
) -> tuple[FloatArray, BoolArray, NDArray[np.int_]]:
    """The branches ``todo`` polished from the closed form's ``seeds`` ``(N, B, 6)``; where
    none of a pose's converges within the limits, its other reachable branches too. The
    joint angles, the branches reachable on the model, and the iterations ``(N, B)``."""
    q, converged, iterations = polish(seeds, todo)
    usable = converged & nearest_equivalent(q, rule.ref[:, None, :], rule.limits)[1]
    retry = ~np.any(usable, axis=1) & np.any(reachable & ~todo, axis=1)
    if retry.any():  # the chosen branch failed: solve the others of those poses
        more = reachable & ~todo & retry[:, None]
        q2, c2, it2 = polish(seeds, more)
        q, converged = np.where(more[..., None], q2, q), converged | c2
        iterations = np.where(more, it2, iterations)
    return q, reachable & converged, iterations


def _checked_by_forward(
    model: KinematicModel, q: FloatArray, reachable: BoolArray, rot: FloatArray, pos: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Every reported solution checked by the model's own forward kinematics: the flange's
    position (mm) and orientation (rad) errors ``(N, B)``, NaN where unreachable."""
    n_pose = q.shape[0]
    residual_mm = np.full((n_pose, N_BRANCHES), np.nan)
    residual_rad = np.full((n_pose, N_BRANCHES), np.nan)
    if reachable.any():
        rows = np.nonzero(reachable)[0]
        dp, dr = _pose_error(model, q[reachable], rot[rows], pos[rows])
        residual_mm[reachable] = np.linalg.norm(dp, axis=1)
        residual_rad[reachable] = np.linalg.norm(dr, axis=1)
    return residual_mm, residual_rad


@dataclass(frozen=True, eq=False)
class _Rule:
    """The reference vector and selection settings of one :func:`solve_ik` call."""

    ref: FloatArray  # (N, 6)
    limits: JointLimits | None
    weights: ArrayLike
    singular_penalty: float
    margins: SingularityMargins

    def widened(self, slack_rad: float) -> _Rule:
        if self.limits is None:
            return self
        wide = JointLimits(self.limits.lower_rad - slack_rad, self.limits.upper_rad + slack_rad)
        return replace(self, limits=wide)

    def candidates(self, geo: _Pieper, seeds: FloatArray, reachable: BoolArray) -> BoolArray:
        """Branches worth polishing per pose, mask ``(N, B)``: the two best seeds by the
        rule, and the best by travel alone (singularity flags of seeds near a margin may
        change when polished). Seeds are off by up to a few degrees, so near-ties are
        decided after polishing.
        """
        todo = np.zeros_like(reachable)
        rows = np.arange(reachable.shape[0])
        left = reachable.copy()
        for rule in (self, self, replace(self, singular_penalty=0.0)):
            pick = rule.assess(geo, seeds, left)[-1]
            todo[rows, pick.index] |= pick.found
            left[rows, pick.index] &= ~pick.found
        return todo

    def assess(
        self, geo: _Pieper, q: FloatArray, reachable: BoolArray
    ) -> tuple[FloatArray, BoolArray, BoolArray, BoolArray, BoolArray, Selection]:
        """2π-equivalents, limit and singularity flags of ``q`` ``(N, B, 6)``, and the pick."""
        q, within = nearest_equivalent(q, self.ref[:, None, :], self.limits)
        within &= reachable
        flags = _singularity_flags(geo, q, self.margins)
        shoulder, elbow, wrist = (flag & reachable for flag in flags)
        selection = select_solution(
            q,
            self.ref,
            valid=reachable & within,
            singular=shoulder | elbow | wrist,
            limits=self.limits,
            weights=self.weights,
            singular_penalty=self.singular_penalty,
        )
        return q, within, shoulder, elbow, wrist, selection


def _refine_branches(
    model: KinematicModel,
    q: FloatArray,
    todo: BoolArray,
    *,
    rot: FloatArray,
    pos: FloatArray,
    tol_mm: float,
    tol_rad: float,
    max_iterations: int,
) -> tuple[FloatArray, BoolArray, NDArray[np.int_]]:
    """Polish the branches ``todo`` ``(N, B)`` of seeds ``q`` ``(N, B, 6)`` on ``model``.

    Returns joint vectors wrapped to [-π, π) (NaN where not polished or not converged),
    the converged mask and the steps taken, shaped like the inputs.
    """
    rows = np.nonzero(todo)[0]
    out = np.full(q.shape, np.nan)
    converged = np.zeros(todo.shape, dtype=bool)
    steps = np.zeros(todo.shape, dtype=int)
    if rows.size:
        q_done, ok, n_steps = _refine(
            model,
            q[todo],
            rot[rows],
            pos[rows],
            tol_mm=tol_mm,
            tol_rad=tol_rad,
            max_iterations=max_iterations,
        )
        out[todo] = np.where(ok[:, None], _wrap(q_done), np.nan)
        converged[todo], steps[todo] = ok, n_steps
    return out, converged, steps


def _singularity_flags(
    geo: _Pieper, q: FloatArray, margins: SingularityMargins
) -> tuple[BoolArray, BoolArray, BoolArray]:
    """Shoulder, elbow and wrist flags for joint vectors ``(..., 6)`` on a Pieper geometry."""
    with np.errstate(invalid="ignore"):
        psi = geo.elbow_angle(q[..., 2])
        r = geo.shoulder_distance(q[..., 1], psi)
        shoulder = np.abs(r) < margins.shoulder_mm
        elbow = np.abs(np.sin(psi)) < np.sin(margins.elbow_rad)
        wrist = np.abs(np.sin(q[..., 4] + geo.offsets[4])) < np.sin(margins.wrist_rad)
    return shoulder, elbow, wrist


def singularity_flags(
    model: KinematicModel, q_rad: ArrayLike, margins: SingularityMargins | None = None
) -> tuple[BoolArray, BoolArray, BoolArray]:
    """Shoulder, elbow and wrist singularity flags of joint vectors ``(..., 6)`` (rad).

    Evaluated on ``model`` if it is a Pieper geometry, else on its
    :func:`spherical_approximation`.
    """
    geo = _Pieper.of(model if is_spherical_wrist(model) else spherical_approximation(model))
    return _singularity_flags(geo, np.asarray(q_rad, dtype=float), margins or SingularityMargins())
