"""The live twin's model, cheap per batch: joint angles from grating counts through the
scale maps (:class:`AngleReader`), and the TCP, flange and link frames from the calibrated
geometry with its effects (:class:`TwinPredictor`: the chain's matrices built once, one
vectorised walk per batch).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from calibration.model.description import RobotDescription
    from calibration.model.kinematics import KinematicModel
    from calibration.scales.scale_files import ScaleCalibration

FloatArray = NDArray[np.float64]


class AngleReader:
    """Joint angles (deg) from grating counts through the scale maps, cheap per batch.

    The scale maps are smooth functions of the counts (a scale, harmonics of the ring,
    at most a slow polynomial), evaluated per joint by
    :meth:`~calibration.scales.grating_scale.GratingScale.counts_to_angle_deg` at a cost per
    call (~0.2-0.3 ms for six joints here). As :class:`TwinPredictor` does for the
    effects, each map is linearised at the newest sample's counts (value and slope from
    one call with ``c0``, ``c0 ± h``) and used within ``radius_deg`` of it; a sample
    farther away moves the linearisation there, a batch wider than the radius gets the
    maps themselves. Error: second order, ~2e-6° at most at 0.25° for the demo's maps
    (far below one count, ~1e-4°; tests/test_twin_predictor.py); ``radius_deg = 0``:
    the maps for every batch."""

    def __init__(
        self, scale: ScaleCalibration, n: int, home_deg: ArrayLike, *, radius_deg: float = 0.25
    ) -> None:
        self.maps = [scale.scale(j) for j in range(1, n + 1)]
        self.home = np.asarray(home_deg, dtype=float)
        self.radius_deg = float(radius_deg)
        self.h = 64  # counts
        self._c0: np.ndarray | None = None
        self._a0 = np.zeros(n)
        self._slope = np.zeros(n)
        self._radius_counts = np.zeros(n)
        self.refreshes = 0
        self.full_calls = 0

    def exact(self, counts: np.ndarray) -> np.ndarray:
        self.full_calls += 1
        cols = [mp.counts_to_angle_deg(counts[:, j]) for j, mp in enumerate(self.maps)]
        out: np.ndarray = self.home + np.column_stack(cols)
        return out

    def _linearise(self, c0: np.ndarray) -> None:
        h = self.h
        for j, mp in enumerate(self.maps):
            a = mp.counts_to_angle_deg(np.array([c0[j], c0[j] + h, c0[j] - h], dtype=np.int64))
            self._a0[j] = a[0]
            self._slope[j] = (a[1] - a[2]) / (2 * h)
        with np.errstate(divide="ignore"):
            self._radius_counts = np.where(
                self._slope != 0, self.radius_deg / np.abs(self._slope), 0.0
            )
        self._c0 = c0.copy()
        self.refreshes += 1

    def _offsets(self, counts: np.ndarray) -> np.ndarray:
        assert self._c0 is not None  # counts since c0, undoing 32-bit counter wraps
        out: np.ndarray = (counts - self._c0 + (1 << 31)) % (1 << 32) - (1 << 31)
        return out

    def angles(self, counts: np.ndarray) -> np.ndarray:
        """Joint angles ``(m, n)`` deg (Home + map) of counts ``(m, n)``."""
        if self.radius_deg <= 0:
            return self.exact(counts)
        if self._c0 is None or bool(
            np.any(np.abs(self._offsets(counts[-1])) > self._radius_counts)
        ):
            self._linearise(counts[-1])
        d = self._offsets(counts)
        if bool(np.any(np.abs(d) > self._radius_counts)):  # a batch wider than the radius
            return self.exact(counts)
        return self.home + self._a0 + d * self._slope


class TwinPredictor:
    """TCP and flange poses of the calibrated model, cheap enough per grating batch.

    The geometric TCP and flange are evaluated for every sample (one vectorized chain
    walk). What the modelled effects add to the TCP, ``c(q, t)``, comes from the full
    predictor (:func:`~calibration.effects.model_effects.predict_tcp`), whose cost is per call
    (1.5-5 ms here for one pose of the demo's model with its gravity deflection, ~90 % of
    the twin's time per batch before), so it is *linearised*: at a pose ``q0`` the
    predictor is evaluated once for ``q0`` and ``q0 ± h·e_j`` (one call, 2n + 1 poses) and
    the samples within ``radius_deg`` of ``q0`` (every joint) get ``c(q0) + G·(q − q0)``.
    The linearisation moves with the robot: a sample farther than the radius, or more
    than ``max_age_s`` later (time terms), makes the newest sample the next ``q0``; a
    batch that spans more than the radius gets the full predictor. The error is second
    order: ≈ ½·|c''|·Δq², below 1e-4 mm for the emulated cell's gravity deflection at
    0.25° (tests/test_twin_predictor.py against the full predictor).
    ``radius_deg = 0``: the full predictor for every batch (as the twin did before).
    """

    def __init__(
        self,
        desc: RobotDescription,
        *,
        radius_deg: float = 0.25,
        max_age_s: float = 1.0,
        h_rad: float = 4e-6,
    ) -> None:
        from calibration.effects.model_effects import description_effects
        from calibration.model.kinematics import KinematicModel

        self.desc = desc
        self.model = KinematicModel.from_description(desc)
        specs, _ = description_effects(desc)
        self.has_effects = bool(specs)
        self.radius = float(np.radians(radius_deg))
        self.radius_deg = float(radius_deg)
        self.max_age_s = float(max_age_s)
        # below calibration.effects.effect_base.MIN_MOVE_RAD: the stencil's poses keep q0's
        # approach directions (direction-dependent terms see one pose, not a motion)
        self.h = float(h_rad)
        self._q0: np.ndarray | None = None
        self._t0 = 0.0
        self._c0 = np.zeros(3)
        self._g = np.zeros((desc.n_joints, 3))
        self.refreshes = 0
        self.full_calls = 0
        n = desc.n_joints
        self.frame_names: tuple[str, ...] = ("base", *(f"link{i + 1}" for i in range(n)), "tcp")
        self._calibrated = _ChainConstants.of(self.model)
        self._chain_of = self._calibrated  # the published geometry (tracked: set_geometry)

    def set_geometry(self, model: KinematicModel) -> None:
        """Publish ``model``'s geometry from now on (the tracked model: a dwell updated it);
        the effects' share stays the calibrated description's (linearised against its
        geometry), as :func:`calibration.twin.tracking.effect_offsets` holds it."""
        self.model = model
        self._chain_of = _ChainConstants.of(model)

    def describe(self) -> dict[str, Any]:
        return {
            "modelled": self.has_effects,
            "linearised_radius_deg": self.radius_deg,
            "linearisations": self.refreshes,
            "full_predictor_calls": self.full_calls,
        }

    def _chain(
        self, q_rad: np.ndarray, keep: bool, consts: _ChainConstants | None = None
    ) -> list[np.ndarray]:
        """Poses ``(m, 4, 4)`` of the base and of the frame after each joint (``keep``),
        else of the flange alone; one small matmul per joint and factor (``consts``: the
        geometry, default the published one)."""
        k = self._chain_of if consts is None else consts
        q = np.atleast_2d(q_rad)
        m, n = q.shape
        theta = q + k.theta_offset_rad
        c, s_ = np.cos(theta), np.sin(theta)
        z = np.zeros((m, n, 4, 4))  # Rz(θ)·Trans_z(d)
        z[:, :, 0, 0] = c
        z[:, :, 0, 1] = -s_
        z[:, :, 1, 0] = s_
        z[:, :, 1, 1] = c
        z[:, :, 2, 2] = 1.0
        z[:, :, 2, 3] = k.d_mm
        z[:, :, 3, 3] = 1.0
        t = np.broadcast_to(k.base, (m, 4, 4))
        out = [t] if keep else []
        for i in range(n):
            t = t @ k.link[i] @ z[:, i]
            if keep:
                out.append(t)
        return out if keep else [t]

    def _geometric(
        self, q_rad: np.ndarray, consts: _ChainConstants | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        k = self._chain_of if consts is None else consts
        fl = self._chain(q_rad, keep=False, consts=k)[0]
        return (fl @ k.tool)[:, :3], fl

    def _full(self, q_rad: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        from calibration.effects.model_effects import predict_tcp

        self.full_calls += 1
        return predict_tcp(self.desc, q_rad, t_s)

    def _linearise(self, q0: np.ndarray, t0: float) -> None:
        n = len(q0)
        step = self.h * np.eye(n)
        qs = np.vstack([q0, q0 + step, q0 - step])
        c = self._full(qs, np.full(len(qs), t0)) - self._geometric(qs, self._calibrated)[0]
        self._c0 = c[0]
        self._g = (c[1 : n + 1] - c[n + 1 :]) / (2 * self.h)  # (n, 3): dc/dq_j
        self._q0 = q0.copy()
        self._t0 = t0
        self.refreshes += 1

    def tcp_and_flange(self, q_rad: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP ``(m, 3)`` mm with the modelled effects and flange poses ``(m, 4, 4)``."""
        tcp, fl = self._geometric(q_rad)
        if not self.has_effects:
            return tcp, fl
        if self.radius <= 0:
            return self._full(q_rad, t_s), fl
        q_new, t_new = q_rad[-1], float(t_s[-1])
        if (
            self._q0 is None
            or float(np.max(np.abs(q_new - self._q0))) > self.radius
            or abs(t_new - self._t0) > self.max_age_s
        ):
            self._linearise(q_new, t_new)
        assert self._q0 is not None
        dq = q_rad - self._q0
        if float(np.max(np.abs(dq))) > self.radius:  # a batch wider than the radius
            return self._full(q_rad, t_s), fl
        return tcp + self._c0 + dq @ self._g, fl

    def frames(self, q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Origins ``(m, k, 3)`` mm and rotations ``(m, k, 4)`` (w, x, y, z) of the frames
        ``frame_names`` (base, the frame after each joint, the TCP), tracker frame,
        geometry only (the modelled effects move the TCP by well under a millimetre)."""
        poses = self._chain(q_rad, keep=True)
        t = np.stack(poses, axis=1)  # (m, n + 1, 4, 4)
        m, k = t.shape[0], t.shape[1] + 1
        pos = np.empty((m, k, 3))
        pos[:, :-1] = t[:, :, :3, 3]
        pos[:, -1] = (poses[-1] @ self._chain_of.tool)[:, :3]
        rot = np.concatenate([t[:, :, :3, :3], t[:, -1:, :3, :3]], axis=1)
        quat = rotation_quaternions(rot.reshape(-1, 3, 3)).reshape(m, k, 4)
        return pos, quat


@dataclass(frozen=True)
class _ChainConstants:
    """A geometry's chain as 4x4 matrices, built once: joint i is Trans_x(a)·Rx(α)Ry(β) ·
    Rz(θ + offset)·Trans_z(d), as calibration.model.kinematics walks it."""

    base: np.ndarray  # (4, 4)
    link: np.ndarray  # (n, 4, 4)
    tool: np.ndarray  # (4,) homogeneous
    theta_offset_rad: np.ndarray  # (n,)
    d_mm: np.ndarray  # (n,)

    @classmethod
    def of(cls, md: KinematicModel) -> _ChainConstants:
        base = np.eye(4)
        base[:3, :3] = md.base_rotation()
        base[:3, 3] = md.base_mm
        link = np.zeros((md.n_joints, 4, 4))
        link[:, :3, :3] = md.link_constants()
        link[:, 0, 3] = md.a_mm
        link[:, 3, 3] = 1.0
        tool = np.append(md.tool_mm, 1.0)
        return cls(base, link, tool, np.asarray(md.theta_offset_rad), np.asarray(md.d_mm))


def rotation_quaternions(r: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(N, 4)`` (w, x, y, z) of rotation matrices ``(N, 3, 3)``."""
    w = np.sqrt(np.maximum(0.0, 1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2])) / 2
    x = np.sqrt(np.maximum(0.0, 1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2])) / 2
    y = np.sqrt(np.maximum(0.0, 1.0 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2])) / 2
    z = np.sqrt(np.maximum(0.0, 1.0 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2])) / 2
    x = np.copysign(x, r[:, 2, 1] - r[:, 1, 2])
    y = np.copysign(y, r[:, 0, 2] - r[:, 2, 0])
    z = np.copysign(z, r[:, 1, 0] - r[:, 0, 1])
    q = np.column_stack([w, x, y, z])
    out: np.ndarray = q / np.linalg.norm(q, axis=1, keepdims=True)
    return out
