"""Polishing inverse-kinematics solutions on a calibrated model: Levenberg-Marquardt on
the geometric Jacobian over the flange's position (mm) and rotation-vector (rad) error,
vectorised over the poses."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calibration.model.kinematics import (
    FloatArray,
    KinematicModel,
    flange_poses,
    geometric_jacobian,
)

BoolArray = NDArray[np.bool_]


# Smallest Levenberg damping, relative to the trace of the normal matrix: keeps the solve
# defined at an exact singularity without slowing Newton's convergence elsewhere.
_MU_MIN = 1e-12


# Damping after a rejected step: skip the useless decades between _MU_MIN and real damping.
_MU_REJECTED = 1e-6


# Length (mm) that makes one radian of orientation error weigh like this many mm.
_ORIENTATION_SCALE_MM = 1000.0


def rotation_error(r_target: FloatArray, r: FloatArray) -> FloatArray:
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


def pose_error(
    model: KinematicModel, q: FloatArray, rot: FloatArray, pos: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Flange position error (mm) and rotation error vector (rad), each ``(M, 3)``."""
    t = flange_poses(model, q, world=False)
    return pos - t[:, :3, 3], rotation_error(rot, t[:, :3, :3])


def refine(
    model: KinematicModel,
    q: FloatArray,
    rot: FloatArray,
    pos: FloatArray,
    *,
    tol_mm: float,
    tol_rad: float,
    max_iterations: int,
) -> tuple[FloatArray, BoolArray, NDArray[np.int_]]:
    """Levenberg-Marquardt on the model's geometric Jacobian, flattened solutions ``(M, n)``.

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
        normal += (mu[idx] * np.trace(normal, axis1=1, axis2=2))[:, None, None] * np.eye(q.shape[1])
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
    dp, dr = pose_error(model, q, rot, pos)
    return np.concatenate([dp, dr], axis=1)
