"""Effects of the emulated cell that nobody declares to the twin (all off by default).

One physical implementation of each, shared by the pose campaign generator
(:mod:`sim_devices.pose_campaign`), the static scale campaign
(:mod:`sim_devices.scale_campaign`) and the live plant (:mod:`sim_devices.plant`):

* **gravity deflection** downstream of the grating ring: the link and the output bearing
  give under the static load of everything outboard (links, payload, and on joint 2 of a
  heavy arm the counterbalance; :class:`sim_devices.physical_arm.PhysicalArm`, the
  emulator's own masses), an extra rotation ``tau_i / K_i`` about joint axis i *after*
  the ring the grating reads. (Gear torsion sits before the ring: the gratings see it;
  :mod:`sim_devices.gears`.)
* **joint coupling** of two joints' compliance after the ring (joints 2 and 3 by
  default: a shared gearbox housing or parallelogram linkage, or the casting both sit
  in): the gravity deflection's compliance matrix gets a symmetric cross term,
  ``δq_a += c_ab·τ_b``, ``δq_b += c_ab·τ_a``, ``c_ab = ρ/√(K_a·K_b)``, the coupling
  coefficient ``|ρ| < 1`` keeping the matrix positive definite
  (:func:`coupling_compliance_rad_per_nmm`); a part of the gravity deflection, which it
  switches on.
* **link bending** under gravity: link j (and its output bearing) turns about its own x
  and y axes through its frame origin by ``M⊥_j / K_b,j``, ``M⊥_j`` the part of the
  emulator's own weight moment at that origin across the joint axis
  (:meth:`sim_devices.physical_arm.PhysicalArm.weight_moments_nmm`).
* **cyclic grating error** left after the scale calibration: joint j's reading is
  ``q + A·sin(k·q + phi)`` (k = 2: ovality of the ring).
* **thermal drift** of a link length (``a`` or ``d`` of one joint) with campaign time,
  linear or approaching a final value exponentially.
* **thermal lag**: a link length (its own joint and parameter) growing as
  ``A·(1 − e^(−t/τ))`` from the campaign's start (the arm warming up).
* **thermal expansion** with a temperature: every link length grows
  ``κ·L·(T(t) − T_ref)``, T the arm's temperature warming up with the hall's air-handling
  cycle on top (:func:`arm_temperature_c`); the campaign writes it as ``temp_c`` with a
  sensor's noise (the only effect the twin is given a measurement of).
* **tracker scale error**: distance-proportional (about the tracker, the origin of the
  world frame), constant and/or drifting with time (air temperature).
* **lost motion** downstream of the ring: joint j stands ``±w_j`` off depending on the
  direction it last moved in.

A **process force** on the tool is an input, not an effect: the same compliance after the
ring turns joint j by ``J_jᵀ·F / K_j`` (:func:`force_stiffness_nmm_per_rad`), whether or
not gravity deflection is switched on (a real arm is never rigid).

Units are in the names; angles are radians inside the functions, degrees in the settings.
The functions take the emulator's arm; a :class:`RobotDescription` stands for an arm with
exactly that description's mass model and no counterbalance (for checks against the twin's
mass-model terms). The truth written for tests carries these settings and the derived
stiffnesses (:func:`effects_document`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.description import RobotDescription
from calibration.model.kinematics import geometric_jacobian, tcp_positions
from sim_devices.physical_arm import PhysicalArm

FloatArray = NDArray[np.float64]

#: Effect names (the ``--effect`` choices of the campaign generator) -> what they are.
EFFECT_NAMES: dict[str, str] = {
    "gravity_deflection": "link/bearing compliance after the grating ring under gravity",
    "joint_coupling": "joints 2 and 3 sharing compliance after the ring: a symmetric cross "
    "term of the gravity deflection's compliance matrix (switches gravity_deflection on)",
    "link_bending": "links 1-3 turning about their own x and y axes under the bending "
    "moment of everything outboard",
    "grating_cyclic": "cyclic error of one joint's grating reading (harmonic of its angle)",
    "thermal_drift": "a link length growing with campaign time",
    "thermal_lag": "a link length growing as A·(1 − exp(−t/τ)) from the campaign start",
    "thermal_expansion": "every link length growing ∝ (T − T_ref) with the arm's temperature, "
    "which warms up with an air-handling cycle on top (written as temp_c)",
    "tracker_scale": "distance-proportional tracker scale error (constant and/or drifting)",
    "lost_motion": "direction-dependent lost motion after the grating ring",
}

#: The emulator's arm, or a description standing for an arm with its mass model.
ArmLike = PhysicalArm | RobotDescription


@dataclass(frozen=True)
class UndeclaredEffects:
    """Which undeclared effects the emulated cell has, and how strong (all off by default).

    ``deflection_stiffness_nmm_per_rad`` empty: each joint's stiffness is set so that its
    RMS deflection over the joint ranges is ``deflection_rms_deg`` (stiffness scales with
    the load, as on real arms), from the emulator's own torques (its masses and
    counterbalance), and joints carrying less than 1 % of the largest RMS torque (joint 1
    about the vertical, the flange) are rigid. A KR500-class arm then gets 1e10-1e11
    N·mm/rad on axes 2-3, 1e9-2e9 on the wrist and tenths of a mm at the TCP.
    """

    gravity_deflection: bool = False
    deflection_stiffness_nmm_per_rad: tuple[float, ...] = ()
    deflection_rms_deg: float = 0.005
    joint_coupling: bool = False  # a cross compliance of two joints (needs the deflection)
    coupling_joints: tuple[int, ...] = (2, 3)  # 1-based: the pair (shoulder and elbow)
    coupling_coefficient: float = 0.5  # ρ = c_ab/√(c_aa·c_bb), |ρ| < 1
    link_bending: bool = False
    bending_links: tuple[int, ...] = (1, 2, 3)  # 1-based: the column and the long arms
    bending_rms_deg: float = 0.002  # each bending link's RMS turn over the joint ranges
    bending_stiffness_nmm_per_rad: tuple[float, ...] = ()  # empty: from bending_rms_deg
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
    thermal_lag: bool = False
    lag_joint: int = 2  # 1-based
    lag_parameter: str = "a"  # "a" or "d" of that joint
    lag_mm: float = 0.15  # final growth A
    lag_time_constant_s: float = 900.0  # τ
    thermal_expansion: bool = False
    expansion_ppm_per_k: float = 11.5  # steel
    temp_ref_c: float = 20.0  # the true geometry's temperature (ISO 1)
    temp_start_c: float = 21.0  # the arm at the campaign's start
    temp_rise_k: float = 3.0  # warm-up, approached as 1 − e^(−t/τ)
    temp_time_constant_s: float = 1800.0
    temp_cycle_k: float = 0.5  # the air handling's cycle: amplitude
    temp_cycle_period_s: float = 1200.0
    temp_sensor_noise_k: float = 0.05  # 1 σ of the temp_c reading
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
        switched: dict[str, Any] = {n: True for n in names}
        if "joint_coupling" in names:  # a cross term of the deflection's compliance matrix
            switched["gravity_deflection"] = True
        return replace(cls(), **switched, **overrides)

    @property
    def active(self) -> tuple[str, ...]:
        return tuple(n for n in EFFECT_NAMES if getattr(self, n))

    @property
    def any_active(self) -> bool:
        return bool(self.active)

    def document(self) -> dict[str, Any]:
        return asdict(self)


def physical_arm(arm: ArmLike) -> PhysicalArm:
    """The arm itself, or a description's mass model as an arm (no counterbalance)."""
    return arm if isinstance(arm, PhysicalArm) else PhysicalArm.of_description(arm)


