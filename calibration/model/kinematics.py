"""Vectorized kinematics of a serial arm in modified D-H with Hayati beta.

Conventions (fixed for the whole project):

* Joint angles are radians inside this module, shape ``(N, n)`` (a single ``(n,)`` vector
  is accepted and the leading axis dropped again on output).
* Lengths are mm. The *world* frame is the measuring instrument's (tracker) frame; the
  robot base sits in it at ``base`` (fixed-axis XYZ angles, R = Rz·Ry·Rx).
* Link i: ``Rot_x(alpha) · Trans_x(a) · Rot_y(beta) · Rot_z(theta + offset) · Trans_z(d)``.
* The model parameter vector (see :data:`PARAMETERS_PER_JOINT`) is, per joint,
  ``a_mm, alpha_rad, d_mm, theta_offset_rad, beta_rad``, then the base
  ``x_mm, y_mm, z_mm, rx_rad, ry_rad, rz_rad``, then the tool ``x_mm, y_mm, z_mm``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import KinematicsError
from calibration.model.description import BaseDescription, RobotDescription, ToolDescription

FloatArray = NDArray[np.float64]

PARAMETERS_PER_JOINT: tuple[str, ...] = (
    "a_mm",
    "alpha_rad",
    "d_mm",
    "theta_offset_rad",
    "beta_rad",
)
BASE_PARAMETERS: tuple[str, ...] = ("x_mm", "y_mm", "z_mm", "rx_rad", "ry_rad", "rz_rad")
TOOL_PARAMETERS: tuple[str, ...] = ("x_mm", "y_mm", "z_mm")


def rot_x(angle: float) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_fixed_xyz(rx: float, ry: float, rz: float) -> FloatArray:
    """Rotation matrix of fixed-axis XYZ angles (rad): R = Rz(rz) · Ry(ry) · Rx(rx)."""
    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)


def fixed_xyz_from_rotation(r: FloatArray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_fixed_xyz` (rad); ry in [-pi/2, pi/2]."""
    ry = float(np.arctan2(-r[2, 0], np.hypot(r[0, 0], r[1, 0])))  # exact near ±90° too
    rx = float(np.arctan2(r[2, 1], r[2, 2]))
    rz = float(np.arctan2(r[1, 0], r[0, 0]))
    return rx, ry, rz


