"""Inverse kinematics of any arm of 6 joints or more, numerically: Levenberg-Marquardt from
several starts.

The closed form (:mod:`calibration.model.inverse_kinematics`) needs a spherical wrist, or a
geometry near one to seed from. An arm whose wrist axes do not meet (the UR family: joints
2, 3 and 4 parallel, the wrist offset by d5) has neither, and for it the same
Levenberg-Marquardt polish (:func:`calibration.model.ik_refinement.refine`) starts instead
from joint vectors drawn uniformly inside the limits. Different starts settle on different
branches; which ones, and whether every branch is found, is up to the draws, so this is a
generator of solutions (what a campaign planner needs), not the enumeration of all eight
branches that the closed form gives. A redundant arm (7 joints, e.g. a Barrett WAM) has a
one-parameter family of joints per flange pose; each start settles on one member of it
(the least-squares steps move no joint along the family), so the starts' spread is the
redundancy's resolution: nothing optimises the elbow angle.

Near a singularity a general arm has no named branch angle to test (q5 on a spherical
wrist); :func:`jacobian_conditioning` measures the distance to one as the smallest
singular value of the geometric Jacobian over the largest, its position rows in units of
the arm's reach so that a radian of orientation and a reach of travel weigh alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.errors import KinematicsError
from calibration.model.ik_refinement import refine
from calibration.model.ik_results import JointLimits, Selection
from calibration.model.inverse_kinematics import select_solution
from calibration.model.kinematics import FloatArray, KinematicModel, geometric_jacobian
from calibration.model.pieper_closed_form import nearest_equivalent, wrap_angle

BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class NumericIK:
    """Solutions of :func:`multi_start_ik`, one row per start.

    ``solutions_rad`` ``(N, K, n)``: each start's converged joint vector, mapped to the
    2π-equivalent inside the limits nearest the reference (NaN where it did not converge);
    ``converged`` ``(N, K)``: the flange pose reached within the tolerances;
    ``within_limits`` ``(N, K)``: converged, and inside the limits.
    """

    solutions_rad: FloatArray
    converged: BoolArray
    within_limits: BoolArray


def arm_reach_mm(model: KinematicModel) -> float:
    """A length scale of the arm (mm): the sum of its link lengths and offsets, the tool's
    offset included; at least 1 mm."""
    return max(float(np.sum(np.abs(model.a_mm)) + np.sum(np.abs(model.d_mm))), 1.0) + float(
        np.linalg.norm(model.tool_mm)
    )


def jacobian_conditioning(model: KinematicModel, q_rad: FloatArray) -> FloatArray:
    """Smallest over largest singular value ``(N,)`` of the flange's geometric Jacobian at
    ``q_rad`` ``(N, n)``, the velocity rows divided by the arm's reach: 0 at a singularity,
    where some flange motion needs unbounded joint rates."""
    jac = geometric_jacobian(model, q_rad, point="flange", frame="base")
    jac[:, :3, :] /= arm_reach_mm(model)
    s = np.linalg.svd(jac, compute_uv=False)
    ratio: FloatArray = s[:, -1] / np.maximum(s[:, 0], 1e-300)
    return ratio


def _start_box(limits: JointLimits) -> tuple[FloatArray, FloatArray]:
    """Where starts are drawn ``(n,)`` each: the limits, a joint with more than a turn of
    range over one turn (its other solutions are the same angles 2π on)."""
    lo = np.maximum(limits.lower_rad, -np.pi)
    hi = np.minimum(limits.upper_rad, np.pi)
    inside = hi > lo
    return np.where(inside, lo, limits.lower_rad), np.where(inside, hi, limits.upper_rad)


def multi_start_ik(
    model: KinematicModel,
    rot: FloatArray,
    pos: FloatArray,
    limits: JointLimits,
    rng: np.random.Generator,
    *,
    n_starts: int = 4,
    starts_rad: FloatArray | None = None,
    reference_rad: FloatArray | None = None,
    tol_mm: float = 1e-6,
    tol_rad: float = 1e-9,
    max_iterations: int = 60,
) -> NumericIK:
    """Flange poses (rotations ``rot`` ``(N, 3, 3)``, origins ``pos`` ``(N, 3)`` mm, base
    frame) solved from ``n_starts`` joint vectors each, drawn uniformly inside ``limits``
    (a joint whose range spans more than a turn drawn over one turn), or from the same
    ``starts_rad`` ``(K, n)`` for every pose when given (``rng`` then unused). Solutions are mapped
    to the 2π-equivalent inside the limits nearest ``reference_rad`` ``(n,)`` (zeros when
    omitted). Raises :class:`KinematicsError` for an arm of fewer than 6 joints (it has no
    solution for a general flange pose)."""
    if model.n_joints < 6:
        raise KinematicsError(f"numeric IK needs 6 joints or more, model has {model.n_joints}")
    n, dof = len(pos), model.n_joints
    lo, hi = _start_box(limits)
    if starts_rad is None:
        starts = rng.uniform(lo, hi, size=(n, n_starts, dof))
    else:
        n_starts = len(starts_rad)
        starts = np.broadcast_to(np.asarray(starts_rad, dtype=float), (n, n_starts, dof))
    q, ok, _ = refine(
        model,
        starts.reshape(-1, dof),
        np.repeat(rot, n_starts, axis=0),
        np.repeat(pos, n_starts, axis=0),
        tol_mm=tol_mm,
        tol_rad=tol_rad,
        max_iterations=max_iterations,
    )
    ref = np.zeros(dof) if reference_rad is None else np.asarray(reference_rad, dtype=float)
    q, within = nearest_equivalent(wrap_angle(q), ref, limits)
    q[~ok] = np.nan
    return NumericIK(
        solutions_rad=q.reshape(n, n_starts, dof),
        converged=ok.reshape(n, n_starts),
        within_limits=(ok & within).reshape(n, n_starts),
    )


#: Starts of :func:`chosen_solution`: enough that every branch of a 6R arm is usually
#: found (a UR has 8), drawn once so that every target and every run see the same ones;
#: a pose none of them solves inside the limits gets the further ones (a redundant arm's
#: tight limits: on Barrett's WAM 2.3 % of 1000 random poses inside its limits had no
#: solution from 16 starts, 0.1 % from 64).
CHOSEN_STARTS = 16
FURTHER_STARTS = 48


def chosen_solution(
    model: KinematicModel,
    rot: FloatArray,
    pos: FloatArray,
    limits: JointLimits,
    *,
    reference_rad: FloatArray | None = None,
    min_conditioning: float = 0.01,
) -> Selection:
    """The shortest-travel solution (:func:`~calibration.model.inverse_kinematics.select_solution`)
    of the flange poses (``rot`` ``(N, 3, 3)``, ``pos`` ``(N, 3)`` mm, base frame) among
    those :func:`multi_start_ik` finds from :data:`CHOSEN_STARTS` fixed starts inside
    ``limits`` (:data:`FURTHER_STARTS` more for a pose none of them solves); a solution
    whose :func:`jacobian_conditioning` is below ``min_conditioning`` counts as singular.
    Deterministic: the same poses give the same joints. ``Selection.index`` is the start
    that found it (not a named branch)."""
    n = model.n_joints
    lo, hi = _start_box(limits)
    starts = np.random.default_rng(0).uniform(lo, hi, size=(CHOSEN_STARTS + FURTHER_STARTS, n))
    ref = np.zeros(n) if reference_rad is None else np.asarray(reference_rad, dtype=float)
    solutions = np.full((len(pos), len(starts), n), np.nan)
    within = np.zeros(solutions.shape[:2], dtype=bool)
    rows = np.arange(len(pos))
    for part in (slice(0, CHOSEN_STARTS), slice(CHOSEN_STARTS, None)):
        rows = rows[~within[rows].any(axis=1)]  # the poses no start has solved yet
        if rows.size == 0:
            break
        ik = multi_start_ik(
            model, rot[rows], pos[rows], limits, np.random.default_rng(0),
            starts_rad=starts[part], reference_rad=ref,
        )  # fmt: skip
        solutions[rows, part] = ik.solutions_rad
        within[rows, part] = ik.within_limits
    singular = np.zeros(within.shape, dtype=bool)
    if within.any():
        singular[within] = jacobian_conditioning(model, solutions[within]) < min_conditioning
    return select_solution(solutions, ref, valid=within, singular=singular, limits=limits)
