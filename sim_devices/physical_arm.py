"""The emulated arm's statics: its own masses, its counterbalance, its joint torques.

One implementation for everything in the emulator that needs the load on a joint: the
live plant's gear torsion and backlash flank (:mod:`sim_devices.plant`), the undeclared
deflection after the grating ring (:mod:`sim_devices.effects`), the static scale campaign
(:mod:`sim_devices.scale_campaign`) and the pose campaign. The parameters are the
emulator's own (:mod:`sim_devices.arm_masses`, :mod:`sim_devices.counterbalance`); the
twin is never given them, and this module does not use the twin's statics.

Frames: the true modified D-H chain (:class:`calibration.model.kinematics.KinematicModel`, the
forward kinematics the emulator shares with the twin) in the robot base frame; gravity
along −z of that frame. Sign: ``tau[:, j]`` is the torque (N·mm) about joint j's axis
``z_j`` that the loads exert on everything outboard of joint j; a joint of stiffness K
holding it turns by ``tau_j / K`` in its positive sense.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel
from sim_devices.arm_masses import ArmMasses
from sim_devices.counterbalance import (
    DEFAULT_SHARE,
    HEAVY_ARM_KG,
    Counterbalance,
    size_counterbalance,
)

FloatArray = NDArray[np.float64]

STANDARD_GRAVITY_M_S2 = 9.80665
#: Poses that size the counterbalance and the deflection stiffness (uniform within the
#: limits, fixed seed): "RMS over the joint ranges" means over these.
RANGE_POSES = 400
RANGE_POSES_SEED = 0


@dataclass(frozen=True, eq=False)
class PhysicalArm:
    """The true geometry, the emulator's masses, an optional counterbalance, joint limits."""

    model: KinematicModel
    masses: ArmMasses
    lower_rad: FloatArray  # (n,)
    upper_rad: FloatArray  # (n,)
    counterbalance: Counterbalance | None = None
    counterbalance_share: float = 0.0  # share of joint 2's RMS weight torque it cancels
    gravity_m_s2: float = STANDARD_GRAVITY_M_S2

    @classmethod
    def of(
        cls,
        truth: RobotDescription,
        masses: ArmMasses,
        *,
        counterbalance: bool | None = None,
        share: float = DEFAULT_SHARE,
    ) -> PhysicalArm:
        """The arm of ``truth``'s geometry carrying ``masses``.

        ``counterbalance`` None: one on joint 2 when the links weigh at least
        :data:`~sim_devices.counterbalance.HEAVY_ARM_KG` or the description declares one
        there (``counterbalance = true``: that it exists, never its parameters), sized to
        cancel ``share`` of joint 2's RMS gravity torque over the joint ranges.
        """
        arm = cls(
            KinematicModel.from_description(truth),
            masses,
            np.radians([j.lower_deg for j in truth.joints]),
            np.radians([j.upper_deg for j in truth.joints]),
        )
        declared = arm.n_joints >= 2 and bool(getattr(truth.joints[1], "counterbalance", False))
        heavy = masses.arm_kg >= HEAVY_ARM_KG or declared
        wanted = heavy if counterbalance is None else counterbalance
        if not wanted or arm.n_joints < 3:
            return arm
        q = arm.range_poses()
        theta2 = q[:, 1] + arm.model.theta_offset_rad[1]
        length = abs(truth.joints[2].a_mm) + abs(truth.joints[2].d_mm)
        spring, achieved = size_counterbalance(
            theta2, arm.weight_torques_nmm(q)[:, 1], length, share=share
        )
        return replace(arm, counterbalance=spring, counterbalance_share=achieved)

    @classmethod
    def of_description(cls, desc: RobotDescription) -> PhysicalArm:
        """An arm with exactly ``desc``'s mass model and no counterbalance (for checks
        against the twin's mass-model terms; the emulator uses its own arm)."""
        return cls.of(desc, ArmMasses.of_description(desc), counterbalance=False)

    @property
    def n_joints(self) -> int:
        return self.model.n_joints

    def range_poses(self, n: int = RANGE_POSES) -> FloatArray:
        """``(n, n_joints)`` rad uniform within the joint limits (fixed seed)."""
        rng = np.random.default_rng(RANGE_POSES_SEED)
        return rng.uniform(self.lower_rad, self.upper_rad, size=(n, self.n_joints))

    def link_frames(self, q_rad: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Rotations ``(N, n, 3, 3)`` and origins ``(N, n, 3)`` mm of frames 1..n in the
        robot base frame, each ``T_i = T_{i-1}·Rx(α)·Tx(a)·Ry(β)·Rz(θ)·Tz(d)``."""
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))
        m = self.model
        n_pose, n = q.shape
        theta = q + m.theta_offset_rad
        rot = np.empty((n_pose, n, 3, 3))
        org = np.empty((n_pose, n, 3))
        r_prev = np.broadcast_to(np.eye(3), (n_pose, 3, 3))
        o_prev = np.zeros((n_pose, 3))
        consts = m.link_constants()  # Rx(α)·Ry(β) per link
        for i in range(n):
            c, s = np.cos(theta[:, i]), np.sin(theta[:, i])
            rz = np.zeros((n_pose, 3, 3))
            rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1] = c, -s, s, c
            rz[:, 2, 2] = 1.0
            o_a = o_prev + m.a_mm[i] * r_prev[:, :, 0]  # Tx(a) after Rx(α) (x unchanged)
            r_i = r_prev @ consts[i] @ rz
            rot[:, i], org[:, i] = r_i, o_a + m.d_mm[i] * r_i[:, :, 2]
            r_prev, o_prev = r_i, org[:, i]
        return rot, org

    def weight_torques_nmm(self, q_rad: ArrayLike) -> FloatArray:
        """Torque ``(N, n)`` N·mm of the outboard links' and payload's weights about each
        joint axis, at joint angles ``(N, n)`` rad."""
        rot, _ = self.link_frames(q_rad)
        moment = self.weight_moments_nmm(q_rad)
        torque: FloatArray = np.einsum("pjk,pjk->pj", rot[:, :, :, 2], moment)
        return torque

    def weight_moments_nmm(self, q_rad: ArrayLike) -> FloatArray:
        """Moment ``(N, n, 3)`` N·mm (robot base frame) of the weights of link j and
        everything outboard about frame j's origin, at joint angles ``(N, n)`` rad: along
        z_j the joint's torque, across it what bends the link."""
        rot, org = self.link_frames(q_rad)
        ms = self.masses
        com = org + np.einsum("pikl,il->pik", rot, ms.com_mm)  # (N, n, 3) base frame
        payload = org[:, -1] + rot[:, -1] @ ms.payload_com_mm  # (N, 3)
        weight = -self.gravity_m_s2 * ms.mass_kg  # z-force of each link (N)
        w_pay = -self.gravity_m_s2 * ms.payload_kg
        # about joint j: Σ_{i ≥ j} (c_i − o_j) × F_i, F along z: sums of weights and of
        # weight-weighted positions outboard of each joint (cumulative from the flange)
        f_out = np.cumsum(weight[::-1])[::-1] + w_pay  # (n,)
        wc = np.cumsum((weight[:, None] * com)[:, ::-1], axis=1)[:, ::-1] + w_pay * payload[:, None]
        lever = wc - f_out[:, None] * org  # Σ F_i (c_i − o_j), (N, n, 3)
        ez = np.array([0.0, 0.0, 1.0])
        moment: FloatArray = np.cross(lever, ez)  # Σ (c_i − o_j) × (F_i·ez)
        return moment

    def counterbalance_torques_nmm(self, q_rad: ArrayLike) -> FloatArray:
        """The spring's torque ``(N, n)`` N·mm (non-zero on its joint only)."""
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))
        out = np.zeros_like(q)
        cb = self.counterbalance
        if cb is not None:
            j = cb.joint - 1
            out[:, j] = cb.torque_nmm(q[:, j] + self.model.theta_offset_rad[j])
        return out

    def joint_torques_nmm(self, q_rad: ArrayLike) -> FloatArray:
        """The static load ``(N, n)`` N·mm each joint holds: weights plus counterbalance."""
        return self.weight_torques_nmm(q_rad) + self.counterbalance_torques_nmm(q_rad)

    def document(self) -> dict[str, Any]:
        """The arm's own parameters for the truth file (never given to the twin)."""
        doc: dict[str, Any] = {
            "gravity_m_s2": self.gravity_m_s2,
            "masses": self.masses.document(),
        }
        if self.counterbalance is not None:
            doc["counterbalance"] = {
                **self.counterbalance.document(),
                "share_of_rms_torque": self.counterbalance_share,
            }
        return doc
