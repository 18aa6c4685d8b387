"""The closed-form inverse kinematics of a Pieper arm (three intersecting wrist axes):
whether a model is one, its spherical approximation, and the eight branches' joint
angles (shoulder, elbow, wrist) of flange poses, vectorised over the poses. Angles in
rad, lengths in mm."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import KinematicsError
from calibration.model.ik_results import LIMIT_SLACK_RAD, JointLimits
from calibration.model.kinematics import (
    FloatArray,
    KinematicModel,
    rot_x,
)

BoolArray = NDArray[np.bool_]


N_BRANCHES = 8
BRANCH_SIGNS: NDArray[np.int_] = np.array(
    [[s, e, w] for s in (1, -1) for e in (1, -1) for w in (1, -1)], dtype=int
)
"""Signs (shoulder, elbow, wrist) of each branch, shape ``(8, 3)``."""
BRANCHES: tuple[str, ...] = tuple(
    "shoulder{} elbow{} wrist{}".format(*("+" if v > 0 else "-" for v in row))
    for row in BRANCH_SIGNS
)


# A 2-vector shorter than this (unitless, the rows of a rotation matrix) has no direction:
# the wrist is exactly singular and q4 is taken from the reference vector.
WRIST_DEGENERATE = 1e-12


# Wrist centre closer than this to axis 1 (mm) with no lateral offset: q1 from the reference.
SHOULDER_DEGENERATE_MM = 1e-9


# Relative slack on the elbow's law-of-cosines argument before a pose counts unreachable.
ELBOW_SLACK = 1e-12


# Seeding a calibrated model: the nominal law-of-cosines argument may exceed 1 by this much
# (a few mm beyond the nominal reach), the seed elbow stays 2° off stretched/folded and the
# seed wrist centre 1 mm off the shoulder-singular surface, so that branches stay apart.
SEED_ELBOW_SLACK = 0.02


SEED_SHOULDER_MM = 1.0


SEED_ELBOW_COS = float(np.cos(np.radians(2.0)))


ANGLE_TOL = 1e-9  # tolerance on the structural angles of a Pieper geometry (rad)


# -- geometry ---------------------------------------------------------------------------
def _turn_z(x: FloatArray, angle: FloatArray) -> FloatArray:
    """``Rz(angle)ᵀ · x`` for stacked 3×3 ``x`` ``(..., 3, 3)`` and ``angle`` ``(...)``.

    Row arithmetic instead of stacked matmuls: several times faster for 3×3 stacks.
    """
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    x0, x1, x2 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
    return np.stack(np.broadcast_arrays(c * x0 + s * x1, c * x1 - s * x0, x2), axis=-2)


def _turn_x(x: FloatArray, angle: float) -> FloatArray:
    """``Rx(angle)ᵀ · x`` for stacked 3×3 ``x`` ``(..., 3, 3)``."""
    c, s = np.cos(angle), np.sin(angle)
    x0, x1, x2 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
    return np.stack([x0, c * x1 + s * x2, c * x2 - s * x1], axis=-2)


def pieper_violations(model: KinematicModel) -> list[str]:
    """Why ``model`` is not a Pieper arm (empty list when it is)."""
    if model.n_joints != 6:
        return [f"needs 6 joints, has {model.n_joints}"]
    out = []
    al, a, d = model.alpha_rad, model.a_mm, model.d_mm
    if np.any(np.abs(model.beta_rad) > ANGLE_TOL):
        out.append("every beta must be 0")
    if abs(np.sin(al[2])) > ANGLE_TOL or np.cos(al[2]) < 0:
        out.append("alpha3 must be 0 (joints 2 and 3 parallel)")
    for i in (1, 3, 4, 5):
        if abs(np.cos(al[i])) > ANGLE_TOL:
            out.append(f"alpha{i + 1} must be ±90°")
    if abs(a[4]) > 0 or abs(a[5]) > 0 or abs(d[4]) > 0:
        out.append("a5, a6 and d5 must be 0 (wrist axes must meet in one point)")
    if a[2] <= 0 or np.hypot(a[3], d[3]) <= 0:
        out.append("upper arm a3 and forearm (a4, d4) must have length")
    return out


def is_spherical_wrist(model: KinematicModel) -> bool:
    """Whether the closed form applies exactly to ``model`` (see the module docstring)."""
    return not pieper_violations(model)


def spherical_approximation(model: KinematicModel) -> KinematicModel:
    """The nearest Pieper geometry: betas, a5, a6, d5 zeroed, alphas snapped to 0/±90°.

    Used as the nominal geometry of a calibrated model whose own geometry is not exactly
    spherical; base and tool are kept.
    """
    if model.n_joints != 6:
        raise KinematicsError(f"closed-form IK needs 6 joints, model has {model.n_joints}")
    x = model.parameter_vector().copy()
    per_joint = x[:30].reshape(6, 5)
    per_joint[:, 1] = np.round(per_joint[:, 1] / (np.pi / 2)) * (np.pi / 2)
    per_joint[:, 4] = 0.0
    per_joint[4, 0] = per_joint[5, 0] = per_joint[4, 2] = 0.0
    approx = model.with_parameters(x)
    problems = pieper_violations(approx)
    if problems:
        raise KinematicsError("no spherical-wrist approximation: " + "; ".join(problems))
    return approx


def has_spherical_approximation(model: KinematicModel) -> bool:
    """Whether :func:`spherical_approximation` exists for ``model``: the closed form can
    seed its inverse kinematics (not so for an arm whose wrist axes are far from meeting,
    such as the UR family's)."""
    try:
        spherical_approximation(model)
    except KinematicsError:
        return False
    return True


@dataclass(frozen=True, eq=False)
class PieperGeometry:
    """Constants of the closed form, derived from a Pieper model (mm, rad)."""

    pre_rot: FloatArray  # Rx(alpha1), (3, 3)
    a0: float
    d0: float
    s1: float  # sin(alpha2) = ±1
    a1: float
    h: float  # lateral offset of the wrist centre from the arm plane
    a2: float
    forearm: float  # L: distance axis 3 -> wrist centre, projected on the arm plane
    phi: float  # angle of the forearm in frame 3
    sigma4: float  # sin(alpha5) = ±1
    kappa: float  # +1 when alpha5 + alpha6 = 0, -1 when it is ±180°
    post_rot: FloatArray  # Rx(alpha5 + alpha6)
    d_flange: float
    offsets: FloatArray  # (6,)
    alpha: FloatArray  # (6,)

    @classmethod
    def of(cls, model: KinematicModel) -> PieperGeometry:
        problems = pieper_violations(model)
        if problems:
            raise KinematicsError("not a spherical-wrist geometry: " + "; ".join(problems))
        al, a, d = model.alpha_rad, model.a_mm, model.d_mm
        w3 = np.array([a[3], -np.sin(al[3]) * d[3], np.cos(al[3]) * d[3]])
        return cls(
            pre_rot=rot_x(al[0]),
            a0=float(a[0]),
            d0=float(d[0]),
            s1=float(np.round(np.sin(al[1]))),
            a1=float(a[1]),
            h=float(d[1] + d[2] + w3[2]),
            a2=float(a[2]),
            forearm=float(np.hypot(w3[0], w3[1])),
            phi=float(np.arctan2(w3[1], w3[0])),
            sigma4=float(np.round(np.sin(al[4]))),
            kappa=1.0 if np.cos(al[4] + al[5]) > 0 else -1.0,
            post_rot=rot_x(al[4] + al[5]),
            d_flange=float(d[5]),
            offsets=model.theta_offset_rad.copy(),
            alpha=model.alpha_rad.copy(),
        )

    def elbow_angle(self, q3: FloatArray) -> FloatArray:
        """psi: angle between upper arm and the forearm's projection (0 = stretched)."""
        elbow: FloatArray = q3 + self.offsets[2] + self.phi
        return elbow

    def shoulder_distance(self, q2: FloatArray, psi: FloatArray) -> FloatArray:
        """Signed distance r of the wrist centre from axis 1 in the arm plane (mm)."""
        w2x = self.a2 + self.forearm * np.cos(psi)
        w2y = self.forearm * np.sin(psi)
        t2 = q2 + self.offsets[1]
        dist: FloatArray = self.a1 + np.cos(t2) * w2x - np.sin(t2) * w2y
        return dist


def closed_form(
    geo: PieperGeometry, rot: FloatArray, pos: FloatArray, q_ref: FloatArray, *, seed: bool = False
) -> tuple[FloatArray, BoolArray]:
    """All 8 branches for flange poses in the base frame.

    ``rot`` ``(N, 3, 3)``, ``pos`` ``(N, 3)`` mm, ``q_ref`` ``(N, 6)`` rad (used only where
    q1 or q4 is undetermined). Returns joint angles ``(N, 8, 6)`` in [-π, π) and the
    reachable mask ``(N, 8)``. With ``seed`` the result starts a numeric solve on a
    slightly different geometry: poses just out of the nominal reach still get a start,
    and the elbow is kept off stretched/folded so that both elbow branches stay apart.
    """
    sh, el, wr = (BRANCH_SIGNS[None, :, k].astype(float) for k in range(3))
    # Wrist centre, in the frame after Rx(alpha1)·Trans_x(a1) and before Rot_z(theta1).
    w = pos - geo.d_flange * rot[:, :, 2]
    v = w @ geo.pre_rot - np.array([geo.a0, 0.0, geo.d0])
    t1, ux, uy, shoulder_ok = _shoulder(geo, v, sh, q_ref, seed=seed)
    t2, t3, elbow_ok = _elbow(geo, ux, uy, el, seed=seed)
    t4, t5, t6 = _wrist(geo, rot, (t1, t2, t3), wr, q_ref)
    theta = np.stack(np.broadcast_arrays(t1, t2, t3, t4, t5, t6), axis=-1)
    q = wrap_angle(theta - geo.offsets)
    reachable = shoulder_ok & elbow_ok & np.all(np.isfinite(q), axis=-1)
    return np.where(reachable[..., None], q, np.nan), reachable


def _shoulder(
    geo: PieperGeometry, v: FloatArray, sh: FloatArray, q_ref: FloatArray, *, seed: bool
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """θ1 ``(N, 8)`` from the wrist centre ``v`` ``(N, 3)`` mm (frame of
    :func:`closed_form`) for the shoulder signs ``sh`` ``(1, 8)``: Rz(t1)·(r, -s1·h) =
    (vx, vy), two signs of r. Also the wrist centre in the arm plane ``(ux, uy)`` mm
    and whether the shoulder reaches it."""
    vx, vy, vz = (v[:, k, None] for k in range(3))
    rho2 = vx**2 + vy**2
    r2 = rho2 - geo.h**2
    shoulder_ok = r2 >= -1e-9 * max(geo.h**2, 1.0)
    if seed:  # a lateral offset may differ on the real geometry: keep the branches apart
        r2 = np.maximum(r2, SEED_SHOULDER_MM**2)
        shoulder_ok = np.ones_like(shoulder_ok)
    r = sh * np.sqrt(np.maximum(r2, 0.0))
    t1 = np.arctan2(vy, vx) - np.arctan2(-geo.s1 * geo.h, r)
    t1 = np.where(np.sqrt(rho2) < SHOULDER_DEGENERATE_MM, q_ref[:, :1] + geo.offsets[0], t1)
    c1, s1 = np.cos(t1), np.sin(t1)
    r = c1 * vx + s1 * vy  # consistent with the t1 actually used
    ux, uy = r - geo.a1, np.broadcast_to(geo.s1 * vz, r.shape)
    return t1, ux, uy, shoulder_ok


def _elbow(
    geo: PieperGeometry, ux: FloatArray, uy: FloatArray, el: FloatArray, *, seed: bool
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """θ2, θ3 ``(N, 8)`` for the elbow signs ``el`` ``(1, 8)``: the law of cosines in the
    arm plane, psi = t3 + phi; and whether the elbow reaches."""
    cpsi = (ux**2 + uy**2 - geo.a2**2 - geo.forearm**2) / (2.0 * geo.a2 * geo.forearm)
    elbow_ok = np.abs(cpsi) <= 1.0 + (SEED_ELBOW_SLACK if seed else ELBOW_SLACK)
    cpsi = np.clip(cpsi, -1.0, 1.0)
    if seed:
        cpsi = np.clip(cpsi, -SEED_ELBOW_COS, SEED_ELBOW_COS)
    spsi = el * np.sqrt(1.0 - cpsi**2)
    t3 = np.arctan2(spsi, cpsi) - geo.phi
    w2x, w2y = geo.a2 + geo.forearm * cpsi, geo.forearm * spsi
    t2 = np.arctan2(uy, ux) - np.arctan2(w2y, w2x)
    return t2, t3, elbow_ok


def _wrist(
    geo: PieperGeometry,
    rot: FloatArray,
    arm: tuple[FloatArray, FloatArray, FloatArray],
    wr: FloatArray,
    q_ref: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """θ4, θ5, θ6 ``(N, 8)`` for the flange rotations ``rot`` ``(N, 3, 3)``, the arm's θ1–θ3
    ``arm`` and the wrist signs ``wr`` ``(1, 8)``:

        E = (R03·Rx(alpha4))ᵀ · R · Rx(alpha5 + alpha6)ᵀ
          = Rz(t4) · Ry(-sigma4·t5) · Rz(kappa·t6)   (ZYZ Euler angles),

    with R03 = Rx(alpha1)·Rz(t1)·Rx(alpha2)·Rz(t2 + t3) since alpha3 = 0.
    """
    t1, t2, t3 = arm
    e = geo.pre_rot.T @ rot @ geo.post_rot.T
    e = _turn_z(e[:, None], t1)
    e = _turn_x(e, geo.alpha[1])
    e = _turn_z(e, t2 + t3)
    e = _turn_x(e, geo.alpha[3])
    e02, e12 = e[..., 0, 2], e[..., 1, 2]
    flip = -geo.sigma4 * wr  # sign of B = -sigma4·t5 that makes sign(sin t5) = wr
    t4 = np.arctan2(flip * e12, flip * e02)
    t4 = np.where(np.hypot(e02, e12) < WRIST_DEGENERATE, q_ref[:, 3:4] + geo.offsets[3], t4)
    f = _turn_z(e, t4)  # = Ry(B)·Rz(G), exact for any t4
    b = np.arctan2(f[..., 0, 2], f[..., 2, 2])
    g = np.arctan2(f[..., 1, 0], f[..., 1, 1])
    return t4, -geo.sigma4 * b, geo.kappa * g


def wrap_angle(q: FloatArray) -> FloatArray:
    """Angles to [-π, π)."""
    return (q + np.pi) % (2.0 * np.pi) - np.pi


def nearest_equivalent(
    q_rad: ArrayLike, q_ref_rad: ArrayLike, limits: JointLimits | None = None
) -> tuple[FloatArray, BoolArray]:
    """Per joint, the 2π-equivalent of ``q_rad`` within limits nearest ``q_ref_rad``.

    Shapes broadcast (``(..., n)``). Returns the joint vectors and, per vector, whether
    every joint has an equivalent within the limits (joints without one keep the
    equivalent nearest the reference, outside the limits).
    """
    q = np.asarray(q_rad, dtype=float)
    ref = np.asarray(q_ref_rad, dtype=float)
    two_pi = 2.0 * np.pi
    k = np.round((ref - q) / two_pi)
    if limits is None:
        return q + two_pi * k, np.all(np.isfinite(q), axis=-1)
    k_min = np.ceil((limits.lower_rad - LIMIT_SLACK_RAD - q) / two_pi)
    k_max = np.floor((limits.upper_rad + LIMIT_SLACK_RAD - q) / two_pi)
    inside = k_min <= k_max
    k = np.where(inside, np.clip(k, k_min, k_max), k)
    return q + two_pi * k, np.all(inside, axis=-1)