@dataclass(frozen=True, eq=False)
class KinematicModel:
    """Numeric kinematic parameters of an n-joint arm (mm, rad), arrays of shape ``(n,)``."""

    a_mm: FloatArray
    alpha_rad: FloatArray
    d_mm: FloatArray
    theta_offset_rad: FloatArray
    beta_rad: FloatArray
    base_mm: FloatArray  # (3,) base origin in the world frame
    base_rad: FloatArray  # (3,) fixed-axis XYZ angles of the base
    tool_mm: FloatArray  # (3,) target in the flange frame

    @property
    def n_joints(self) -> int:
        return int(self.a_mm.shape[0])

    @property
    def n_parameters(self) -> int:
        return len(PARAMETERS_PER_JOINT) * self.n_joints + 9

    @classmethod
    def from_description(cls, desc: RobotDescription) -> KinematicModel:
        j = desc.joints
        base = desc.base or BaseDescription()
        return cls(
            a_mm=np.array([x.a_mm for x in j]),
            alpha_rad=np.radians([x.alpha_deg for x in j]),
            d_mm=np.array([x.d_mm for x in j]),
            theta_offset_rad=np.radians([x.theta_offset_deg for x in j]),
            beta_rad=np.radians([x.beta_deg for x in j]),
            base_mm=np.array([base.x_mm, base.y_mm, base.z_mm]),
            base_rad=np.radians([base.rx_deg, base.ry_deg, base.rz_deg]),
            tool_mm=np.array([desc.tool.x_mm, desc.tool.y_mm, desc.tool.z_mm]),
        )

    def to_description(self, template: RobotDescription) -> RobotDescription:
        """The template description with this model's geometry written in (mm, degrees)."""
        if template.n_joints != self.n_joints:
            raise KinematicsError(
                f"template has {template.n_joints} joints, model has {self.n_joints}"
            )
        joints = tuple(
            replace(
                j,
                a_mm=float(self.a_mm[i]),
                alpha_deg=float(np.degrees(self.alpha_rad[i])),
                d_mm=float(self.d_mm[i]),
                theta_offset_deg=float(np.degrees(self.theta_offset_rad[i])),
                beta_deg=float(np.degrees(self.beta_rad[i])),
            )
            for i, j in enumerate(template.joints)
        )
        bx, by, bz = (float(v) for v in self.base_mm)
        rx, ry, rz = (float(v) for v in np.degrees(self.base_rad))
        tx, ty, tz = (float(v) for v in self.tool_mm)
        return replace(
            template,
            joints=joints,
            base=BaseDescription(
                bx, by, bz, rx, ry, rz, template.base.gravity if template.base else None
            ),
            tool=ToolDescription(tx, ty, tz, template.tool.mass_kg),
        )

    def parameter_names(self) -> list[str]:
        names = [f"joint{i + 1}.{p}" for i in range(self.n_joints) for p in PARAMETERS_PER_JOINT]
        names += [f"base.{p}" for p in BASE_PARAMETERS]
        names += [f"tool.{p}" for p in TOOL_PARAMETERS]
        return names

    def parameter_vector(self) -> FloatArray:
        """All parameters as one vector of shape ``(5n + 9,)`` in mm and rad."""
        per_joint = np.stack(
            [self.a_mm, self.alpha_rad, self.d_mm, self.theta_offset_rad, self.beta_rad], axis=1
        )
        return np.concatenate([per_joint.ravel(), self.base_mm, self.base_rad, self.tool_mm])

    def with_parameters(self, x: ArrayLike) -> KinematicModel:
        """A new model from a parameter vector laid out as :meth:`parameter_vector`."""
        x = np.asarray(x, dtype=float)
        if x.shape != (self.n_parameters,):
            raise KinematicsError(f"parameter vector must have shape ({self.n_parameters},)")
        n = self.n_joints
        per_joint = x[: 5 * n].reshape(n, 5)
        return KinematicModel(
            a_mm=per_joint[:, 0].copy(),
            alpha_rad=per_joint[:, 1].copy(),
            d_mm=per_joint[:, 2].copy(),
            theta_offset_rad=per_joint[:, 3].copy(),
            beta_rad=per_joint[:, 4].copy(),
            base_mm=x[5 * n : 5 * n + 3].copy(),
            base_rad=x[5 * n + 3 : 5 * n + 6].copy(),
            tool_mm=x[5 * n + 6 :].copy(),
        )

    def truncated(self, n_joints: int, tool_mm: ArrayLike = (0.0, 0.0, 0.0)) -> KinematicModel:
        """The first ``n_joints`` links with a point ``tool_mm`` fixed in the last one's frame.

        Used for targets mounted on an intermediate link (scale calibration sweeps).
        """
        if not 1 <= n_joints <= self.n_joints:
            raise KinematicsError(f"n_joints must be in 1..{self.n_joints}, got {n_joints}")
        k = slice(0, n_joints)
        return KinematicModel(
            a_mm=self.a_mm[k].copy(),
            alpha_rad=self.alpha_rad[k].copy(),
            d_mm=self.d_mm[k].copy(),
            theta_offset_rad=self.theta_offset_rad[k].copy(),
            beta_rad=self.beta_rad[k].copy(),
            base_mm=self.base_mm.copy(),
            base_rad=self.base_rad.copy(),
            tool_mm=np.asarray(tool_mm, dtype=float).copy(),
        )

    def base_rotation(self) -> FloatArray:
        return rotation_from_fixed_xyz(*self.base_rad)

    def link_constants(self) -> FloatArray:
        """Per-link constant rotation Rx(alpha)·Ry(beta), shape ``(n, 3, 3)``."""
        return np.stack(
            [rot_x(al) @ rot_y(be) for al, be in zip(self.alpha_rad, self.beta_rad, strict=True)]
        )


