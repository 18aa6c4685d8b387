"""One pose's TCP and identification Jacobian, for the per-check tracker update.

:func:`calibration.model.kinematics.identification_jacobian` is built for many poses at once;
for a single pose most of its time is numpy's per-call overhead on ``(1, n, 3)`` arrays
(``np.cross``'s axis handling, a 3×3 product per link constant). The tracker predicts one
check at a time, so this walks the same chain (modified D-H with Hayati β, fixed-XYZ base
angles, the tool point) once, with the link constants in closed form. The same columns,
the same order, equal to ``identification_jacobian`` to rounding (tested).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product of ``(m, 3)`` arrays (np.cross without its axis handling)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def point_jacobian(model: KinematicModel, q_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The TCP ``(3,)`` mm (world frame) at joints ``(n,)`` rad and ∂TCP/∂parameters
    ``(3, 5n + 9)``, columns as :meth:`KinematicModel.parameter_vector`."""
    n = model.n_joints
    ca, sa = np.cos(model.alpha_rad), np.sin(model.alpha_rad)
    cb, sb = np.cos(model.beta_rad), np.sin(model.beta_rad)
    # Rx(alpha)·Ry(beta) per link, closed form
    consts = np.empty((n, 3, 3))
    consts[:, 0] = np.stack([cb, np.zeros(n), sb], axis=1)
    consts[:, 1] = np.stack([sa * sb, ca, -sa * cb], axis=1)
    consts[:, 2] = np.stack([-ca * sb, sa, ca * cb], axis=1)
    theta = q_rad + model.theta_offset_rad
    ct, st = np.cos(theta), np.sin(theta)
    rot = model.base_rotation()
    pos = model.base_mm.copy()
    x_prev, o_prev, y_a, o_b, z, o = (np.empty((n, 3)) for _ in range(6))
    for i in range(n):
        x_prev[i] = rot[:, 0]
        o_prev[i] = pos
        y_a[i] = ca[i] * rot[:, 1] + sa[i] * rot[:, 2]
        pos = pos + model.a_mm[i] * rot[:, 0]
        o_b[i] = pos
        rot = rot @ consts[i]
        col0 = ct[i] * rot[:, 0] + st[i] * rot[:, 1]
        col1 = ct[i] * rot[:, 1] - st[i] * rot[:, 0]
        rot[:, 0], rot[:, 1] = col0, col1
        pos = pos + model.d_mm[i] * rot[:, 2]
        z[i] = rot[:, 2]
        o[i] = pos
    p = pos + rot @ model.tool_mm
    per_joint = np.empty((n, 5, 3))
    per_joint[:, 0] = x_prev
    per_joint[:, 1] = _cross(x_prev, p - o_prev)
    per_joint[:, 2] = z
    per_joint[:, 3] = _cross(z, p - o)
    per_joint[:, 4] = _cross(y_a, p - o_b)
    jac = np.empty((3, model.n_parameters))
    jac[:, : 5 * n] = per_joint.reshape(5 * n, 3).T
    _, ry, rz = model.base_rad
    cy, sy, cz, sz = np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    # rotation axes of rx, ry, rz in the world: Rz·Ry·x, Rz·y, z
    axes = np.array([[cz * cy, sz * cy, -sy], [-sz, cz, 0.0], [0.0, 0.0, 1.0]])
    off = 5 * n
    jac[:, off : off + 3] = np.eye(3)
    rel = p - model.base_mm
    jac[:, off + 3 : off + 6] = _cross(axes, np.array([rel, rel, rel])).T
    jac[:, off + 6 :] = rot
    return p, jac
