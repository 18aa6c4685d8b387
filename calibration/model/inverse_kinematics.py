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
from calibration.model.ik_refinement import pose_error, refine
from calibration.model.ik_results import IKResult, JointLimits, Selection, SingularityMargins
from calibration.model.kinematics import (
    FloatArray,
    KinematicModel,
)
from calibration.model.pieper_closed_form import (
    N_BRANCHES,
    PieperGeometry,
    closed_form,
    is_spherical_wrist,
    nearest_equivalent,
    spherical_approximation,
    wrap_angle,
)

BoolArray = NDArray[np.bool_]


# Travel weights of the shortest-travel rule: the main axes move the arm's mass and swing
# the TCP by the whole reach, the wrist only by the flange distance, so a radian of a main
# axis costs more than a radian of the wrist (an arm of more joints: 1 for each joint after
# the sixth).
DEFAULT_TRAVEL_WEIGHTS: tuple[float, ...] = (3.0, 3.0, 2.0, 1.0, 1.0, 1.0)


def _travel_weights(n: int) -> tuple[float, ...]:
    """:data:`DEFAULT_TRAVEL_WEIGHTS` for an arm of ``n`` joints (1 past the sixth)."""
    return (DEFAULT_TRAVEL_WEIGHTS + (1.0,) * n)[:n]


# With branches="chosen" the seeds are ranked allowing them this far past a joint limit.
_SEED_LIMIT_SLACK_RAD = float(np.radians(5.0))


# -- selection --------------------------------------------------------------------------
def select_solution(
    solutions_rad: ArrayLike,
    q_current_rad: ArrayLike,
    *,
    valid: ArrayLike | None = None,
    singular: ArrayLike | None = None,
    limits: JointLimits | None = None,
    weights: ArrayLike | None = None,
    singular_penalty: float = np.inf,
) -> Selection:
    """Shortest-travel choice among IK solutions (method section 5).

    ``solutions_rad`` ``(N, B, n)``; ``q_current_rad`` ``(N, n)`` or ``(n,)``; ``valid``
    and ``singular`` ``(N, B)`` (default: all valid where finite, none singular).
    Each joint is first moved to its 2π-equivalent within ``limits`` nearest the current
    value; candidates outside the limits or invalid are dropped. The rest are ranked by
    weighted travel ``Σ w_j·|Δq_j|`` (rad; the default weights,
    :data:`DEFAULT_TRAVEL_WEIGHTS`, make the main axes dearer than the wrist) plus
    ``singular_penalty`` for a singular one. The default infinite penalty is the method's
    order: any non-singular candidate beats every singular one,
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
    w = np.asarray(_travel_weights(n) if weights is None else weights, dtype=float)
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


def flange_in_base(
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

    rot, pos = flange_in_base(model, t, frame, target)
    exact = nominal is None and is_spherical_wrist(model)
    if exact:
        geo = PieperGeometry.of(model)
    else:
        geo = PieperGeometry.of(nominal if nominal is not None else spherical_approximation(model))
    q, reachable = closed_form(geo, rot, pos, ref, seed=not exact)

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
        dp, dr = pose_error(model, q[reachable], rot[rows], pos[rows])
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

    def candidates(self, geo: PieperGeometry, seeds: FloatArray, reachable: BoolArray) -> BoolArray:
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
        self, geo: PieperGeometry, q: FloatArray, reachable: BoolArray
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
        q_done, ok, n_steps = refine(
            model,
            q[todo],
            rot[rows],
            pos[rows],
            tol_mm=tol_mm,
            tol_rad=tol_rad,
            max_iterations=max_iterations,
        )
        out[todo] = np.where(ok[:, None], wrap_angle(q_done), np.nan)
        converged[todo], steps[todo] = ok, n_steps
    return out, converged, steps


def _singularity_flags(
    geo: PieperGeometry, q: FloatArray, margins: SingularityMargins
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
    geo = PieperGeometry.of(model if is_spherical_wrist(model) else spherical_approximation(model))
    return _singularity_flags(geo, np.asarray(q_rad, dtype=float), margins or SingularityMargins())
