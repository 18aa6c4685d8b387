"""Gear torsion and backlash: where each joint's output ring stands for a motor position.

The servo holds the motor at ``q_cmd`` (times the gear ratio); the gear between motor and
output ring twists under the joint's static load τ and has a backlash gap. The ring, which
the grating reads, stands at

    q_ring = q_cmd + τ/K + ½·b·side,   side = w·sign(τ) + (1 − w)·direction,
    w = clip(|τ| / τ_b, 0, 1)

(the loaded flank by the load's sign; below ``τ_b`` the last motion direction decides).
One implementation for the live plant and the static scale campaign; τ comes from the
emulator's own arm (:meth:`sim_devices.physical_arm.PhysicalArm.joint_torques_nmm`).
Defaults: :class:`sim_devices.config.EffectsSection`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sim_devices.config import EffectsSection

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class GearTrain:
    """Per-joint gear stiffness ``(n,)`` N·mm/rad and backlash ``(n,)`` rad (full gap)."""

    stiffness_nmm_per_rad: FloatArray
    backlash_rad: FloatArray
    backlash_torque_nmm: float = 5e4
    torsion: bool = True
    backlash: bool = True

    @classmethod
    def of(cls, effects: EffectsSection, n_joints: int) -> GearTrain:
        """The gears of a cell configuration's ``[effects]`` (values resized to n joints)."""
        return cls(
            np.resize(np.asarray(effects.stiffness_nmm_per_rad, float), n_joints),
            np.radians(np.resize(np.asarray(effects.backlash_deg, float), n_joints)),
            effects.backlash_torque_nmm,
            effects.torsion,
            effects.backlash,
        )

    @property
    def active(self) -> bool:
        return self.torsion or self.backlash

    def ring_offset_rad(self, torque_nmm: ArrayLike, direction: ArrayLike) -> FloatArray:
        """``q_ring − q_cmd`` ``(N, n)`` rad for loads ``(N, n)`` N·mm and last motion
        directions ``(N, n)`` in {−1, 0, +1}."""
        tau = np.atleast_2d(np.asarray(torque_nmm, dtype=float))
        out = np.zeros_like(tau)
        if self.torsion:
            out += tau / self.stiffness_nmm_per_rad
        if self.backlash:
            w = np.clip(np.abs(tau) / self.backlash_torque_nmm, 0.0, 1.0)
            side = w * np.sign(tau) + (1.0 - w) * np.asarray(direction, dtype=float)
            out += 0.5 * self.backlash_rad * side
        return out
