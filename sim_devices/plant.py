"""The emulated physical robot: truth, robot program, joint/motor/target states over time.

The :class:`Plant` owns the truth (:class:`sim_devices.truth.TrueCell`), a robot program
(:class:`sim_devices.motion.Trajectory`) and the effects of the cell's configuration. The
controller servos the *motors* to the commanded joint vector ``q_cmd``; the joint
*outputs*, which the gratings, the TCP and the tracker see, differ from it by gear torsion
under the arm's static load (``tau / K``) and by the backlash flank
(:class:`sim_devices.gears.GearTrain`; tau from the emulator's own masses and
counterbalance, :class:`sim_devices.physical_arm.PhysicalArm`). Motor encoders read
``gear_ratio · q_cmd``. All evaluations are vectorized over arrays of simulated times.

The undeclared effects of ``[effects.undeclared]`` (:mod:`sim_devices.effects`, the same
physics as the campaign generators): gravity deflection after the ring and the thermal
link drift and lag move the target (:meth:`Plant.target_mm`), the cyclic grating error
changes the counts (:meth:`Plant.grating_counts`), a constant tracker scale error goes to
the tracker model. Drift and lag follow program time; a caller that does not pass the
sample's time gets the clock's current time (the drift moves 4e-5 mm/s at 0.15 mm/h).

Which target the tracker measures (``[tracker] target``): ``"program"`` (default) follows
the robot program — in the campaign the target fixed on link J during joint J's Home
returns and sweeps (``TrueCell.link_target_mm``), the TCP target for the poses (method.md
§2-3), the operator moving the reflector in a zero-motion move between the phases; free
programs keep the TCP. ``"tcp"`` / ``"linkN"`` pin one target for the whole run. A link
target sees the effects physically downstream of its link: the gravity deflection of rings
1..J and a drifting length of joints 1..J; sag, tracker scale and noise apply to every
target.

The cell's drift (``[effects.drift]``, :mod:`sim_devices.drift`'s physics) moves the
truth on the simulated clock from production's start (:func:`production_start_s`): a TCP
target by all of it, a link target by its rigid part (base creep, tracker bump); the
seed's draws are in the truth document. The ``production`` program
(:func:`production_program`) shows the tracker the reflector only at its check poses.

Clocks: :class:`SimClock` maps the host's ``time.monotonic()`` to wall seconds since the
emulator started and to simulated robot-program seconds (``speed`` times faster); each
device has its own :class:`DeviceClock` (drift in ppm, restarts).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel, tcp_positions
from sim_devices.config import CellConfig, CellSection, read_plan, read_plan_sweeps
from sim_devices.drift import DriftDraws, draw_drift, drifted_points_mm
from sim_devices.effects import (
    grating_reading_rad,
    true_point_mm,
    true_tcp_mm,
    with_derived_stiffness,
)
from sim_devices.gears import GearTrain
from sim_devices.motion import HIDDEN, Move, Trajectory, parse_target
from sim_devices.truth import TrackerModel, TrueCell

FloatArray = NDArray[np.float64]

#: Default joint speed/acceleration limits of a KR500-class arm (deg/s, deg/s²).
DEFAULT_VMAX_DEG_S = (105.0, 94.0, 94.0, 120.0, 120.0, 180.0)
DEFAULT_AMAX_DEG_S2 = (200.0, 200.0, 200.0, 300.0, 300.0, 400.0)


class SimClock:
    """Wall seconds since start, and simulated program seconds (``speed`` × wall)."""

    def __init__(self, speed: float = 1.0, t0_monotonic: float | None = None) -> None:
        self.speed = speed
        self.t0 = time.monotonic() if t0_monotonic is None else t0_monotonic

    def wall_s(self) -> float:
        return time.monotonic() - self.t0

    def sim_s(self, wall_s: ArrayLike | None = None) -> FloatArray:
        w = self.wall_s() if wall_s is None else wall_s
        return np.asarray(w, dtype=float) * self.speed


@dataclass
class DeviceClock:
    """A device's free-running µs clock: drifts by ``ppm`` and restarts when rebooted.

    ``device_us(wall)`` is the clock at wall time ``wall`` (s since emulator start);
    ``wall_of(device_us)`` inverts it within the current boot. The device counter is
    ``bits`` wide (the wire value wraps).
    """

    ppm: float = 0.0
    start_us: int = 0
    boot_wall_s: float = 0.0
    boot_count: int = 0

    @property
    def rate(self) -> float:
        return 1.0 + 1e-6 * self.ppm

    def device_us(self, wall_s: ArrayLike) -> FloatArray:
        return (
            self.start_us + (np.asarray(wall_s, dtype=float) - self.boot_wall_s) * 1e6 * self.rate
        )

    def wall_of(self, device_us: ArrayLike) -> FloatArray:
        return self.boot_wall_s + (np.asarray(device_us, dtype=float) - self.start_us) / (
            1e6 * self.rate
        )

    def reboot(self, wall_s: float) -> None:
        self.boot_wall_s = wall_s
        self.start_us = 0
        self.boot_count += 1


@dataclass(frozen=True, eq=False)
class JointState:
    """Joint states at N instants: commanded, output (true), motor angles; all ``(N, n)``."""

    q_cmd_rad: FloatArray
    q_out_rad: FloatArray
    motor_rad: FloatArray


class Plant:
    """The robot cell's physics as seen by the devices."""

    def __init__(
        self, cell: TrueCell, trajectory: Trajectory, config: CellConfig, clock: SimClock
    ) -> None:
        self.cell = cell
        self.trajectory = trajectory
        self.config = config
        self.clock = clock
        self.truth_model: KinematicModel = cell.model
        self.arm = cell.arm
        n = cell.truth.n_joints
        gears = [j.gear_ratio if j.gear_ratio else 100.0 for j in cell.truth.joints]
        self.gear_ratio = np.array(gears, dtype=float)
        self.gears = GearTrain.of(config.effects, n)
        # derive the deflection stiffness once, not per sample
        self.undeclared = with_derived_stiffness(config.effects.undeclared, cell.arm)
        #: pinned target (``[tracker] target = "linkN"``), else None
        self.link_joint: int | None = None
        target = config.tracker.target
        self.follow_program = target == "program"
        if target.startswith("link"):
            self.link_joint = int(target[4:]) - 1
            if not 0 <= self.link_joint < n:
                raise ValueError(f"tracker target {target}: robot has {n} joints")
        #: per program move: -1 the TCP target, -2 none in view (HIDDEN), else the
        #: 0-based joint whose link carries the target
        self._target_table = np.array(
            [_target_index(trajectory.target_of(k)) for k in range(len(trajectory.labels))],
            dtype=np.intp,
        )
        for k, j in enumerate(self._target_table.tolist()):
            if not j < n:
                raise ValueError(f"program move {k}: target link:{j + 1}, robot has {n} joints")
        self._blocks: dict[int, FloatArray] = {}
        #: the truth's drift ([effects.drift]) and the seed's draws for it; None: none
        self.drift = config.effects.drift
        self.drift_draws: DriftDraws | None = None
        if self.drift.any_active:
            start = production_start_s(config.cell, trajectory, self.drift.start_s)
            self.drift_draws = draw_drift(
                self.drift,
                n,
                start,
                start + self.drift.span_s,
                np.random.default_rng([config.cell.seed, 28]),
            )

    @classmethod
    def from_config(cls, config: CellConfig, clock: SimClock | None = None) -> Plant:
        nominal = load_robot(config.cell.robot)
        und = config.effects.undeclared
        tracker = TrackerModel(scale_error_ppm=und.tracker_scale_ppm) if und.tracker_scale else None
        cell = TrueCell.create(
            nominal, config.cell.seed, eccentricity_mm=config.cell.eccentricity_mm, tracker=tracker
        )
        rng = np.random.default_rng(config.cell.seed + 1)
        planned = read_plan(config, nominal, "cell config")
        trajectory = build_program(
            config.cell.program,
            nominal,
            rng,
            planned,
            start_hold_s=config.cell.start_hold_s,
            cell=config.cell,
            sweeps=read_plan_sweeps(config, nominal, "cell config"),
        )
        return cls(cell, trajectory, config, clock or SimClock(config.cell.speed))

    @property
    def n_joints(self) -> int:
        return self.cell.truth.n_joints

    def joint_state(self, sim_s: ArrayLike) -> JointState:
        """States at simulated times ``(N,)``.

        The trajectory is evaluated exactly; the slowly varying output correction (torsion,
        backlash) is interpolated from a grid of :attr:`CORRECTION_STEP_S` computed in
        blocks, which keeps a call for a handful of samples cheap.
        """
        t = np.atleast_1d(np.asarray(sim_s, dtype=float))
        q_cmd, _qd, _direction = self.trajectory.evaluate(t)
        q_out = q_cmd + self._correction(t) if self._has_correction else q_cmd.copy()
        return JointState(q_cmd, q_out, q_cmd * self.gear_ratio)

    CORRECTION_STEP_S = 0.005
    CORRECTION_BLOCK = 400  # grid points per cached block (2 s of program time)

    @property
    def _has_correction(self) -> bool:
        return self.gears.active

    @property
    def stiffness(self) -> FloatArray:
        """Gear stiffness ``(n,)`` N·mm/rad."""
        return self.gears.stiffness_nmm_per_rad

    @property
    def backlash_rad(self) -> FloatArray:
        """Full backlash gap ``(n,)`` rad."""
        return self.gears.backlash_rad

    def output_correction_exact(self, sim_s: ArrayLike) -> FloatArray:
        """``q_out - q_cmd`` ``(N, n)`` rad: gear torsion under the arm's static load plus
        the backlash flank (:meth:`GearTrain.ring_offset_rad`)."""
        q_cmd, _qd, direction = self.trajectory.evaluate(sim_s)
        return self.gears.ring_offset_rad(self.arm.joint_torques_nmm(q_cmd), direction)

    def _correction(self, t: FloatArray) -> FloatArray:
        h = self.CORRECTION_STEP_S
        pos = np.maximum(t, 0.0) / h
        i0 = np.floor(pos).astype(np.int64)
        frac = (pos - i0)[:, None]
        out = np.empty((t.shape[0], self.n_joints))
        blocks = i0 // self.CORRECTION_BLOCK
        for b in np.unique(blocks).tolist():
            grid = self._correction_block(b)
            sel = blocks == b
            j = i0[sel] - b * self.CORRECTION_BLOCK
            out[sel] = grid[j] * (1.0 - frac[sel]) + grid[j + 1] * frac[sel]
        return out

    def _correction_block(self, b: int) -> FloatArray:
        grid = self._blocks.get(b)
        if grid is None:
            n = self.CORRECTION_BLOCK
            times = (b * n + np.arange(n + 1)) * self.CORRECTION_STEP_S
            grid = self.output_correction_exact(times)
            if len(self._blocks) > 8:
                self._blocks.pop(next(iter(self._blocks)))
            self._blocks[b] = grid
        return grid

    def target_at(self, wall_s: ArrayLike | None = None) -> list[str]:
        """The target the tracker measures at wall times ``(N,)``: "tcp" or "link:J"."""
        n = 1 if wall_s is None else int(np.size(wall_s))
        return ["tcp" if j < 0 else f"link:{j + 1}" for j in self._links(wall_s, n).tolist()]

    def tcp_target(self, wall_s: ArrayLike | None, n: int) -> NDArray[np.bool_]:
        """Per sample ``(n,)``: the tracker's target is the TCP reflector (not a link's)."""
        tcp: NDArray[np.bool_] = self._links(wall_s, n) == -1
        return tcp

    def hidden_target(self, wall_s: ArrayLike | None, n: int) -> NDArray[np.bool_]:
        """Per sample ``(n,)``: no target in the tracker's view (a move of the program
        with target ``"none"``: the production program's work between its checks)."""
        hidden: NDArray[np.bool_] = self._links(wall_s, n) == -2
        return hidden

    def _links(self, wall_s: ArrayLike | None, n: int) -> NDArray[np.intp]:
        """Per sample: -1 for the TCP target, -2 for none in view, else the 0-based joint
        carrying the target."""
        if self.link_joint is not None:
            return np.full(n, self.link_joint, dtype=np.intp)
        if not self.follow_program:
            return np.full(n, -1, dtype=np.intp)
        wall = self.clock.wall_s() if wall_s is None else wall_s
        seg = self.trajectory.segments_at(np.broadcast_to(self.clock.sim_s(wall), (n,)))
        out: NDArray[np.intp] = self._target_table[seg]
        return out

    def link_target_mm(self, joint: int, q_out_rad: FloatArray, sim_s: ArrayLike) -> FloatArray:
        """True position ``(N, 3)`` of the target on link ``joint`` (0-based), with the
        undeclared effects upstream of it (deflection after rings 1..joint+1, drift, lag)."""
        target = self.cell.link_targets_mm[joint]
        return true_point_mm(self.undeclared, self.arm, joint, target, q_out_rad, sim_s)

    def target_mm(self, q_out_rad: FloatArray, wall_s: ArrayLike | None = None) -> FloatArray:
        """True target positions ``(N, 3)`` in the tracker frame for joint outputs.

        Which target (TCP or a link's) follows the program at the samples' wall times
        ``wall_s`` (``(N,)`` or scalar), or at the clock's current time when not given
        (none in view: the TCP's point, which the tracker does not report). The cell's
        drift (``[effects.drift]``) moves them last, on the simulated clock: the tracker
        frame moves with a bump, so it is the outermost transform.
        """
        q = np.atleast_2d(q_out_rad)
        und = self.undeclared
        links = self._links(wall_s, len(q))
        tcp = links < 0
        pts = np.empty((len(q), 3))
        if tcp.any():
            qt = q[tcp]
            if (
                und.gravity_deflection
                or und.thermal_drift
                or und.thermal_lag
                or und.thermal_expansion
                or und.link_bending
            ):
                wall = self.clock.wall_s() if wall_s is None else wall_s
                sim = np.broadcast_to(self.clock.sim_s(wall), (len(q),))[tcp]
                pts[tcp] = true_tcp_mm(und, self.arm, qt, sim)
            else:
                pts[tcp] = tcp_positions(self.truth_model, qt)
        if not tcp.all():
            wall = self.clock.wall_s() if wall_s is None else wall_s
            sim = np.broadcast_to(self.clock.sim_s(wall), (len(q),))
            for j in np.unique(links[~tcp]).tolist():
                sel = links == j
                pts[sel] = self.link_target_mm(j, q[sel], sim[sel])
        if self.config.effects.sag:
            base = self.truth_model.base_mm
            reach_m = np.linalg.norm((pts - base)[:, :2], axis=1) / 1000.0
            pts[:, 2] -= self.config.effects.sag_mm_per_m2 * reach_m**2
        if self.drift_draws is not None:
            wall = self.clock.wall_s() if wall_s is None else wall_s
            sim = np.broadcast_to(self.clock.sim_s(wall), (len(q),))
            for sel, at_tcp in ((tcp, True), (~tcp, False)):
                if sel.any():
                    pts[sel] = drifted_points_mm(
                        self.drift,
                        self.drift_draws,
                        self.truth_model,
                        q[sel],
                        sim[sel],
                        pts[sel],
                        tcp=at_tcp,
                    )
        return pts

    def grating_counts(
        self, q_out_rad: FloatArray, rng: np.random.Generator, noise_counts: float
    ) -> NDArray[np.int64]:
        """Unwrapped noisy integer counts ``(N, n)`` of every strip (wrap is the reader's)."""
        out = np.empty(q_out_rad.shape, dtype=np.int64)
        q_read = grating_reading_rad(self.undeclared, q_out_rad)
        for j, strip in enumerate(self.cell.strips):
            ideal = strip.ideal_counts(q_read[:, j])
            out[:, j] = np.rint(ideal + rng.normal(0.0, noise_counts, ideal.shape)).astype(np.int64)
        return out

    def truth_document(self) -> dict[str, Any]:
        doc = self.cell.truth_document()
        doc["plant"] = {
            "gear_ratio": self.gear_ratio.tolist(),
            "stiffness_nmm_per_rad": self.stiffness.tolist(),
            "backlash_deg": np.degrees(self.backlash_rad).tolist(),
            "speed": self.clock.speed,
            "tracker_target": self.config.tracker.target,
        }
        if self.undeclared.gravity_deflection:
            k = self.undeclared.deflection_stiffness_nmm_per_rad
            doc["plant"]["deflection_stiffness_nmm_per_rad"] = [
                float(v) if np.isfinite(v) else 0.0 for v in k
            ]
        if self.drift_draws is not None:  # what moved and when (the twin is never told)
            doc["drift"] = {
                "settings": self.drift.document(),
                "draws": self.drift_draws.document(),
            }
        doc["program"] = self.trajectory.schedule()
        doc["config"] = self.config.to_document()
        return doc


