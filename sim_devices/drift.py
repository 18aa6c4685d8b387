"""The cell's truth moving with time: thermal growth, base creep and steps (all off by default).

Production starts at ``start_s`` on the calibration campaign's clock (the campaign itself
sees the cell as it was calibrated); from then on, with ``u = t − start_s``:

* **thermal growth**: every link length (``a`` and ``d`` of each joint) grows by
  ``g_j · ppm · 1e-6 · length · (1 − e^(−u/τ))`` (the arm warming up); ``g_j`` in
  [0.5, 1.5] is drawn per joint from the seed (links warm unequally);
* **base creep**: the robot base slides at ``creep_mm_per_h`` in a seed-drawn horizontal
  direction and turns about its vertical axis at ``creep_mdeg_per_h``;
* **steps** at seed-drawn times in the middle of the program: ``tracker_bump`` (the tracker
  moved by ``bump_mm`` and turned by ``bump_deg`` about a random axis: every later point
  is read in a moved frame) and ``tool_remount`` (the target remounted ``remount_mm`` off
  in a random direction of the flange frame).

Points are linear in every ``a``, ``d`` and tool coordinate, so the thermal growth and the
remount are added exactly through the identification Jacobian of the true model. The twin
is never told what moved or when: only the points (and a test's truth file) carry it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.kinematics import KinematicModel, identification_jacobian

FloatArray = NDArray[np.float64]

#: Step kinds (the ``--drift-step`` choices) -> what they are.
STEP_KINDS: dict[str, str] = {
    "tracker_bump": "the tracker moved 0.2 mm and turned 0.05° (every later point moves)",
    "tool_remount": "the tracker target remounted 0.3 mm off on the flange",
}


@dataclass(frozen=True)
class CellDrift:
    """How the cell's truth moves during production (off by default)."""

    thermal: bool = False
    thermal_ppm: float = 40.0  # final growth: ~11.5 ppm/K steel over 3.5 K of warm-up
    thermal_time_constant_s: float = 3600.0
    creep: bool = False
    creep_mm_per_h: float = 0.02
    creep_mdeg_per_h: float = 0.5
    steps: tuple[str, ...] = ()  # kinds of STEP_KINDS, each once at a drawn time
    bump_mm: float = 0.2
    bump_deg: float = 0.05
    remount_mm: float = 0.3
    # the live cell (sim-cell) only; the campaign generator starts production 10 min after
    # its campaign and draws the steps over its --check-hours
    start_s: float = -1.0  # production's start, simulated s; < 0: the program's (see plant)
    span_s: float = 28800.0  # production's length, simulated s: the steps fall in its middle 60 %

    @property
    def any_active(self) -> bool:
        return self.thermal or self.creep or bool(self.steps)

    def document(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class DriftDraws:
    """What the seed drew for one program: per-joint thermal gains, the creep direction,
    and each step's time (s, campaign clock) and direction."""

    start_s: float
    thermal_gain: FloatArray  # (n,)
    creep_direction: FloatArray  # (3,) unit, horizontal in the tracker frame
    step_times_s: dict[str, float] = field(default_factory=dict)
    bump_axis: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    bump_shift: FloatArray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    remount_direction: FloatArray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))

    def document(self) -> dict[str, Any]:
        return {
            "start_s": self.start_s,
            "thermal_gain": self.thermal_gain.tolist(),
            "creep_direction": self.creep_direction.tolist(),
            "step_times_s": dict(self.step_times_s),
            "bump_axis": self.bump_axis.tolist(),
            "bump_shift": self.bump_shift.tolist(),
            "remount_direction": self.remount_direction.tolist(),
        }


def _unit(v: FloatArray) -> FloatArray:
    out: FloatArray = v / np.linalg.norm(v)
    return out


def draw_drift(
    settings: CellDrift, n_joints: int, start_s: float, end_s: float, rng: np.random.Generator
) -> DriftDraws:
    """The program's random draws (always the same number, whatever is switched on, so a
    seed's checks differ between settings by the drift alone). Steps fall in the middle
    60 % of ``[start_s, end_s]``."""
    gain = rng.uniform(0.5, 1.5, n_joints)
    creep = np.array([*rng.normal(size=2), 0.0])
    span = end_s - start_s
    times = rng.uniform(start_s + 0.2 * span, start_s + 0.8 * span, len(STEP_KINDS))
    axis, shift, remount = (_unit(rng.normal(size=3)) for _ in range(3))
    step_times = {
        k: float(t) for k, t in zip(STEP_KINDS, times, strict=True) if k in settings.steps
    }
    return DriftDraws(start_s, gain, _unit(creep), step_times, axis, shift, remount)