def deflection_stiffness_nmm_per_rad(settings: UndeclaredEffects, arm: ArmLike) -> FloatArray:
    """Per-joint stiffness ``(n,)`` N·mm/rad of the compliance after the ring (inf: rigid)."""
    body = physical_arm(arm)
    n = body.n_joints
    if settings.deflection_stiffness_nmm_per_rad:
        return np.resize(np.asarray(settings.deflection_stiffness_nmm_per_rad, float), n)
    tau = body.joint_torques_nmm(body.range_poses())
    rms = np.sqrt(np.mean(tau**2, axis=0))
    k = rms / np.radians(settings.deflection_rms_deg)
    k[rms < 0.01 * max(float(rms.max()), 1e-300)] = np.inf
    stiffness: FloatArray = k
    return stiffness


def coupling_compliance_rad_per_nmm(settings: UndeclaredEffects, arm: ArmLike) -> float:
    """The cross compliance ``c_ab = ρ/√(K_a·K_b)`` rad/(N·mm) of the coupled joints
    (``coupling_joints``), ``K`` the gravity deflection's stiffnesses; 0 when the coupling
    is off or either joint is rigid. ``|ρ| < 1`` keeps the compliance matrix positive
    definite (a ValueError otherwise)."""
    if not settings.joint_coupling:
        return 0.0
    rho = settings.coupling_coefficient
    if not abs(rho) < 1.0:
        raise ValueError(f"coupling_coefficient must be in (-1, 1), got {rho}")
    k = deflection_stiffness_nmm_per_rad(settings, arm)
    a, b = (j - 1 for j in settings.coupling_joints)
    if not (np.isfinite(k[a]) and np.isfinite(k[b])):
        return 0.0
    return float(rho / np.sqrt(k[a] * k[b]))