# -- robot programs ------------------------------------------------------------------------


def _limits_rad(desc: RobotDescription, margin_deg: float = 1.0) -> tuple[FloatArray, FloatArray]:
    lo = np.radians([j.lower_deg + margin_deg for j in desc.joints])
    hi = np.radians([j.upper_deg - margin_deg for j in desc.joints])
    return lo, hi


def _random_poses(desc: RobotDescription, n: int, rng: np.random.Generator) -> FloatArray:
    """Joint vectors ``(n, 6)`` rad for random reachable poses.

    Uses ``sim_devices.pose_campaign.sample_reachable_poses`` (IK-based) when present;
    otherwise a simple fallback: uniform joint samples within ±60 % of each range around
    Home whose TCP stays above the robot's base plane.
    """
    try:
        from sim_devices.pose_campaign import sample_reachable_poses

        q = np.asarray(sample_reachable_poses(desc, n, rng), dtype=float)
        if q.shape == (n, desc.n_joints) and np.all(np.isfinite(q)):
            return q
    except Exception:  # helper absent or different API: fall back (noted in docs)
        pass
    model = KinematicModel.from_description(desc)
    lo, hi = _limits_rad(desc, 5.0)
    home = np.radians(desc.home)
    out: list[FloatArray] = []
    for _ in range(100):
        cand = home + 0.6 * rng.uniform(lo - home, hi - home, (4 * n, desc.n_joints))
        z = tcp_positions(model, cand, world=False)[:, 2]
        out.extend(cand[z > 200.0])
        if len(out) >= n:
            break
    return np.array(out[:n])