def _as_joint_array(model: KinematicModel, q_rad: ArrayLike) -> tuple[FloatArray, bool]:
    q = np.asarray(q_rad, dtype=float)
    single = q.ndim == 1
    q = np.atleast_2d(q)
    if q.ndim != 2 or q.shape[1] != model.n_joints:
        raise KinematicsError(
            f"joint array must have shape (N, {model.n_joints}) or ({model.n_joints},), "
            f"got {np.shape(q_rad)}"
        )
    return q, single


def _chain(
    model: KinematicModel, q: FloatArray, *, world: bool, keep_frames: bool
) -> tuple[FloatArray, FloatArray, dict[str, FloatArray] | None]:
    """Walk the chain for all poses at once.

    Returns the flange rotation ``(N,3,3)`` and origin ``(N,3)``; with ``keep_frames`` also
    the per-joint axes and points the Jacobians need, each ``(N, n, 3)``.
    """
    n_pose, n = q.shape
    if world:
        rot = np.broadcast_to(model.base_rotation(), (n_pose, 3, 3)).copy()
        pos = np.broadcast_to(model.base_mm, (n_pose, 3)).copy()
    else:
        rot = np.broadcast_to(np.eye(3), (n_pose, 3, 3)).copy()
        pos = np.zeros((n_pose, 3))
    frames = None
    if keep_frames:
        frames = {k: np.empty((n_pose, n, 3)) for k in ("x_prev", "o_prev", "y_a", "o_b", "z", "o")}
    theta = q + model.theta_offset_rad
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    consts = model.link_constants()
    for i in range(n):
        if frames is not None:
            frames["x_prev"][:, i] = rot[:, :, 0]
            frames["o_prev"][:, i] = pos
            # y axis after Rot_x(alpha): cos(alpha)·y_prev + sin(alpha)·z_prev
            ca, sa = np.cos(model.alpha_rad[i]), np.sin(model.alpha_rad[i])
            frames["y_a"][:, i] = ca * rot[:, :, 1] + sa * rot[:, :, 2]
        pos = pos + model.a_mm[i] * rot[:, :, 0]
        if frames is not None:
            frames["o_b"][:, i] = pos
        rot = rot @ consts[i]
        c, s = cos_t[:, i, None], sin_t[:, i, None]
        col0 = c * rot[:, :, 0] + s * rot[:, :, 1]
        col1 = c * rot[:, :, 1] - s * rot[:, :, 0]
        rot[:, :, 0], rot[:, :, 1] = col0, col1
        pos = pos + model.d_mm[i] * rot[:, :, 2]
        if frames is not None:
            frames["z"][:, i] = rot[:, :, 2]
            frames["o"][:, i] = pos
    return rot, pos, frames


def flange_poses(model: KinematicModel, q_rad: ArrayLike, *, world: bool = True) -> FloatArray:
    """Homogeneous flange poses, ``(N, 4, 4)`` (mm), in the world frame or the base frame."""
    q, single = _as_joint_array(model, q_rad)
    rot, pos, _ = _chain(model, q, world=world, keep_frames=False)
    out = np.zeros((q.shape[0], 4, 4))
    out[:, :3, :3] = rot
    out[:, :3, 3] = pos
    out[:, 3, 3] = 1.0
    return out[0] if single else out


def tcp_positions(model: KinematicModel, q_rad: ArrayLike, *, world: bool = True) -> FloatArray:
    """Tracker-target (TCP) positions ``(N, 3)`` in mm, world frame by default."""
    q, single = _as_joint_array(model, q_rad)
    rot, pos, _ = _chain(model, q, world=world, keep_frames=False)
    tcp = pos + rot @ model.tool_mm
    return tcp[0] if single else tcp


