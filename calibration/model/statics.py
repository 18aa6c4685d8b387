"""Joint gravity torques from a robot description's mass model (vectorized over poses).

Mass model: link i (frame i of the D-H chain, i.e. after joint i's rotation and its ``d``
translation) carries ``mass_kg`` at ``com_mm`` given in frame i; the tool carries
``tool.mass_kg`` at the tool point ``(x_mm, y_mm, z_mm)`` of the flange frame. Links
without a mass model weigh nothing. Gravity acts along ``-z`` of the robot base frame.

Sign: ``tau[:, j]`` is the torque (N·mm) that gravity exerts on everything outboard of
joint j, about joint j's axis ``z_j``. A joint of stiffness ``K_j`` (N·mm/rad) holding
that load deflects by ``tau_j / K_j`` rad in the joint's positive sense.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import KinematicsError
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]

STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True, eq=False)
class MassModel:
    """Link masses ``(n,)`` kg, centres of mass ``(n, 3)`` mm in each link frame, tool."""

    mass_kg: FloatArray
    com_mm: FloatArray
    tool_mass_kg: float
    tool_mm: FloatArray

    @classmethod
    def from_description(cls, desc: RobotDescription) -> MassModel:
        mass = np.array([j.mass_kg or 0.0 for j in desc.joints], dtype=float)
        com = np.array([j.com_mm or (0.0, 0.0, 0.0) for j in desc.joints], dtype=float)
        tool = np.array([desc.tool.x_mm, desc.tool.y_mm, desc.tool.z_mm], dtype=float)
        return cls(mass, com, float(desc.tool.mass_kg or 0.0), tool)

    @property
    def total_mass_kg(self) -> float:
        return float(self.mass_kg.sum() + self.tool_mass_kg)


def gravity_torques_nmm(
    model: KinematicModel,
    masses: MassModel,
    q_rad: ArrayLike,
    *,
    gravity_m_s2: float = STANDARD_GRAVITY_M_S2,
) -> FloatArray:
    """Gravity torque about each joint axis, ``(N, n)`` N·mm, for joints ``(N, n)`` rad.

    A single joint vector ``(n,)`` gives ``(n,)``. Computed in the robot base frame (the
    base pose in the tracker frame does not matter: gravity is along the base's -z).
    """
    q = np.asarray(q_rad, dtype=float)
    single = q.ndim == 1
    q = np.atleast_2d(q)
    n = model.n_joints
    if q.ndim != 2 or q.shape[1] != n:
        raise KinematicsError(f"joint array must have shape (N, {n}) or ({n},), got {q.shape}")
    if masses.mass_kg.shape != (n,):
        raise KinematicsError(f"mass model has {masses.mass_kg.shape[0]} links, robot has {n}")
    n_pose = q.shape[0]
    rot = np.broadcast_to(np.eye(3), (n_pose, 3, 3)).copy()
    pos = np.zeros((n_pose, 3))
    z_axes = np.empty((n_pose, n, 3))
    origins = np.empty((n_pose, n, 3))
    mc = np.empty((n_pose, n + 1, 3))  # mass · centre-of-mass position (kg·mm), base frame
    theta = q + model.theta_offset_rad
    consts = model.link_constants()
    for i in range(n):
        pos = pos + model.a_mm[i] * rot[:, :, 0]
        rot = rot @ consts[i]
        c, s = np.cos(theta[:, i])[:, None], np.sin(theta[:, i])[:, None]
        col0 = c * rot[:, :, 0] + s * rot[:, :, 1]
        col1 = c * rot[:, :, 1] - s * rot[:, :, 0]
        rot[:, :, 0], rot[:, :, 1] = col0, col1
        pos = pos + model.d_mm[i] * rot[:, :, 2]
        z_axes[:, i] = rot[:, :, 2]
        origins[:, i] = pos
        mc[:, i] = masses.mass_kg[i] * (pos + rot @ masses.com_mm[i])
    mc[:, n] = masses.tool_mass_kg * (pos + rot @ masses.tool_mm)
    all_mass = np.append(masses.mass_kg, masses.tool_mass_kg)
    # outboard sums: S_j = Σ_{i≥j} m_i c_i, M_j = Σ_{i≥j} m_i (tool included)
    s_out = np.cumsum(mc[:, ::-1], axis=1)[:, ::-1][:, :n]
    m_out = np.cumsum(all_mass[::-1])[::-1][:n]
    g = np.array([0.0, 0.0, -gravity_m_s2])  # N per kg
    lever = s_out - m_out[None, :, None] * origins  # kg·mm
    torque = np.einsum("pjk,pjk->pj", z_axes, np.cross(lever, g))
    result: FloatArray = torque[0] if single else torque
    return result


def gravity_torques_for(desc: RobotDescription, q_rad: ArrayLike) -> FloatArray:
    """Convenience: :func:`gravity_torques_nmm` straight from a description."""
    return gravity_torques_nmm(
        KinematicModel.from_description(desc), MassModel.from_description(desc), q_rad
    )


def torsion_rad(torque_nmm: ArrayLike, stiffness_nmm_per_rad: ArrayLike) -> FloatArray:
    """Joint deflection ``tau / K`` (rad), broadcasting ``(N, n)`` over ``(n,)``."""
    k = np.asarray(stiffness_nmm_per_rad, dtype=float)
    if np.any(k <= 0):
        raise KinematicsError("joint stiffness must be positive (N·mm/rad)")
    twist: FloatArray = np.asarray(torque_nmm, dtype=float) / k
    return twist