def coupling_rotation_rad(
    settings: UndeclaredEffects, arm: ArmLike, tau_nmm: FloatArray
) -> FloatArray:
    """The coupled joints' extra turn ``(N, n)`` rad under the joint torques ``tau_nmm``
    ``(N, n)`` N·mm: ``c_ab·τ_b`` on joint a, ``c_ab·τ_a`` on joint b (Maxwell's
    reciprocity: one cross compliance both ways)."""
    out = np.zeros_like(tau_nmm)
    c = coupling_compliance_rad_per_nmm(settings, arm)
    if c != 0.0:
        a, b = (j - 1 for j in settings.coupling_joints)
        out[:, a] = c * tau_nmm[:, b]
        out[:, b] = c * tau_nmm[:, a]
    return out


#: Joint stiffness proportions of a KUKA KR60 (method.md §4; N·mm/rad as the source
#: states them): what the emulator gives, scaled to its arm, the joints that gravity
#: hardly loads (joint 1 about the vertical, the flange), whose gravity stiffness is inf.
KR60_STIFFNESS_NMM_PER_RAD = (5.7e7, 6.2e6, 1.2e7, 2.1e6, 2.3e6, 2.3e6)


def force_stiffness_nmm_per_rad(settings: UndeclaredEffects, arm: ArmLike) -> FloatArray:
    """Per-joint stiffness ``(n,)`` N·mm/rad under a process force: the gravity
    deflection's where finite; elsewhere the KR60 proportion times the median ratio of
    the finite joints to theirs (the emulator's own; never given to the twin)."""
    k = deflection_stiffness_nmm_per_rad(settings, arm).copy()
    pattern = np.resize(np.asarray(KR60_STIFFNESS_NMM_PER_RAD, float), len(k))
    finite = np.isfinite(k)
    scale = float(np.median(k[finite] / pattern[finite])) if finite.any() else 1e3
    k[~finite] = scale * pattern[~finite]
    return k


def force_rotation_rad(
    settings: UndeclaredEffects, arm: ArmLike, q_ring_rad: ArrayLike, force_n: ArrayLike
) -> FloatArray:
    """Rotation ``(N, n)`` rad of each link after its ring under a force ``(N, 3)`` N at
    the TCP (tracker frame): ``J_jᵀ·F / K_j`` at the ring angles."""
    body = physical_arm(arm)
    q = np.atleast_2d(np.asarray(q_ring_rad, dtype=float))
    f = np.broadcast_to(np.asarray(force_n, dtype=float), (len(q), 3))
    jp = geometric_jacobian(body.model, q, point="tcp", frame="world")[:, :3, :]
    torque: FloatArray = np.einsum("min,mi->mn", jp, f)
    return torque / force_stiffness_nmm_per_rad(settings, body)


