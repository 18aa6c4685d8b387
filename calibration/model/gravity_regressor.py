"""Gravity torques from the kinematics alone: linear in the links' first mass moments.

The torque gravity exerts about joint j's axis is linear in the links' first mass moments
(mass × centre-of-mass coordinates), with a regressor that needs only the joint angles,
the gravity direction and the geometry (method.md §6):

    τ_j(q) = g · Σ_{k ≥ j} Σ_a Ŷ_j,(k,a)(q) · μ_k,a,     Ŷ_j,(k,a) = (R_k e_a) · (ĝ × z_j)

with ``μ_k`` the first moment of link k in its own frame (kg·mm; ``a`` = x, y, z), ``R_k``
that frame's orientation and ``z_j`` joint j's axis in the robot base frame, ``ĝ`` the unit
gravity direction and g = 9.80665 N/kg. The regressor is dimensionless, so τ is in N·mm.

Link masses need no parameters of their own: the origin of frame k lies on joint k's axis
and is fixed in frame k − 1, so a mass there acts on joints 1..k−1 exactly as a first
moment of link k − 1 (``M_k · o_k`` in frame k − 1, with ``M_k`` everything outboard). The
payload is a first moment of the last link. So 3n raw moments describe any mass model.

Not all 3n act independently: a z moment has no lever about its own joint, a joint about
a vertical axis carries no torque at all, and consecutive parallel axes group moments.
:func:`base_moments` picks a set of raw moments whose columns span everything gravity can
do (the *base* moments: 10 for a 6R arm with joint 1 vertical, method.md §6), the others
being grouped into them; the choice is made once on the nominal geometry, by a fixed
order (outer links first, then x, y, z), and is stored by name (``link3.mx``) so that a
calibrated model reproduces the same columns whatever its identified geometry.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import GravityRegressorError
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]

#: Gravity along −z of the robot base frame: a floor-mounted arm.
FLOOR_GRAVITY = (0.0, 0.0, -1.0)
MOMENT_AXES = ("x", "y", "z")
#: Poses (uniform within the joint limits, fixed seed) on which base moments are chosen.
SELECTION_POSES = 256
#: A column adds a direction when its residual against the kept ones exceeds this
#: (relative): structural zeros are ~1e-15, the weakest real directions ~1e-2.
SELECTION_RTOL = 1e-8


def moment_names(n_joints: int) -> tuple[str, ...]:
    """Names of the 3n raw first moments, ``link{k}.m{x,y,z}`` (k 1-based)."""
    return tuple(f"link{k}.m{a}" for k in range(1, n_joints + 1) for a in MOMENT_AXES)


def unit_gravity(direction: ArrayLike | None) -> FloatArray:
    """The unit gravity direction ``(3,)`` in the robot base frame (default: −z)."""
    g = np.asarray(FLOOR_GRAVITY if direction is None else direction, dtype=float)
    norm = float(np.linalg.norm(g)) if g.shape == (3,) else 0.0
    if not (np.all(np.isfinite(g)) and norm > 0.0):
        raise GravityRegressorError(f"gravity direction must be a non-zero 3-vector, got {g}")
    return g / norm


def link_rotations(model: KinematicModel, q_rad: ArrayLike) -> FloatArray:
    """Orientation of every link frame in the robot base frame, ``(N, n, 3, 3)``."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    n_pose, n = q.shape
    rot = np.broadcast_to(np.eye(3), (n_pose, 3, 3)).copy()
    out = np.empty((n_pose, n, 3, 3))
    theta = q + model.theta_offset_rad
    consts = model.link_constants()
    for i in range(n):  # n steps, vectorized over poses
        rot = rot @ consts[i]
        c, s = np.cos(theta[:, i])[:, None], np.sin(theta[:, i])[:, None]
        col0 = c * rot[:, :, 0] + s * rot[:, :, 1]
        col1 = c * rot[:, :, 1] - s * rot[:, :, 0]
        rot[:, :, 0], rot[:, :, 1] = col0, col1
        out[:, i] = rot
    return out


def raw_regressor(
    model: KinematicModel, q_rad: ArrayLike, gravity: ArrayLike | None = None
) -> FloatArray:
    """Dimensionless regressor ``Ŷ`` ``(N, n, 3n)``: τ_j = g·Ŷ[:, j] @ μ (μ in kg·mm, the
    raw moments of :func:`moment_names`)."""
    rot = link_rotations(model, q_rad)
    n_pose, n = rot.shape[:2]
    w = np.cross(unit_gravity(gravity), rot[:, :, :, 2])  # ĝ × z_j, (N, n, 3)
    y = np.einsum("pkca,pjc->pjka", rot, w)  # (N, j, k, a)
    outboard = np.arange(n)[None, :] >= np.arange(n)[:, None]  # [j, k]: k ≥ j
    y *= outboard[None, :, :, None]
    regressor: FloatArray = y.reshape(n_pose, n, 3 * n)
    return regressor


def _selection_poses(description: RobotDescription) -> FloatArray:
    lo = np.radians([j.lower_deg for j in description.joints])
    hi = np.radians([j.upper_deg for j in description.joints])
    return np.random.default_rng(20260517).uniform(lo, hi, size=(SELECTION_POSES, len(lo)))