def campaign_moves(
    desc: RobotDescription,
    rng: np.random.Generator,
    *,
    home_returns: int = 10,
    sweep_step_deg: float = 2.0,
    slow_speed: float = 0.03,
    n_identification: int = 100,
    n_validation: int = 150,
    dwell_s: float = 1.0,
    joints: tuple[int, ...] | None = None,
    target_change_s: float = 20.0,
    poses: tuple[FloatArray, FloatArray] | None = None,
    sweeps: Mapping[int, FloatArray] | None = None,
) -> list[Move]:
    """The calibration campaign as moves (method.md §2-3).

    Per joint: ``home_returns`` returns to Home at ``slow_speed`` from random angles, then
    a sweep limit to limit stopping every ``sweep_step_deg`` and back; then the
    identification and validation poses: random, or ``poses`` (identify ``(N, n)``,
    validate ``(M, n)`` rad, a plan's, in its order). Each stop dwells ``dwell_s``.

    The tracker target (:attr:`Move.target`): on link j during joint j's returns and sweeps,
    on the TCP for the poses. The reflector is mounted on the first swept link before the
    program starts; every later change is a zero-motion move at Home whose dwell
    ``target_change_s`` is the operator moving it (the random draws do not depend on it).

    ``sweeps``: a plan's (1-based joint: its stops ``(K, n)`` rad, the others held where
    the plan puts them), swept after the joint's Home returns (:func:`_planned_sweep`).
    """
    home = np.radians(desc.home)
    lo, hi = _limits_rad(desc)
    moves: list[Move] = []
    for j in joints if joints is not None else range(desc.n_joints):
        link = f"link:{j + 1}"
        if moves:
            moves.append(Move(tuple(home), 0.3, target_change_s, f"target {link}", link))
        for r in range(home_returns):
            away = home.copy()
            away[j] = rng.uniform(lo[j], hi[j])
            moves.append(
                Move(tuple(away), 0.3, 0.2, f"joint{j + 1} home-return {r + 1} away", link)
            )
            moves.append(Move(tuple(home), slow_speed, dwell_s, f"joint{j + 1} home {r + 1}", link))
        if sweeps is not None and j + 1 in sweeps:
            moves += _planned_sweep(home, j, sweeps[j + 1], slow_speed, dwell_s, target_change_s)
            continue
        step = math.radians(sweep_step_deg)
        stops = np.tile(home, (math.floor((hi[j] - lo[j]) / step) + 1, 1))
        stops[:, j] = hi[j] - step * np.arange(len(stops))
        moves += _sweep(home, j, stops, slow_speed, dwell_s, link)
    if moves:
        moves.append(Move(tuple(home), 0.3, target_change_s, "target tcp", "tcp"))
    if poses is None:
        poses = (_random_poses(desc, n_identification, rng), _random_poses(desc, n_validation, rng))
    for name, q_set in zip(("identification", "validation"), poses, strict=True):
        for k, q in enumerate(q_set):
            moves.append(Move(tuple(q), 0.3, dwell_s, f"{name} {k}"))
    moves.append(Move(tuple(home), 0.3, 1.0, "end"))
    return moves