def _bending_moments_nmm(body: PhysicalArm, q_rad: FloatArray) -> FloatArray:
    """``M⊥`` ``(N, n, 3)`` N·mm, base frame: each link's weight moment across its axis."""
    rot, _ = body.link_frames(q_rad)
    moment = body.weight_moments_nmm(q_rad)
    z = rot[:, :, :, 2]
    across: FloatArray = moment - np.sum(moment * z, axis=2)[:, :, None] * z
    return across


def bending_stiffness_nmm_per_rad(settings: UndeclaredEffects, arm: ArmLike) -> FloatArray:
    """Per-link bending stiffness ``(n,)`` N·mm/rad (inf: rigid): given, or each bending
    link's RMS ``|M⊥|`` over the joint ranges over ``bending_rms_deg`` (a link built
    for its load, as the joints are); links under 1 % of the largest RMS are rigid."""
    body = physical_arm(arm)
    n = body.n_joints
    if settings.bending_stiffness_nmm_per_rad:
        return np.resize(np.asarray(settings.bending_stiffness_nmm_per_rad, float), n)
    across = _bending_moments_nmm(body, body.range_poses())
    rms = np.sqrt(np.mean(np.sum(across**2, axis=2), axis=0))
    k = np.full(n, np.inf)
    links = [j - 1 for j in settings.bending_links if 1 <= j <= n]
    k[links] = rms[links] / np.radians(settings.bending_rms_deg)
    k[rms < 0.01 * max(float(rms[links].max(initial=0.0)), 1e-300)] = np.inf
    return k


def bending_rotation_rad(
    settings: UndeclaredEffects, arm: ArmLike, q_ring_rad: ArrayLike
) -> FloatArray:
    """Rotation vector ``(N, n, 3)`` rad (robot base frame) of each link about its own x
    and y axes through its frame origin: ``M⊥ / K_b`` at the ring angles (0: off)."""
    body = physical_arm(arm)
    q = np.atleast_2d(np.asarray(q_ring_rad, dtype=float))
    if not settings.link_bending:
        return np.zeros((len(q), body.n_joints, 3))
    k = bending_stiffness_nmm_per_rad(settings, body)
    out: FloatArray = _bending_moments_nmm(body, q) / k[None, :, None]
    return out


def _bent(
    body: PhysicalArm, pts: FloatArray, q_link: FloatArray, phi: FloatArray, last: int
) -> FloatArray:
    """Points ``(N, 3)`` (tracker frame) fixed in link ``last`` (0-based) with links
    0..last turned by ``phi`` ``(N, n, 3)`` about their origins: outer links first, each
    an exact rotation (Rodrigues) of everything outboard of it."""
    rot_base = body.model.base_rotation()
    _, org = body.link_frames(q_link)
    out = pts.copy()
    for j in range(last, -1, -1):
        v = phi[:, j] @ rot_base.T  # tracker frame
        angle = np.linalg.norm(v, axis=1)
        if not np.any(angle > 0.0):
            continue
        axis = v / np.where(angle > 0.0, angle, 1.0)[:, None]
        origin = org[:, j] @ rot_base.T + body.model.base_mm
        r = out - origin
        c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
        dot = np.sum(axis * r, axis=1)[:, None]
        out = origin + r * c + np.cross(axis, r) * s + axis * dot * (1.0 - c)
    return out


def with_derived_stiffness(settings: UndeclaredEffects, arm: ArmLike) -> UndeclaredEffects:
    """``settings`` with the deflection and bending stiffnesses derived once (not per
    evaluation)."""
    if settings.link_bending and not settings.bending_stiffness_nmm_per_rad:
        k = bending_stiffness_nmm_per_rad(settings, arm)
        settings = replace(settings, bending_stiffness_nmm_per_rad=tuple(float(v) for v in k))
    if not settings.gravity_deflection or settings.deflection_stiffness_nmm_per_rad:
        return settings
    k = deflection_stiffness_nmm_per_rad(settings, arm)
    return replace(settings, deflection_stiffness_nmm_per_rad=tuple(float(v) for v in k))