def _greedy_span(columns: FloatArray, order: Sequence[int]) -> list[int]:
    """Columns (in ``order``) that each add a direction to the ones kept before them."""
    norms = np.linalg.norm(columns, axis=0)
    ref = max(float(norms.max(initial=0.0)), 1e-300)
    basis = np.zeros((columns.shape[0], 0))
    kept: list[int] = []
    for i in order:
        c = columns[:, i]
        if norms[i] <= SELECTION_RTOL * ref:
            continue
        r = c - basis @ (basis.T @ c)
        r = r - basis @ (basis.T @ r)
        rn = float(np.linalg.norm(r))
        if rn > SELECTION_RTOL * norms[i] and rn > SELECTION_RTOL * ref:
            kept.append(i)
            basis = np.column_stack([basis, r / rn])
    return kept


def _preferred_order(n: int) -> list[int]:
    """Outer links first, then x, y, z: a wrist moment is kept, an arm's grouped into it."""
    return [3 * k + a for k in range(n - 1, -1, -1) for a in range(3)]


@dataclass(frozen=True)
class BaseMoments:
    """The base first moments of an arm and, per joint, which of them act on it.

    ``names`` are raw moment names (``link3.mx``); ``per_joint[j]`` lists, for joint j
    (0-based), the indices into ``names`` of an independent subset spanning that joint's
    torque (empty for a joint gravity cannot load, e.g. joint 1 about a vertical axis).
    """

    names: tuple[str, ...]
    per_joint: tuple[tuple[int, ...], ...]
    gravity: tuple[float, float, float]

    @property
    def n_joints(self) -> int:
        return len(self.per_joint)

    @property
    def raw_index(self) -> NDArray[np.intp]:
        """Position of each base moment among the 3n raw ones."""
        all_names = moment_names(self.n_joints)
        return np.array([all_names.index(n) for n in self.names], dtype=np.intp)

    @property
    def loaded_joints(self) -> tuple[int, ...]:
        """1-based joints that gravity can load."""
        return tuple(j + 1 for j, cols in enumerate(self.per_joint) if cols)

    def values_from_raw(self, raw_kgmm: ArrayLike, model: KinematicModel) -> FloatArray:
        """Base moments ``(b,)`` kg·mm giving the same torques as raw moments ``(3n,)``."""
        q = _selection_poses_for(model)
        y = raw_regressor(model, q, self.gravity)
        rows = y.reshape(-1, y.shape[-1])
        target = rows @ np.asarray(raw_kgmm, dtype=float)
        coef: FloatArray = np.linalg.lstsq(rows[:, self.raw_index], target, rcond=None)[0]
        return coef


def _selection_poses_for(model: KinematicModel) -> FloatArray:
    # limits are not part of a KinematicModel: any spread of angles spans the same space
    rng = np.random.default_rng(20260517)
    return rng.uniform(-np.pi, np.pi, size=(SELECTION_POSES, model.n_joints))


def base_moments(description: RobotDescription, gravity: ArrayLike | None = None) -> BaseMoments:
    """Choose the base moments of ``description`` (nominal geometry, fixed poses)."""
    g = unit_gravity(gravity if gravity is not None else gravity_of(description))
    model = KinematicModel.from_description(description)
    q = _selection_poses(description)
    y = raw_regressor(model, q, g)  # (N, n, 3n)
    n = model.n_joints
    order = _preferred_order(n)
    kept = _greedy_span(y.reshape(-1, 3 * n), order)
    kept_sorted = sorted(kept)
    names = tuple(moment_names(n)[i] for i in kept_sorted)
    per_joint = []
    for j in range(n):
        rows = y[:, j, :][:, kept_sorted]
        local = _greedy_span(rows, [kept_sorted.index(i) for i in order if i in kept_sorted])
        per_joint.append(tuple(sorted(local)))
    return BaseMoments(names, tuple(per_joint), (float(g[0]), float(g[1]), float(g[2])))


def gravity_of(description: RobotDescription) -> FloatArray:
    """Gravity direction in the robot base frame: the description's, else −z (floor)."""
    base = description.base
    return unit_gravity(base.gravity if base is not None else None)


def raw_moments_from_masses(description: RobotDescription) -> FloatArray | None:
    """Raw first moments ``(3n,)`` kg·mm of the description's mass model (None: no masses).

    Each link's mass and everything outboard of it is moved to the previous link as a
    first moment at this link's origin (see the module docstring); the payload sits at
    the tool point (the description has no separate payload centre of mass).
    """
    joints = description.joints
    if all(j.mass_kg is None for j in joints) and not description.tool.mass_kg:
        return None
    model = KinematicModel.from_description(description)
    n = model.n_joints
    mass = np.array([j.mass_kg or 0.0 for j in joints])
    com = np.array([j.com_mm or (0.0, 0.0, 0.0) for j in joints], dtype=float)
    payload = float(description.tool.mass_kg or 0.0)
    tool = np.asarray(model.tool_mm, dtype=float)
    mu = mass[:, None] * com
    mu[-1] += payload * tool
    outboard = np.cumsum(np.append(mass, payload)[::-1])[::-1]  # M_k = Σ_{i ≥ k} m_i + payload
    consts = model.link_constants()
    for k in range(1, n):  # origin of frame k in frame k-1: a along x, then d along z_k
        origin = np.array([model.a_mm[k], 0.0, 0.0]) + consts[k] @ np.array(
            [0.0, 0.0, model.d_mm[k]]
        )
        mu[k - 1] += outboard[k] * origin
    moments: FloatArray = mu.ravel()
    return moments
