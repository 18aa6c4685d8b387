"""Effects of the emulated cell that nobody declares to the twin (all off by default).

One physical implementation of each, shared by the static campaign generator
(:mod:`sim_devices.pose_campaign`) and the live plant (:mod:`sim_devices.plant`):

* **gravity deflection** downstream of the grating ring: the link and the output bearing
  give under the gravity torque of everything outboard (links and payload), an extra
  rotation ``tau_i / K_i`` about joint axis i *after* the ring the grating reads. (Gear
  torsion sits before the ring: the gratings see it, the twin does not need it.)
* **cyclic grating error** left after the scale calibration: joint j's reading is
  ``q + A·sin(k·q + phi)`` (k = 2: ovality of the ring).
* **thermal drift** of a link length (``a`` or ``d`` of one joint) with campaign time,
  linear or approaching a final value exponentially.
* **tracker scale error**: distance-proportional (about the tracker, the origin of the
  world frame), constant and/or drifting with time (air temperature).
* **lost motion** downstream of the ring: joint j stands ``±w_j`` off depending on the
  direction it last moved in.

Units are in the names; angles are radians inside the functions, degrees in the settings.
The truth written for tests carries these settings and the derived stiffnesses.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.description import RobotDescription
from calibration.kinematics import KinematicModel, tcp_positions
from calibration.statics import MassModel, gravity_torques_nmm

FloatArray = NDArray[np.float64]

#: Effect names (the ``--effect`` choices of the campaign generator) -> what they are.
EFFECT_NAMES: dict[str, str] = {
    "gravity_deflection": "link/bearing compliance after the grating ring under gravity",
    "grating_cyclic": "cyclic error of one joint's grating reading (harmonic of its angle)",
    "thermal_drift": "a link length growing with campaign time",
    "tracker_scale": "distance-proportional tracker scale error (constant and/or drifting)",
    "lost_motion": "direction-dependent lost motion after the grating ring",
}

#: Poses the default stiffness is derived from (uniform within limits, fixed seed).
_STIFFNESS_POSES = 400


@dataclass(frozen=True)
class UndeclaredEffects:
    """Which undeclared effects the emulated cell has, and how strong (all off by default).

    ``deflection_stiffness_nmm_per_rad`` empty: each joint's stiffness is set so that its
    RMS deflection over the joint ranges is ``deflection_rms_deg`` (stiffness scales with
    the load, as on real arms), and joints carrying less than 1 % of the largest RMS gravity
    torque (joint 1 about the vertical, the flange) are rigid. A KR500-class arm then gets
    1e10-9e10 N·mm/rad on axes 2-3, 1e9-2e9 on the wrist and tenths of a mm at the TCP.
    """

    gravity_deflection: bool = False
    deflection_stiffness_nmm_per_rad: tuple[float, ...] = ()
    deflection_rms_deg: float = 0.005
    grating_cyclic: bool = False
    cyclic_joint: int = 1  # 1-based
    cyclic_order: int = 2
    cyclic_amplitude_deg: float = 0.004
    cyclic_phase_deg: float = 30.0
    thermal_drift: bool = False
    drift_joint: int = 2  # 1-based
    drift_parameter: str = "a"  # "a" or "d" of that joint
    drift_mm_per_h: float = 0.15  # initial rate of growth
    drift_time_constant_s: float = 0.0  # 0: linear; > 0: exponential approach
    tracker_scale: bool = False
    tracker_scale_ppm: float = 20.0
    tracker_scale_drift_ppm_per_h: float = 0.0
    lost_motion: bool = False
    lost_motion_deg: tuple[float, ...] = (0.0, 0.003, 0.003, 0.0, 0.0, 0.0)  # half widths

    @classmethod
    def named(cls, *names: str, **overrides: Any) -> UndeclaredEffects:
        """Settings with the effects ``names`` (see :data:`EFFECT_NAMES`) switched on."""
        unknown = [n for n in names if n not in EFFECT_NAMES]
        if unknown:
            raise ValueError(f"unknown effect {unknown[0]!r} (valid: {', '.join(EFFECT_NAMES)})")
        return replace(cls(), **{n: True for n in names}, **overrides)

    @property
    def active(self) -> tuple[str, ...]:
        return tuple(n for n in EFFECT_NAMES if getattr(self, n))

    @property
    def any_active(self) -> bool:
        return bool(self.active)

    def document(self) -> dict[str, Any]:
        return asdict(self)


def deflection_stiffness_nmm_per_rad(
    settings: UndeclaredEffects, truth: RobotDescription
) -> FloatArray:
    """Per-joint stiffness ``(n,)`` N·mm/rad of the compliance after the ring (inf: rigid)."""
    n = truth.n_joints
    if settings.deflection_stiffness_nmm_per_rad:
        return np.resize(np.asarray(settings.deflection_stiffness_nmm_per_rad, float), n)
    rng = np.random.default_rng(0)
    lo = np.radians([j.lower_deg for j in truth.joints])
    hi = np.radians([j.upper_deg for j in truth.joints])
    q = rng.uniform(lo, hi, size=(_STIFFNESS_POSES, n))
    tau = gravity_torques_nmm(
        KinematicModel.from_description(truth), MassModel.from_description(truth), q
    )
    rms = np.sqrt(np.mean(tau**2, axis=0))
    k = rms / np.radians(settings.deflection_rms_deg)
    k[rms < 0.01 * max(float(rms.max()), 1e-300)] = np.inf
    return k


def link_rotation_rad(
    settings: UndeclaredEffects,
    truth: RobotDescription,
    q_ring_rad: ArrayLike,
    direction: ArrayLike | None = None,
) -> FloatArray:
    """Rotation ``(N, n)`` rad of each link about its joint axis beyond the grating ring.

    Gravity deflection (``tau / K`` at the ring angles, truth's mass model) plus lost
    motion (``w_j · direction_j``, direction ``(N, n)`` in {-1, 0, 1}: last motion).
    """
    q = np.atleast_2d(np.asarray(q_ring_rad, dtype=float))
    out = np.zeros_like(q)
    if settings.gravity_deflection:
        tau = gravity_torques_nmm(
            KinematicModel.from_description(truth), MassModel.from_description(truth), q
        )
        out += tau / deflection_stiffness_nmm_per_rad(settings, truth)
    if settings.lost_motion and direction is not None:
        w = np.radians(np.resize(np.asarray(settings.lost_motion_deg, float), q.shape[1]))
        out += w * np.asarray(direction, dtype=float)
    return out


def grating_reading_rad(settings: UndeclaredEffects, q_ring_rad: ArrayLike) -> FloatArray:
    """What the (scale-calibrated) gratings read ``(N, n)`` rad at ring angles ``(N, n)``."""
    q = np.array(np.atleast_2d(np.asarray(q_ring_rad, dtype=float)))
    if settings.grating_cyclic:
        j = settings.cyclic_joint - 1
        a = np.radians(settings.cyclic_amplitude_deg)
        phase = np.radians(settings.cyclic_phase_deg)
        q[:, j] += a * np.sin(settings.cyclic_order * q[:, j] + phase)
    return q


def length_drift_mm(settings: UndeclaredEffects, t_s: ArrayLike) -> FloatArray:
    """Growth ``(N,)`` mm of the drifting link length at campaign times ``t_s``."""
    t = np.asarray(t_s, dtype=float)
    if not settings.thermal_drift:
        return np.zeros_like(t)
    rate = settings.drift_mm_per_h / 3600.0
    tau = settings.drift_time_constant_s
    if tau > 0:
        return rate * tau * (1.0 - np.exp(-t / tau))
    return rate * t


def true_tcp_mm(
    settings: UndeclaredEffects,
    truth: RobotDescription,
    q_ring_rad: ArrayLike,
    t_s: ArrayLike,
    direction: ArrayLike | None = None,
) -> FloatArray:
    """Physical TCP ``(N, 3)`` mm in the tracker frame at ring angles and times.

    The links stand at the ring angles plus :func:`link_rotation_rad`; the drifting length
    adds along its own axis (a TCP is linear in every a and d, so this is exact).
    """
    q = np.atleast_2d(np.asarray(q_ring_rad, dtype=float))
    model = KinematicModel.from_description(truth)
    q_link = q + link_rotation_rad(settings, truth, q, direction)
    tcp = tcp_positions(model, q_link)
    if settings.thermal_drift:
        growth = length_drift_mm(settings, t_s)
        x = model.parameter_vector()
        index = 5 * (settings.drift_joint - 1) + {"a": 0, "d": 2}[settings.drift_parameter]
        x[index] += 1.0
        axis = tcp_positions(model.with_parameters(x), q_link) - tcp  # per mm of growth
        tcp = tcp + growth[:, None] * axis
    return tcp


def tracker_reading_mm(
    settings: UndeclaredEffects, points_mm: ArrayLike, t_s: ArrayLike
) -> FloatArray:
    """Points ``(N, 3)`` as a noise-free tracker with the scale error reads them."""
    pts = np.atleast_2d(np.asarray(points_mm, dtype=float))
    if not settings.tracker_scale:
        return pts.copy()
    ppm = (
        settings.tracker_scale_ppm
        + settings.tracker_scale_drift_ppm_per_h * np.asarray(t_s, dtype=float) / 3600.0
    )
    return pts * (1.0 + 1e-6 * np.broadcast_to(ppm, (len(pts),)))[:, None]


def approach_direction(q_rad: ArrayLike, start_rad: ArrayLike | None = None) -> FloatArray:
    """Sign ``(N, n)`` of each joint's last move in a pose sequence ``(N, n)`` (time order).

    The first pose moves from ``start_rad`` (zeros, i.e. Home, by default).
    """
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    start = np.zeros(q.shape[1]) if start_rad is None else np.asarray(start_rad, dtype=float)
    return np.sign(np.diff(np.vstack([start, q]), axis=0))