def _rotation_about(axis: FloatArray, angle_rad: float) -> FloatArray:
    """Rodrigues' rotation ``(3, 3)`` about a unit ``axis``."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    r: FloatArray = np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)
    return r


def drifted_tcp_mm(
    settings: CellDrift,
    draws: DriftDraws,
    model: KinematicModel,
    q_rad: ArrayLike,
    t_s: ArrayLike,
) -> FloatArray:
    """The true TCP ``(N, 3)`` mm, as the (possibly bumped) tracker frame sees it, of the
    true ``model`` at joints ``(N, n)`` rad and times ``(N,)`` s."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    t = np.broadcast_to(np.asarray(t_s, dtype=float), (len(q),))
    p, jac = identification_jacobian(model, q)
    return rigid_drift_mm(
        settings, draws, model.base_mm, _grown(settings, draws, model, jac, t, p), t
    )


def drifted_points_mm(
    settings: CellDrift,
    draws: DriftDraws,
    model: KinematicModel,
    q_rad: ArrayLike,
    t_s: ArrayLike,
    points_mm: FloatArray,
    *,
    tcp: bool,
) -> FloatArray:
    """True points ``(N, 3)`` mm of the undrifted cell (its physical effects included) at
    joints ``(N, n)`` rad and times ``(N,)`` s, as the drifting cell's tracker sees them:
    a TCP target (``tcp``) gets all of the drift (the growth and the remount through the
    true ``model``'s Jacobian, as :func:`drifted_tcp_mm`), a target on a link the rigid
    part alone (base creep, tracker bump; its links' growth is left out)."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    t = np.broadcast_to(np.asarray(t_s, dtype=float), (len(q),))
    p = np.asarray(points_mm, dtype=float)
    if tcp and (settings.thermal or "tool_remount" in draws.step_times_s):
        p = _grown(settings, draws, model, identification_jacobian(model, q)[1], t, p)
    return rigid_drift_mm(settings, draws, model.base_mm, p, t)


def _grown(
    settings: CellDrift,
    draws: DriftDraws,
    model: KinematicModel,
    jac: FloatArray,
    t: FloatArray,
    p: FloatArray,
) -> FloatArray:
    """``p`` ``(N, 3)`` plus the thermal growth and the remounted tool, linear through the
    identification Jacobian ``jac`` ``(N, 3, P)`` of the true model (exact: a point is
    linear in every ``a``, ``d`` and tool coordinate)."""
    n = model.n_joints
    if settings.thermal:
        u = np.maximum(t - draws.start_s, 0.0)
        warm = 1e-6 * settings.thermal_ppm * (1.0 - np.exp(-u / settings.thermal_time_constant_s))
        for j in range(n):
            for col, length in ((5 * j, model.a_mm[j]), (5 * j + 2, model.d_mm[j])):
                p = p + (warm * draws.thermal_gain[j] * length)[:, None] * jac[:, :, col]
    t_remount = draws.step_times_s.get("tool_remount")
    if t_remount is not None:
        offset = settings.remount_mm * draws.remount_direction
        moved = (t >= t_remount)[:, None]
        p = p + moved * np.einsum("mij,j->mi", jac[:, :, 5 * n + 6 :], offset)
    return p


def rigid_drift_mm(
    settings: CellDrift, draws: DriftDraws, base_mm: FloatArray, p: FloatArray, t: FloatArray
) -> FloatArray:
    """Points ``p`` ``(N, 3)`` mm at times ``t`` ``(N,)`` s moved by the rigid drift: the
    base's creep (a turn about the vertical through ``base_mm`` and a slide) and, from its
    time on, the bumped tracker's frame."""
    if settings.creep:
        hours = np.maximum(t - draws.start_s, 0.0) / 3600.0
        angle = np.radians(1e-3 * settings.creep_mdeg_per_h * hours)
        rel = p - base_mm
        c, s = np.cos(angle), np.sin(angle)
        turned = np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1], rel[:, 2]])
        p = (
            base_mm
            + turned.T
            + (settings.creep_mm_per_h * hours)[:, None] * (draws.creep_direction)
        )
    t_bump = draws.step_times_s.get("tracker_bump")
    if t_bump is not None:
        rot = _rotation_about(draws.bump_axis, np.radians(settings.bump_deg))
        bumped = rot.T @ (p - settings.bump_mm * draws.bump_shift).T
        p = np.where((t >= t_bump)[:, None], bumped.T, p)
    return p
