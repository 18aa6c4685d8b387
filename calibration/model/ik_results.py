"""The value types of the inverse kinematics: joint limits, singularity margins, the
selection rule, and :class:`IKResult` (every branch's solution, the one chosen, and why).
Angles in rad, lengths in mm."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.description import RobotDescription
from calibration.model.kinematics import (
    FloatArray,
)

BoolArray = NDArray[np.bool_]


# Slack on the joint limits for values that round to just past a limit (rad).
LIMIT_SLACK_RAD = 1e-9


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
