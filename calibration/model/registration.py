"""Closed-form rigid registration of point sets (Kabsch / Umeyama, without scale).

Used to start the identification when the robot description gives no base guess: the
nominal TCP positions in the robot's base frame are registered onto the tracker points, which
gives the base pose in the tracker frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import RegistrationError
from calibration.model.kinematics import fixed_xyz_from_rotation

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RigidTransform:
    """``target ≈ rotation @ source + translation_mm``; ``rms_mm`` is the residual RMS."""

    rotation: FloatArray  # (3, 3), proper rotation (det +1)
    translation_mm: FloatArray  # (3,)
    rms_mm: float

    def apply(self, points_mm: ArrayLike) -> FloatArray:
        """Transform points ``(N, 3)`` mm from the source frame into the target frame."""
        return np.asarray(points_mm, dtype=float) @ self.rotation.T + self.translation_mm

    def fixed_xyz_rad(self) -> tuple[float, float, float]:
        """The rotation as fixed-axis XYZ angles (rad), the base convention of the model."""
        return fixed_xyz_from_rotation(self.rotation)


def rigid_registration(source_mm: ArrayLike, target_mm: ArrayLike) -> RigidTransform:
    """Least-squares rigid transform mapping ``source`` ``(N, 3)`` onto ``target`` ``(N, 3)``.

    Kabsch's SVD solution with Umeyama's reflection fix. Needs at least three points that
    are not collinear.
    """
    src = np.asarray(source_mm, dtype=float)
    dst = np.asarray(target_mm, dtype=float)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise RegistrationError(
            f"point sets must both have shape (N, 3), got {src.shape} and {dst.shape}"
        )
    if len(src) < 3:
        raise RegistrationError(f"need at least 3 points to register, got {len(src)}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise RegistrationError("point sets contain NaN or infinite values")
    c_src, c_dst = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - c_src, dst - c_dst
    u, _, vt = np.linalg.svd(a.T @ b)
    spread = np.linalg.svd(a, compute_uv=False)
    if spread[1] <= 1e-9 * max(spread[0], 1e-300):
        raise RegistrationError("source points are collinear: the rotation is undetermined")
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    translation = c_dst - rotation @ c_src
    resid = dst - (src @ rotation.T + translation)
    rms = float(np.sqrt(np.mean(np.sum(resid**2, axis=1))))
    return RigidTransform(rotation=rotation, translation_mm=translation, rms_mm=rms)