def _planned_sweep(
    home: FloatArray,
    j: int,
    stops: FloatArray,
    slow_speed: float,
    dwell_s: float,
    target_change_s: float,
) -> list[Move]:
    """Joint ``j``'s (0-based) planned sweep through ``stops`` ``(K, n)`` rad: the
    reflector moved to the TCP at Home (the plan's sweeps keep it in view there), to the
    first stop, down and back up at ``slow_speed``, back to Home with the reflector still
    on the TCP (the next joint's target change moves it)."""
    moves = [Move(tuple(home), 0.3, target_change_s, f"joint{j + 1} target tcp", "tcp")]
    moves.append(Move(tuple(stops[0]), 0.3, 0.0, f"joint{j + 1} to sweep", "tcp"))
    return moves + _sweep(home, j, stops, slow_speed, dwell_s, "tcp")


def _sweep(
    home: FloatArray, j: int, stops: FloatArray, slow_speed: float, dwell_s: float, target: str
) -> list[Move]:
    """Joint ``j``'s (0-based) sweep: ``stops`` ``(K, n)`` rad down and back up at
    ``slow_speed``, ``dwell_s`` at each, then back to Home."""
    moves: list[Move] = []
    for direction, seq in (("down", stops), ("up", stops[::-1])):
        for k, q in enumerate(seq):
            label = f"joint{j + 1} sweep {direction} {k}"
            moves.append(Move(tuple(q), slow_speed, dwell_s, label, target))
    moves.append(Move(tuple(home), 0.3, 0.5, f"joint{j + 1} done", target))
    return moves