def geometric_jacobian(
    model: KinematicModel,
    q_rad: ArrayLike,
    *,
    point: Literal["tcp", "flange"] = "tcp",
    frame: Literal["world", "base"] = "base",
) -> FloatArray:
    """Geometric Jacobian ``(N, 6, n)``: rows vx, vy, vz (mm/rad) then wx, wy, wz (rad/rad).

    Velocity of ``point`` and angular velocity of the flange, expressed in ``frame``.
    """
    q, single = _as_joint_array(model, q_rad)
    rot, pos, fr = _chain(model, q, world=(frame == "world"), keep_frames=True)
    assert fr is not None
    p = pos + rot @ model.tool_mm if point == "tcp" else pos
    z, o = fr["z"], fr["o"]
    jac = np.empty((q.shape[0], 6, model.n_joints))
    jac[:, :3, :] = np.cross(z, p[:, None, :] - o).transpose(0, 2, 1)
    jac[:, 3:, :] = z.transpose(0, 2, 1)
    return jac[0] if single else jac


def identification_jacobian(
    model: KinematicModel, q_rad: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """TCP positions ``(N, 3)`` and ∂TCP/∂parameters ``(N, 3, 5n + 9)`` (world frame, analytic).

    Columns follow :meth:`KinematicModel.parameter_vector` (mm and rad).
    """
    q, single = _as_joint_array(model, q_rad)
    rot, pos, fr = _chain(model, q, world=True, keep_frames=True)
    assert fr is not None
    p = pos + rot @ model.tool_mm
    n_pose, n = q.shape
    rel = p[:, None, :]
    per_joint = np.empty((n_pose, n, 5, 3))
    per_joint[:, :, 0] = fr["x_prev"]  # a: translation along x_{i-1}
    per_joint[:, :, 1] = np.cross(fr["x_prev"], rel - fr["o_prev"])  # alpha
    per_joint[:, :, 2] = fr["z"]  # d: translation along z_i
    per_joint[:, :, 3] = np.cross(fr["z"], rel - fr["o"])  # theta offset
    per_joint[:, :, 4] = np.cross(fr["y_a"], rel - fr["o_b"])  # beta
    jac = np.empty((n_pose, 3, model.n_parameters))
    jac[:, :, : 5 * n] = per_joint.reshape(n_pose, 5 * n, 3).transpose(0, 2, 1)

    _, ry, rz = model.base_rad
    rz_m = rot_z(rz)
    axes = np.stack([rz_m @ rot_y(ry) @ np.array([1.0, 0, 0]), rz_m @ np.array([0, 1.0, 0])])
    axes = np.vstack([axes, [0.0, 0.0, 1.0]])  # rx, ry, rz rotation axes in the world
    off = 5 * n
    jac[:, :, off : off + 3] = np.eye(3)
    jac[:, :, off + 3 : off + 6] = np.cross(
        axes[None, :, :], (p - model.base_mm)[:, None, :]
    ).transpose(0, 2, 1)
    jac[:, :, off + 6 :] = rot
    return (p[0], jac[0]) if single else (p, jac)


def nearly_parallel_joints(model: KinematicModel, tol_deg: float = 5.0) -> NDArray[np.bool_]:
    """Joints whose axis is nearly parallel to the previous one, shape ``(n,)``.

    These carry the Hayati ``beta``; their ``d`` is then redundant and held at its value.
    Joint 1 is never flagged (its predecessor is the base, which has its own parameters).
    """
    alpha = np.abs(np.degrees(np.asarray(model.alpha_rad)) % 180.0)
    flags = np.minimum(alpha, 180.0 - alpha) < tol_deg
    flags[0] = False
    return flags