def effects_document(settings: UndeclaredEffects, arm: ArmLike) -> dict[str, Any]:
    """The settings for the truth file, with the derived stiffness (0 = rigid)."""
    doc = settings.document()
    doc["deflection_stiffness_nmm_per_rad"] = [
        v if np.isfinite(v) else 0.0 for v in doc["deflection_stiffness_nmm_per_rad"]
    ]
    if settings.gravity_deflection:
        k = deflection_stiffness_nmm_per_rad(settings, arm)
        doc["derived_stiffness_nmm_per_rad"] = [float(v) if np.isfinite(v) else 0.0 for v in k]
    if settings.joint_coupling:
        doc["derived_coupling_compliance_rad_per_nmm"] = coupling_compliance_rad_per_nmm(
            settings, arm
        )
    doc["bending_stiffness_nmm_per_rad"] = [
        v if np.isfinite(v) else 0.0 for v in doc["bending_stiffness_nmm_per_rad"]
    ]
    if settings.link_bending:
        k = bending_stiffness_nmm_per_rad(settings, arm)
        doc["derived_bending_stiffness_nmm_per_rad"] = [
            float(v) if np.isfinite(v) else 0.0 for v in k
        ]
    return doc


def link_rotation_rad(
    settings: UndeclaredEffects,
    arm: ArmLike,
    q_ring_rad: ArrayLike,
    direction: ArrayLike | None = None,
    force_n: ArrayLike | None = None,
) -> FloatArray:
    """Rotation ``(N, n)`` rad of each link about its joint axis beyond the grating ring.

    Gravity deflection (``tau / K`` at the ring angles, the arm's static load; with the
    joint coupling, the compliance matrix's cross term too) plus lost
    motion (``w_j · direction_j``, direction ``(N, n)`` in {-1, 0, 1}: last motion), plus
    a process force ``(N, 3)`` N at the TCP (:func:`force_rotation_rad`).
    """
    q = np.atleast_2d(np.asarray(q_ring_rad, dtype=float))
    out = np.zeros_like(q)
    if settings.gravity_deflection:
        body = physical_arm(arm)
        tau = body.joint_torques_nmm(q)
        out += tau / deflection_stiffness_nmm_per_rad(settings, body)
        if settings.joint_coupling:
            out += coupling_rotation_rad(settings, body, tau)
    if settings.lost_motion and direction is not None:
        w = np.radians(np.resize(np.asarray(settings.lost_motion_deg, float), q.shape[1]))
        out += w * np.asarray(direction, dtype=float)
    if force_n is not None:
        out += force_rotation_rad(settings, arm, q, force_n)
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


def length_lag_mm(settings: UndeclaredEffects, t_s: ArrayLike) -> FloatArray:
    """Growth ``(N,)`` mm of the lagging link length: ``A·(1 − e^(−t/τ))``."""
    t = np.asarray(t_s, dtype=float)
    if not settings.thermal_lag:
        return np.zeros_like(t)
    return settings.lag_mm * (1.0 - np.exp(-t / settings.lag_time_constant_s))


def arm_temperature_c(settings: UndeclaredEffects, t_s: ArrayLike) -> FloatArray:
    """The arm's true temperature ``(N,)`` °C at campaign times ``t_s``: a warm-up
    ``T0 + ΔT·(1 − e^(−t/τ))`` and the hall's air-handling cycle ``A·sin(2πt/P)`` (a
    temperature no polynomial or lag in time follows)."""
    t = np.asarray(t_s, dtype=float)
    warm = settings.temp_rise_k * -np.expm1(-t / settings.temp_time_constant_s)
    cycle = settings.temp_cycle_k * np.sin(2.0 * np.pi * t / settings.temp_cycle_period_s)
    out: FloatArray = settings.temp_start_c + warm + cycle
    return out


def expansion_ppm(settings: UndeclaredEffects, t_s: ArrayLike) -> FloatArray:
    """Growth ``(N,)`` ppm of every link length at times ``t_s``: ``κ·(T − T_ref)``."""
    t = np.asarray(t_s, dtype=float)
    if not settings.thermal_expansion:
        return np.zeros_like(t)
    rise = arm_temperature_c(settings, t) - settings.temp_ref_c
    out: FloatArray = settings.expansion_ppm_per_k * rise
    return out