def build_program(
    name: str,
    desc: RobotDescription,
    rng: np.random.Generator,
    planned: tuple[FloatArray, FloatArray] | None = None,
    *,
    start_hold_s: float = 0.0,
    cell: CellSection | None = None,
    sweeps: Mapping[int, FloatArray] | None = None,
) -> Trajectory:
    """A built-in program by name (``campaign``, ``production``, ``random``, ``hold``);
    ``planned``: the campaign's identify and validate poses (rad), a plan's
    (:func:`campaign_moves`); ``sweeps``: a plan's sweeps of the joints it sweeps whole in
    view (:func:`campaign_moves`); ``start_hold_s``: the campaign first holds at Home this
    long (robot seconds); ``production`` takes its check poses, period and dwell from
    ``cell``."""
    vmax = np.radians(DEFAULT_VMAX_DEG_S[: desc.n_joints])
    amax = np.radians(DEFAULT_AMAX_DEG_S2[: desc.n_joints])
    home = np.radians(desc.home)
    if name == "campaign":
        moves = campaign_moves(desc, rng, poses=planned, sweeps=sweeps)
        if start_hold_s > 0.0 and moves:  # the first target mounted already
            moves.insert(0, Move(tuple(home), 0.3, start_hold_s, "start hold", moves[0].target))
        return Trajectory.build(home, moves, vmax, amax)
    if name == "production":
        return production_program(desc, rng, cell or CellSection(), vmax, amax)
    if name == "random":
        poses = _random_poses(desc, 50, rng)
        moves = [Move(tuple(q), 0.5, 0.2, f"free {k}") for k, q in enumerate(poses)]
        moves.append(Move(tuple(home), 0.5, 0.2, "home"))
        return Trajectory.build(home, moves, vmax, amax, repeat=True)
    if name == "hold":
        return Trajectory.build(home, [Move(tuple(home), 1.0, 1.0, "hold")], vmax, amax)
    raise ValueError(f"unknown program {name!r}")


