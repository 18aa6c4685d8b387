"""The robot as drawable geometry, from its description: pure numpy, no viewer.

Everything is in the tracker (world) frame in mm, as the twin computes it; the viewer
scales to metres when it draws. Frames follow the description's modified D-H convention
(docs/robot-description.md): frame ``i`` is where link ``i``'s transform ends, so the
link from frame ``i-1`` to frame ``i`` runs first along ``x_{i-1}`` by ``a_i``, then along
``z_i`` by ``d_i``; drawing both legs shows the arm's true shape (a straight line from
origin to origin would cut the corners of the shoulder and the wrist offset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel, flange_poses

FloatArray = NDArray[np.float64]
#: the page's switch for error vectors and the ghost's deviation: drawn this many times
#: larger (the twin's residuals are µm to mm; the arm is metres)
MAGNIFICATIONS = ("100", "1000", "10000")


@dataclass(frozen=True)
class ArmGeometry:
    """One posture of the arm: ``frames`` ``(n + 1, 4, 4)`` (base, then joints 1..n;
    homogeneous, mm), ``polyline`` ``(2n + 2, 3)`` mm through the base, each link's two
    legs and the tool point."""

    frames: FloatArray
    polyline: FloatArray

    @property
    def segments(self) -> FloatArray:
        """The polyline as line segments ``(2n + 1, 2, 3)`` mm (start, end)."""
        return polyline_segments(self.polyline)


def joint_frames(model: KinematicModel, q_deg: ArrayLike) -> FloatArray:
    """Base and joint frames ``(n + 1, 4, 4)`` (mm) of the arm at ``q_deg`` ``(n,)``.

    Frame ``k`` is the flange of the arm cut after joint ``k``
    (:meth:`KinematicModel.truncated` with no tool), so the chain is walked by the
    project's own kinematics.
    """
    q_rad = np.radians(np.asarray(q_deg, dtype=float))
    n = model.n_joints
    if q_rad.shape != (n,):
        raise ValueError(f"q_deg must have shape ({n},), got {q_rad.shape}")
    frames = np.empty((n + 1, 4, 4))
    frames[0] = np.eye(4)
    frames[0, :3, :3] = model.base_rotation()
    frames[0, :3, 3] = model.base_mm
    for k in range(1, n + 1):
        frames[k] = flange_poses(model.truncated(k), q_rad[:k])
    return frames


def arm_geometry(model: KinematicModel, q_deg: ArrayLike) -> ArmGeometry:
    """Frames and link polyline of ``model`` at ``q_deg`` ``(n,)`` (deg)."""
    frames = joint_frames(model, q_deg)
    n = model.n_joints
    points = np.empty((2 * n + 2, 3))
    points[0] = frames[0, :3, 3]
    # the a-leg of link i ends at o_{i-1} + a_i · x_{i-1} (Rot_x and Rot_y keep that point)
    points[1 : 2 * n : 2] = frames[:-1, :3, 3] + model.a_mm[:, None] * frames[:-1, :3, 0]
    points[2 : 2 * n + 1 : 2] = frames[1:, :3, 3]
    points[-1] = frames[-1, :3, :3] @ model.tool_mm + frames[-1, :3, 3]
    return ArmGeometry(frames, points)


def polyline_segments(points: ArrayLike) -> FloatArray:
    """Consecutive points ``(m, 3)`` as segments ``(m - 1, 2, 3)``."""
    p = np.asarray(points, dtype=float)
    return np.stack([p[:-1], p[1:]], axis=1)


def magnified(reference: ArrayLike, other: ArrayLike, factor: float) -> FloatArray:
    """``reference + factor · (other − reference)``, elementwise (same shapes): a small
    deviation drawn ``factor`` times larger, anchored on the reference."""
    r = np.asarray(reference, dtype=float)
    drawn: FloatArray = r + factor * (np.asarray(other, dtype=float) - r)
    return drawn


def error_segments(measured_mm: ArrayLike, twin_mm: ArrayLike, factor: float) -> FloatArray:
    """Error vectors ``(k, 2, 3)`` mm from each measured point toward the twin's point,
    ``factor`` times their length; rows with a NaN are left out."""
    m = np.asarray(measured_mm, dtype=float).reshape(-1, 3)
    t = np.asarray(twin_mm, dtype=float).reshape(-1, 3)
    ok = np.isfinite(m).all(axis=1) & np.isfinite(t).all(axis=1)
    m, t = m[ok], t[ok]
    return np.stack([m, magnified(m, t, factor)], axis=1)


def ghost_model(nominal: RobotDescription, calibrated: RobotDescription) -> KinematicModel:
    """The nominal geometry and tool on the calibrated model's base: the model the
    identification started from, placed where the robot stands (the report's "before")."""
    model = KinematicModel.from_description(nominal)
    placed = KinematicModel.from_description(calibrated)
    if model.n_joints != placed.n_joints:
        raise ValueError(
            f"nominal {nominal.name!r} has {model.n_joints} joints, "
            f"calibrated {calibrated.name!r} {placed.n_joints}"
        )
    return KinematicModel(
        model.a_mm,
        model.alpha_rad,
        model.d_mm,
        model.theta_offset_rad,
        model.beta_rad,
        placed.base_mm,
        placed.base_rad,
        model.tool_mm,
    )


def camera_pose(points_mm: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """A camera position and look-at point (mm) that frame ``points_mm`` ``(m, 3)``:
    looking at their centre from the front-left and above, at 1.7 times their extent."""
    p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    centre = (p.min(axis=0) + p.max(axis=0)) / 2
    extent = max(float(np.ptp(p, axis=0).max()), 500.0)
    direction = np.array([-0.55, -0.65, 0.52])
    return centre + 1.7 * extent * direction / np.linalg.norm(direction), centre