_PARAMETER_OFFSET = {"a": 0, "d": 2}  # position in a joint's 5 parameters (a, α, d, θ, β)


def length_changes(settings: UndeclaredEffects, t_s: ArrayLike) -> list[tuple[int, FloatArray]]:
    """The thermal length changes at times ``t_s`` ``(N,)``: (index in the model's
    parameter vector, growth ``(N,)`` mm) for each active one."""
    out = []
    if settings.thermal_drift:
        index = 5 * (settings.drift_joint - 1) + _PARAMETER_OFFSET[settings.drift_parameter]
        out.append((index, length_drift_mm(settings, t_s)))
    if settings.thermal_lag:
        index = 5 * (settings.lag_joint - 1) + _PARAMETER_OFFSET[settings.lag_parameter]
        out.append((index, length_lag_mm(settings, t_s)))
    return out


def true_point_mm(
    settings: UndeclaredEffects,
    arm: ArmLike,
    link: int,
    point_mm: ArrayLike,
    q_ring_rad: ArrayLike,
    t_s: ArrayLike,
    direction: ArrayLike | None = None,
    force_n: ArrayLike | None = None,
) -> FloatArray:
    """Physical position ``(N, 3)`` mm, tracker frame, of a point fixed in link ``link``'s
    frame (0-based; ``point_mm`` ``(3,)``) at ring angles ``(N, n)`` and times ``(N,)``,
    with an optional process force ``(N, 3)`` N on the tool.

    Links 1..link+1 stand at the ring angles plus :func:`link_rotation_rad`, each bent
    about its own x and y axes by :func:`bending_rotation_rad` (at the ring angles); a changing
    length upstream of the point adds along its own direction, the thermal expansion of
    every length along their sum (a point is linear in every a and d, so this is exact).
    """
    body = physical_arm(arm)
    q = np.atleast_2d(np.asarray(q_ring_rad, dtype=float))
    q_link = q + link_rotation_rad(settings, body, q, direction, force_n)
    sub = body.model.truncated(link + 1, tool_mm=point_mm)
    q_sub = q_link[:, : link + 1]
    pts = tcp_positions(sub, q_sub)
    x = sub.parameter_vector()
    if settings.thermal_expansion:
        lengths = np.zeros_like(x, dtype=bool)
        lengths[0 : 5 * (link + 1) : 5] = lengths[2 : 5 * (link + 1) : 5] = True
        grown = x.copy()
        grown[lengths] *= 1.0 + 1e-6
        per_ppm = tcp_positions(sub.with_parameters(grown), q_sub) - pts
        pts = pts + expansion_ppm(settings, np.broadcast_to(t_s, (len(q),)))[:, None] * per_ppm
    for index, growth in length_changes(settings, np.broadcast_to(t_s, (len(q),))):
        if index >= 5 * (link + 1):  # downstream of the point's link
            continue
        bumped = x.copy()
        bumped[index] += 1.0
        axis = tcp_positions(sub.with_parameters(bumped), q_sub) - pts  # per mm of growth
        pts = pts + growth[:, None] * axis
    if settings.link_bending:
        pts = _bent(body, pts, q_link, bending_rotation_rad(settings, body, q), link)
    return pts


def true_tcp_mm(
    settings: UndeclaredEffects,
    arm: ArmLike,
    q_ring_rad: ArrayLike,
    t_s: ArrayLike,
    direction: ArrayLike | None = None,
    force_n: ArrayLike | None = None,
) -> FloatArray:
    """Physical TCP ``(N, 3)`` mm in the tracker frame at ring angles and times, under an
    optional process force ``(N, 3)`` N (:func:`true_point_mm` of the tool point)."""
    body = physical_arm(arm)
    n = body.n_joints
    tool = body.model.tool_mm
    return true_point_mm(settings, body, n - 1, tool, q_ring_rad, t_s, direction, force_n)


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