def production_program(
    desc: RobotDescription,
    rng: np.random.Generator,
    cell: CellSection,
    vmax: FloatArray,
    amax: FloatArray,
) -> Trajectory:
    """Production with periodic checks, looping: ``cell.check_poses`` random reachable
    check poses in turn (the campaign's pose sampler), one every ``cell.check_every_s`` of
    simulated time. A cycle: to the check pose, then ``cell.check_dwell_s`` there with the
    reflector in view (the TCP target: the check), then to a random work pose, working
    there until the next cycle (the last cycle works at Home, where the loop starts). The
    reflector is out of view (:data:`HIDDEN`) whenever the robot moves or works: every
    valid point is one of a check's dwell (the tracker locks on once the robot stands),
    however the streams' clocks are aligned. A cycle is never shorter than its two moves
    and the check's dwell (~10-20 s on the KR500); the truth's schedule has every time."""
    home = np.radians(desc.home)
    checks = _random_poses(desc, cell.check_poses, rng)
    work = np.vstack([_random_poses(desc, cell.check_poses - 1, rng), home[None, :]])

    def moves(fill_s: FloatArray) -> list[Move]:
        out: list[Move] = []
        for k, (q_check, q_work) in enumerate(zip(checks, work, strict=True)):
            out.append(Move(tuple(q_check), 0.5, 0.0, f"to check {k}", HIDDEN))
            out.append(Move(tuple(q_check), 0.5, cell.check_dwell_s, f"check {k}", "tcp"))
            out.append(Move(tuple(q_work), 0.5, float(fill_s[k]), f"work {k}", HIDDEN))
        return out

    # the moves' durations do not depend on the dwells: build once to time them
    timed = Trajectory.build(home, moves(np.zeros(len(checks))), vmax, amax)
    busy = timed.move_s[0::3] + cell.check_dwell_s + timed.move_s[2::3]
    fill = np.maximum(cell.check_every_s - busy, 0.0)
    return Trajectory.build(home, moves(fill), vmax, amax, repeat=True)


def production_start_s(cell: CellSection, trajectory: Trajectory, start_s: float) -> float:
    """When production (the truth's drift) starts, simulated s: ``start_s`` when given
    (>= 0), else the end of the campaign program (the campaign calibrates the undrifted
    cell) or 0 for the other programs."""
    if start_s >= 0.0:
        return start_s
    return float(trajectory.end_s) if cell.program == "campaign" else 0.0


def _target_index(target: str) -> int:
    """-1 for the TCP target, -2 for none in view, else the 0-based joint of ``link:J``."""
    if target == HIDDEN:
        return -2
    j = parse_target(target)
    return -1 if j is None else j
