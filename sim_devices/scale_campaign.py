"""Emulated grating-scale calibration campaign (method §2): home returns and 2° sweeps.

For each joint, the others commanded to Home:

1. ``home_returns`` returns to Home, alternately from above and from below, each read by
   the grating (read noise, optional settling error of the true angle);
2. a sweep from the positive limit to the negative one (``forward``) in ``step_deg``
   stops, then back over the same commanded angles (``backward``); at every stop the
   grating is read and the tracker measures the target(s) on the moving link.

The wrist joints' full ±350° travel is swept (two turns of the target; nothing in the
fit minds). Commanded stops carry a small positioning error (``stop_jitter_deg``) that
the grating and the tracker both see, so it costs nothing but realism.

**The chain's motion** (opt-in, :class:`CampaignOptions`): with ``torsion`` and/or
``backlash`` every joint's output ring stands where the live plant's gears put it
(:class:`sim_devices.gears.GearTrain` under the arm's static load,
:class:`sim_devices.physical_arm.PhysicalArm`), at every Home return and stop: the joints
"held at Home" turn as the swept link's load changes, and their gratings see it (they read
the rings). ``effects`` adds undeclared effects (:mod:`sim_devices.effects`; e.g.
``gravity_deflection``: links 1..J turn after their rings, moving the target on link J,
invisible to every grating). Time-dependent effects follow a campaign clock of
``stop_time_s`` per Home return and per stop.

**Sweep geometry** (opt-in): ``targets`` reflectors on the swept link
(:func:`sim_devices.sweep_plan.target_set_mm`), every one measured at every stop;
``arc_deg`` / ``stops_per_arc`` sweep a shorter arc centred on Home
(:func:`sim_devices.sweep_plan.sweep_stops_deg`).

Off-by-default effects of this generator only (not in :mod:`sim_devices.truth`):

* ``hysteresis_counts``: the head reads ``+h/2`` counts when the joint moves towards the
  positive limit and ``-h/2`` when it moves towards the negative one (so ``h`` is
  backward-minus-forward at the same true angle); a joint at rest keeps the offset of its
  last move;
* ``wild_points``: that many tracker points per joint displaced by ``wild_point_mm`` in a
  random direction.

Files (``write``): ``home.csv`` (``joint,trial,counts``), ``sweep.csv``
(``joint,pass,step,counts,x_mm,y_mm,z_mm``; with more than one reflector a ``target``
column after ``step``, one row per stop and reflector; with the chain's motion or
``all_counts`` every joint's reading ``g1_counts..gN_counts`` at the end) and
``truth.toml`` (the cell's truth plus the campaign options; the twin never reads it).
With all of this off the files are exactly those of the plain campaign.

``python -m sim_devices.scale_campaign --robot kr500 --seed 1 --out DIR``
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import tomli_w
from numpy.typing import ArrayLike, NDArray

from calibration.errors import CalibrationError
from edges.command import run_command, take_debug_flag
from edges.options import OptionParser
from edges.outputs import OutputSet
from sim_devices.config import (
    MAX_COUNT,
    SEED_OPTION,
    EffectsSection,
    check_joints,
    integer_option,
    joint_list,
    number_option,
    robot_option,
)
from sim_devices.effects import (
    EFFECT_NAMES,
    UndeclaredEffects,
    effects_document,
    grating_reading_rad,
    tracker_reading_mm,
    true_point_mm,
    with_derived_stiffness,
)
from sim_devices.errors import SimError
from sim_devices.gears import GearTrain
from sim_devices.sweep_plan import (
    commanded_stops_deg,
    motion_direction,
    sweep_stops_deg,
    target_set_mm,
)
from sim_devices.truth import COUNTER_MODULUS, GratingStrip, TrueCell

if TYPE_CHECKING:  # the twin's fit module (scipy.stats: half a second) only when used
    from calibration.scales.sweep_inputs import JointSweep

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

PASSES: tuple[str, str] = ("forward", "backward")  # positive → negative limit, then back
__all__ = [
    "PASSES",
    "CampaignOptions",
    "JointTruth",
    "ScaleCampaign",
    "commanded_stops_deg",
    "run_campaign",
]


@dataclass(frozen=True)
class CampaignOptions:
    """How the campaign is run; defaults follow the method (2° steps, 10 Home returns)."""

    step_deg: float = 2.0
    home_returns: int = 10
    settling_deg: float = 0.0  # 1σ of the true angle at each Home return
    stop_jitter_deg: float = 0.005  # 1σ of the true angle around each commanded stop
    hysteresis_counts: float = 0.0  # backward-minus-forward reading offset
    wild_points: int = 0  # tracker wild points per joint
    wild_point_mm: float = 1.0
    joints: tuple[int, ...] | None = None  # 1-based joints to calibrate (default: all)
    joints_without_home: tuple[int, ...] = ()  # 1-based joints that get no Home returns
    # the chain's motion: gear torsion and backlash flank of every joint (the live
    # plant's physics; empty tuples: sim_devices.config.EffectsSection's values)
    torsion: bool = False
    backlash: bool = False
    stiffness_nmm_per_rad: tuple[float, ...] = ()
    backlash_deg: tuple[float, ...] = ()
    effects: UndeclaredEffects = field(default_factory=UndeclaredEffects)
    all_counts: bool = False  # write g1_counts..gN_counts even without the chain's motion
    stop_time_s: float = 2.0  # campaign clock per Home return and per stop (drift, lag)
    # sweep geometry
    targets: int = 1  # reflectors on the swept link
    target_spacing_mm: float = 360.0  # side of the reflectors' regular polygon
    arc_deg: float | None = None  # None: limit to limit; else centred on Home
    stops_per_arc: int | None = None  # None: one stop every step_deg

    @property
    def chain_motion(self) -> bool:
        """Whether the joints held at Home move (torsion, backlash or undeclared effects)."""
        return self.torsion or self.backlash or self.effects.any_active

    @property
    def writes_all_counts(self) -> bool:
        return self.all_counts or self.chain_motion

    def gear_train(self, n_joints: int) -> GearTrain:
        """The gears of this campaign (defaults: the live plant's)."""
        default = EffectsSection()
        return GearTrain.of(
            EffectsSection(
                torsion=self.torsion,
                backlash=self.backlash,
                stiffness_nmm_per_rad=self.stiffness_nmm_per_rad or default.stiffness_nmm_per_rad,
                backlash_deg=self.backlash_deg or default.backlash_deg,
            ),
            n_joints,
        )


@dataclass(frozen=True)
class JointTruth:
    """The true counts → angle relation of one joint (what the twin should recover).

    ``angle_deg(counts)`` is the true ring angle relative to the commanded Home posture
    (the nominal Home, ``home_rad``) for a raw, wrapped counter value, inverting
    :meth:`GratingStrip.ideal_counts` (no read noise).

    ``home_ring_rad`` is where the ring really stood at this joint's Home returns (their
    mean true ring angle; None without Home returns). The twin's zero is the mean reading
    there, so its "angle relative to Home" is :meth:`angle_from_home_ring_deg`. The two
    differ by the mean settling error, and with torsion or backlash by the gear's offset
    at Home (``τ(Home)/K`` plus the flank), which no scale calibration can see.
    """

    joint: int  # 1-based
    strip: GratingStrip
    home_rad: float
    hysteresis_counts: float = 0.0
    home_ring_rad: float | None = None

    @property
    def counts_per_rad(self) -> float:
        s = self.strip
        return s.direction * s.radius_mm * (1.0 + 1e-6 * s.scale_error_ppm) * s.counts_per_mm

    @property
    def home_counts(self) -> float:
        """Unwrapped ideal counter value at Home (no hysteresis)."""
        return float(self.strip.ideal_counts(self.home_rad))

    def counts_at(self, angle_deg: ArrayLike, direction: ArrayLike = 0.0) -> FloatArray:
        """Ideal (unwrapped, unquantized) counts at a true angle relative to Home.

        ``direction``: +1 moving towards the positive limit, -1 towards the negative one,
        0 for the direction average.
        """
        q = self.home_rad + np.radians(np.asarray(angle_deg, dtype=float))
        return self.strip.ideal_counts(q) + 0.5 * np.asarray(direction) * self.hysteresis_counts

    def angle_deg(self, counts: ArrayLike, direction: ArrayLike = 0.0) -> FloatArray:
        """True angle relative to Home (deg) of raw counter values (wrapped, 32-bit)."""
        c = np.asarray(counts, dtype=float)
        offset = np.mod(c - self.home_counts + COUNTER_MODULUS / 2, COUNTER_MODULUS)
        target = self.home_counts + offset - COUNTER_MODULUS / 2
        target = target - 0.5 * np.asarray(direction) * self.hysteresis_counts
        k = self.counts_per_rad
        q = self.home_rad + (target - self.home_counts) / k
        for _ in range(6):  # Newton; the cyclic term is a tiny fraction of the slope
            s = self.strip
            slope = k + s.direction * s.eccentricity_mm * s.counts_per_mm * np.cos(
                q + s.eccentricity_phase_rad
            )
            q = q - (self.strip.ideal_counts(q) - target) / slope
        return np.degrees(q - self.home_rad)

    def angle_from_home_ring_deg(self, counts: ArrayLike, direction: ArrayLike = 0.0) -> FloatArray:
        """True angle (deg) from where the ring stood at the Home returns: what the twin's
        "angle relative to Home" estimates. Without Home returns: :meth:`angle_deg`."""
        ref = self.home_rad if self.home_ring_rad is None else self.home_ring_rad
        return self.angle_deg(counts, direction) - math.degrees(ref - self.home_rad)


@dataclass(frozen=True, eq=False)
class ScaleCampaign:
    """The emulated measurements of one campaign, with the truth behind every row.

    Sweep arrays have one row per stop and reflector (stop-major: a stop's T reflectors
    are consecutive rows); a stop's counts and true angles repeat over its rows.
    """

    cell: TrueCell
    options: CampaignOptions
    home_joint: IntArray  # (H,) 1-based
    home_trial: IntArray  # (H,) 1-based
    home_counts: IntArray  # (H,) raw, wrapped
    sweep_joint: IntArray  # (S,) 1-based
    sweep_pass: NDArray[np.str_]  # (S,) "forward" / "backward"
    sweep_step: IntArray  # (S,) stop index from the start of the pass
    sweep_counts: IntArray  # (S,) raw, wrapped
    sweep_points_mm: FloatArray  # (S, 3) tracker measurements
    sweep_true_rad: FloatArray  # (S,) true ring angle of the swept joint at each stop
    sweep_true_points_mm: FloatArray  # (S, 3) true reflector positions (per target)
    wild_rows: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    sweep_target: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    # (S,) 1-based reflector index; below: (S, n) every joint's raw reading, (S, n) every
    # joint's true ring angle, (S,) campaign clock, (H, n) every joint's true ring angle at
    # the Home returns, (H,) their clock
    sweep_all_counts: IntArray = field(default_factory=lambda: np.zeros((0, 0), np.int64))
    sweep_ring_rad: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    sweep_t_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    home_ring_rad: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    home_t_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    targets_mm: tuple[FloatArray, ...] = ()  # per swept joint in order: (T, 3) link frame

    def joint_sweeps(self) -> dict[int, JointSweep]:
        """The sweeps as the twin reads them from sweep.csv, in memory (per joint)."""
        from calibration.scales.sweep_inputs import JointSweep

        out = {}
        for j in sorted(set(self.sweep_joint.tolist())):
            m = self.sweep_joint == j
            out[j] = JointSweep(
                joint=j,
                pass_name=self.sweep_pass[m],
                step=self.sweep_step[m],
                counts=self.sweep_counts[m],
                points_mm=self.sweep_points_mm[m],
                chain_counts=None
                if not self.options.writes_all_counts
                else self.sweep_all_counts[m],
                target=self.sweep_target[m] if self.options.targets > 1 else None,
            )
        return out

    def home_readings(self) -> dict[int, IntArray]:
        """The Home returns' readings per joint, as home.csv gives them."""
        return {int(j): self.home_counts[self.home_joint == j] for j in np.unique(self.home_joint)}

    def truth(self, joint: int) -> JointTruth:
        """The true relation of ``joint`` (1-based), with where its ring stood at Home."""
        home = math.radians(self.cell.nominal.home[joint - 1])
        ring = None
        if np.any(self.home_joint == joint):
            ring = float(np.mean(self.home_ring_rad[self.home_joint == joint, joint - 1]))
        return JointTruth(
            joint, self.cell.strips[joint - 1], home, self.options.hysteresis_counts, ring
        )

    def upstream_motion_rad(self, joint: int) -> FloatArray:
        """Peak-to-peak ``(n,)`` rad of every joint's true ring angle over ``joint``'s
        sweep (1-based): how far the joints held at Home turned (the swept one: its arc)."""
        m = self.sweep_joint == joint
        motion: FloatArray = np.ptp(self.sweep_ring_rad[m], axis=0)
        return motion

    def home_csv(self) -> str:
        lines = ["joint,trial,counts"]
        lines += [
            f"{j},{t},{c}"
            for j, t, c in zip(self.home_joint, self.home_trial, self.home_counts, strict=True)
        ]
        return "\n".join(lines) + "\n"

    def sweep_csv(self) -> str:
        """``joint,pass,step[,target],counts,x_mm,y_mm,z_mm[,g1_counts..gN_counts]``."""
        with_target = self.options.targets > 1
        with_all = self.options.writes_all_counts
        n = self.cell.nominal.n_joints
        header = ["joint", "pass", "step", *(["target"] if with_target else []), "counts"]
        header += ["x_mm", "y_mm", "z_mm"]
        header += [f"g{i}_counts" for i in range(1, n + 1)] if with_all else []
        lines = [",".join(header)]
        target = self.sweep_target if with_target else None
        for r, (j, p, s, c, xyz) in enumerate(
            zip(
                self.sweep_joint,
                self.sweep_pass,
                self.sweep_step,
                self.sweep_counts,
                self.sweep_points_mm,
                strict=True,
            )
        ):
            head = f"{j},{p},{s}," + (f"{target[r]}," if target is not None else "")
            line = head + f"{c},{xyz[0]:.5f},{xyz[1]:.5f},{xyz[2]:.5f}"
            if with_all:
                line += "," + ",".join(str(v) for v in self.sweep_all_counts[r])
            lines.append(line)
        return "\n".join(lines) + "\n"

    def truth_document(self) -> dict[str, Any]:
        """The cell's truth, the campaign options and what the chain's motion did."""
        doc = self.cell.truth_document()
        opts = asdict(self.options)
        opts["effects"] = effects_document(self.options.effects, self.cell.arm)
        doc["campaign"] = _toml_ready(opts)
        gears = self.options.gear_train(self.cell.nominal.n_joints)
        doc["gears"] = {
            "torsion": gears.torsion,
            "backlash": gears.backlash,
            "stiffness_nmm_per_rad": gears.stiffness_nmm_per_rad.tolist(),
            "backlash_deg": np.degrees(gears.backlash_rad).tolist(),
            "backlash_torque_nmm": gears.backlash_torque_nmm,
        }
        joints = sorted(set(self.sweep_joint.tolist()))
        doc["joint_truth"] = [
            {
                "joint": j,
                "home_deg": math.degrees(t.home_rad),
                **(
                    {"home_ring_deg": math.degrees(t.home_ring_rad)}
                    if t.home_ring_rad is not None
                    else {}
                ),
                "targets_mm": self.targets_mm[k].tolist(),
                "upstream_motion_arcsec": (
                    np.degrees(self.upstream_motion_rad(j)[: j - 1]) * 3600.0
                ).tolist(),
            }
            for k, j in enumerate(joints)
            for t in [self.truth(j)]
        ]
        return doc

    def write(self, out_dir: str | Path) -> dict[str, Path]:
        """Write ``home.csv``, ``sweep.csv`` and ``truth.toml`` into ``out_dir`` (created):
        the three appear together or, on any error, none of them
        (:class:`edges.outputs.OutputSet`); files of the same names are replaced."""
        texts = {
            "home": ("home.csv", self.home_csv()),
            "sweep": ("sweep.csv", self.sweep_csv()),
            "truth": ("truth.toml", tomli_w.dumps(self.truth_document())),
        }
        with OutputSet(error=SimError) as outputs:
            staged = outputs.directory(out_dir, "--out")
            for name, text in texts.values():
                (staged / name).write_text(text, encoding="utf-8")
        return {key: Path(out_dir) / name for key, (name, _text) in texts.items()}


def _toml_ready(value: Any) -> Any:
    """Tuples as lists, None entries dropped (TOML has no null)."""
    if isinstance(value, dict):
        return {k: _toml_ready(v) for k, v in value.items() if v is not None}
    if isinstance(value, tuple | list):
        return [_toml_ready(v) for v in value]
    return value


def _read(
    strip: GratingStrip, q: FloatArray, offset: FloatArray, rng: np.random.Generator
) -> IntArray:
    """Grating readings with a direction offset (counts) added before rounding and wrap."""
    noisy = strip.ideal_counts(q) + offset + rng.normal(0.0, strip.noise_counts, q.shape)
    return np.mod(np.rint(noisy).astype(np.int64), COUNTER_MODULUS)


@dataclass
class _ArmState:
    """What the campaign carries from one phase to the next: each joint's last motion
    direction ``(n,)`` (+1 before any move, as the live plant's trajectories) and the
    campaign clock (s)."""

    last_direction: FloatArray
    t_s: float = 0.0


class _Physics:
    """Ring angles, readings and reflector positions of the chain for one campaign."""

    def __init__(self, cell: TrueCell, opt: CampaignOptions) -> None:
        self.cell = cell
        self.opt = opt
        self.gears = opt.gear_train(cell.nominal.n_joints)
        self.effects = with_derived_stiffness(opt.effects, cell.arm)

    def ring_rad(self, q_motor: FloatArray, direction: FloatArray) -> FloatArray:
        """Ring angles ``(K, n)`` for servoed motor positions ``(K, n)`` (joint units)."""
        if not self.gears.active:
            return q_motor
        tau = self.cell.arm.joint_torques_nmm(q_motor)
        return q_motor + self.gears.ring_offset_rad(tau, direction)

    def readings_rad(self, q_ring: FloatArray) -> FloatArray:
        """What the strips see ``(K, n)``: ring angles with any undeclared reading error."""
        return grating_reading_rad(self.effects, q_ring) if self.effects.any_active else q_ring

    def points_mm(
        self,
        link: int,
        targets_mm: FloatArray,
        q_ring: FloatArray,
        t_s: FloatArray,
        direction: FloatArray,
    ) -> FloatArray:
        """Noise-free tracker readings ``(K·T, 3)`` of ``targets_mm`` ``(T, 3)`` on link
        ``link`` (0-based), stop-major."""
        eff = self.effects
        pts = [
            true_point_mm(eff, self.cell.arm, link, t, q_ring, t_s, direction) for t in targets_mm
        ]
        out = np.stack(pts, axis=1).reshape(-1, 3)
        return tracker_reading_mm(eff, out, np.repeat(t_s, len(targets_mm)))


def _home_returns(
    cell: TrueCell,
    opt: CampaignOptions,
    physics: _Physics,
    state: _ArmState,
    joint: int,
    rng: np.random.Generator,
) -> dict[str, NDArray[Any]]:
    """Joint ``joint``'s (1-based) Home returns, alternately from below and from above."""
    i = joint - 1
    home_rad = np.radians(cell.nominal.home)
    trials = np.arange(1, opt.home_returns + 1)
    moving = np.where(trials % 2 == 1, 1.0, -1.0)  # from below, from above, ...
    q_motor = np.tile(home_rad, (trials.size, 1))
    q_motor[:, i] += np.radians(opt.settling_deg) * rng.normal(size=trials.size)
    direction = np.tile(state.last_direction, (trials.size, 1))
    direction[:, i] = moving
    ring = physics.ring_rad(q_motor, direction)
    read = physics.readings_rad(ring)
    h = opt.hysteresis_counts
    out = {
        "joint": np.full(trials.size, joint),
        "trial": trials,
        "counts": _read(cell.strips[i], read[:, i], 0.5 * h * moving, rng),
        "ring": ring,
        "t": state.t_s + opt.stop_time_s * trials,
    }
    state.t_s += opt.stop_time_s * trials.size
    state.last_direction[i] = moving[-1]
    return out


def _sweep(
    cell: TrueCell,
    opt: CampaignOptions,
    physics: _Physics,
    state: _ArmState,
    joint: int,
    rng: np.random.Generator,
    chain_rng: np.random.Generator,
) -> dict[str, NDArray[Any]]:
    """Joint ``joint``'s (1-based) forward and backward passes; arrays per row (stop-major,
    a stop's reflectors consecutive), ``"wild"`` the displaced rows, ``"targets"`` the
    reflectors ``(T, 3)`` in the link's frame."""
    i = joint - 1
    nominal = cell.nominal
    fwd = _forward_stops_deg(cell, opt, i)
    cmd = np.concatenate([fwd, fwd[::-1]])
    k = cmd.size
    h = opt.hysteresis_counts
    moving = np.concatenate([-np.ones(fwd.size), np.ones(fwd.size)])  # hysteresis sign
    q_motor = np.tile(np.radians(nominal.home), (k, 1))
    q_motor[:, i] = np.radians(cmd + opt.stop_jitter_deg * rng.normal(size=k))
    direction = np.tile(state.last_direction, (k, 1))
    direction[:, i] = motion_direction(cmd, nominal.home[i], state.last_direction[i])
    ring = physics.ring_rad(q_motor, direction)
    read = physics.readings_rad(ring)
    counts = _read(cell.strips[i], read[:, i], 0.5 * h * moving, rng)
    t_stop = state.t_s + opt.stop_time_s * np.arange(1, k + 1, dtype=float)
    targets = target_set_mm(cell.link_targets_mm[i], opt.targets, opt.target_spacing_mm)
    n_t = len(targets)
    true_pts = physics.points_mm(i, targets, ring, t_stop, direction)
    measured = _measure(cell, true_pts, rng)
    wild = _displace_wild(measured, opt, rng)
    all_counts = _all_counts(cell, state, i, counts, read, h, chain_rng)
    state.t_s = float(t_stop[-1])
    back = np.sign(nominal.home[i] - cmd[-1])  # the return to Home after the sweep
    state.last_direction[i] = back if back != 0 else direction[-1, i]
    per_stop = {
        "pass": np.repeat(np.array(PASSES), fwd.size),
        "step": np.concatenate([np.arange(fwd.size)] * 2),
        "counts": counts,
        "all": all_counts,
        "q": ring[:, i],
        "ring": ring,
        "t": t_stop,
    }
    return {
        **{key: np.repeat(v, n_t, axis=0) for key, v in per_stop.items()},
        "joint": np.full(k * n_t, joint),
        "target": np.tile(np.arange(1, n_t + 1), k),
        "pts": measured,
        "true": true_pts,
        "wild": wild,
        "targets": targets,
    }


def _forward_stops_deg(cell: TrueCell, opt: CampaignOptions, i: int) -> FloatArray:
    """The commanded stops (deg) of joint ``i``'s (0-based) forward pass."""
    jnt = cell.nominal.joints[i]
    return sweep_stops_deg(
        jnt.lower_deg,
        jnt.upper_deg,
        cell.nominal.home[i],
        step_deg=opt.step_deg,
        arc_deg=opt.arc_deg,
        stops_per_arc=opt.stops_per_arc,
    )


def _measure(cell: TrueCell, true_pts: FloatArray, rng: np.random.Generator) -> FloatArray:
    """The tracker's points of ``true_pts`` ``(m, 3)`` mm; a broken beam is simply
    measured again (draws from ``rng`` until every point is measured)."""
    measured, ok = cell.tracker.measure(true_pts, rng)
    while not ok.all():
        again, ok_again = cell.tracker.measure(true_pts[~ok], rng)
        measured[~ok] = again
        ok[~ok] = ok_again
    return measured


def _displace_wild(
    measured: FloatArray, opt: CampaignOptions, rng: np.random.Generator
) -> IntArray:
    """Move ``opt.wild_points`` random rows of ``measured`` ``(m, 3)`` mm (in place) by
    ``opt.wild_point_mm`` in a random direction; the rows moved, sorted."""
    if not opt.wild_points:
        return np.zeros(0, dtype=np.int64)
    m = len(measured)
    rows = rng.choice(m, size=min(opt.wild_points, m), replace=False)
    offset = rng.normal(size=(rows.size, 3))
    offset /= np.linalg.norm(offset, axis=1, keepdims=True)
    measured[rows] += opt.wild_point_mm * offset
    return np.sort(rows)


def _all_counts(
    cell: TrueCell,
    state: _ArmState,
    i: int,
    counts: IntArray,
    read: FloatArray,
    h: float,
    chain_rng: np.random.Generator,
) -> IntArray:
    """Every joint's reading ``(k, n)`` at the ``k`` stops of joint ``i``'s (0-based) sweep:
    its own ``counts``; the others' read noise from their own stream (``chain_rng``),
    their hysteresis offset (``h`` counts) that of their last move."""
    k, n = len(counts), cell.nominal.n_joints
    all_counts = np.empty((k, n), dtype=np.int64)
    for j in range(n):
        rest = np.full(k, 0.5 * h * state.last_direction[j])
        all_counts[:, j] = counts if j == i else _read(cell.strips[j], read[:, j], rest, chain_rng)
    return all_counts


def run_campaign(
    cell: TrueCell, options: CampaignOptions | None = None, *, seed: int | None = None
) -> ScaleCampaign:
    """Emulate the whole campaign for ``cell``; ``seed`` defaults to the cell's seed.

    The random draws of the plain campaign come first and in the same order whatever the
    options, so switching the chain's motion on changes the rows by the motion alone; the
    other joints' read noise comes from a stream of its own.
    """
    opt = options or CampaignOptions()
    run_seed = cell.seed if seed is None else seed
    rng = np.random.default_rng([run_seed, 20250502])
    chain_rng = np.random.default_rng([run_seed, 20250502, 2])
    n = cell.nominal.n_joints
    physics = _Physics(cell, opt)
    state = _ArmState(np.ones(n))
    homes, sweeps = [], []
    row0 = 0
    for joint in opt.joints or tuple(range(1, n + 1)):
        if joint not in opt.joints_without_home and opt.home_returns > 0:
            homes.append(_home_returns(cell, opt, physics, state, joint, rng))
        sweep = _sweep(cell, opt, physics, state, joint, rng, chain_rng)
        sweep["wild"] = sweep["wild"] + row0
        row0 += len(sweep["joint"])
        sweeps.append(sweep)

    def cat(
        parts: list[dict[str, NDArray[Any]]], key: str, dtype: type, shape: tuple[int, ...] = (0,)
    ) -> NDArray[Any]:
        if not parts:
            return np.zeros(shape, dtype=dtype)
        return np.concatenate([p[key] for p in parts]).astype(dtype)

    return ScaleCampaign(
        cell=cell,
        options=opt,
        home_joint=cat(homes, "joint", np.int64),
        home_trial=cat(homes, "trial", np.int64),
        home_counts=cat(homes, "counts", np.int64),
        sweep_joint=cat(sweeps, "joint", np.int64),
        sweep_pass=cat(sweeps, "pass", str),
        sweep_step=cat(sweeps, "step", np.int64),
        sweep_counts=cat(sweeps, "counts", np.int64),
        sweep_points_mm=cat(sweeps, "pts", float, (0, 3)),
        sweep_true_rad=cat(sweeps, "q", float),
        sweep_true_points_mm=cat(sweeps, "true", float, (0, 3)),
        wild_rows=cat(sweeps, "wild", np.int64),
        sweep_target=cat(sweeps, "target", np.int64),
        sweep_all_counts=cat(sweeps, "all", np.int64, (0, n)),
        sweep_ring_rad=cat(sweeps, "ring", float, (0, n)),
        sweep_t_s=cat(sweeps, "t", float),
        home_ring_rad=cat(homes, "ring", float, (0, n)),
        home_t_s=cat(homes, "t", float),
        targets_mm=tuple(s["targets"] for s in sweeps),
    )


#: The most reflectors on one link (a polygon of side ``target_spacing_mm``).
MAX_TARGETS = 12
#: The most stops of one pass (10 000 stops × 12 reflectors × 2 passes × 6 joints is
#: 1.4 million sweep rows already).
MAX_STOPS = 10_000


def build_parser() -> argparse.ArgumentParser:
    """The generator's options; every value is checked as it is parsed (finite, in range,
    joint lists well formed) and against the robot in :func:`main`. Long as a flat list
    of ``add_argument`` calls, one per option, in the order ``--help`` shows them."""
    parser = OptionParser(
        prog="python -m sim_devices.scale_campaign",
        description="Write home.csv, sweep.csv and truth.toml of an emulated scale campaign.",
    )
    parser.add_argument("--robot", default="kr500", help="preset name or description file")
    parser.add_argument("--seed", type=SEED_OPTION, default=1, help="seed of the true cell")
    parser.add_argument("--out", required=True, help="output directory (created)")
    parser.add_argument(
        "--eccentricity-mm",
        type=number_option(0.0, 1.0, what="mm"),
        default=0.0,
        help="strip cyclic error amplitude, 0..1 mm",
    )
    parser.add_argument(
        "--hysteresis-counts",
        type=number_option(-1e4, 1e4, what="counts"),
        default=0.0,
        help="backward-minus-forward reading offset, counts",
    )
    parser.add_argument(
        "--settling-deg",
        type=number_option(0.0, 10.0, what="deg, 1 sigma"),
        default=0.0,
        help="1 sigma of the true angle at each Home return, deg",
    )
    parser.add_argument(
        "--wild-points",
        type=integer_option(0, MAX_COUNT),
        default=0,
        help="wild tracker points per joint",
    )
    parser.add_argument("--joints", type=joint_list, default=None, help="e.g. 1,2,3")
    parser.add_argument("--no-home", type=joint_list, default=(), help="joints without home")
    parser.add_argument(
        "--torsion", action="store_true", help="gear torsion of every joint (live plant's)"
    )
    parser.add_argument(
        "--backlash", action="store_true", help="backlash flank of every joint (live plant's)"
    )
    parser.add_argument(
        "--effect",
        action="append",
        default=[],
        choices=list(EFFECT_NAMES),
        help="an undeclared effect at its default strength (repeatable)",
    )
    parser.add_argument(
        "--all-counts", action="store_true", help="write g1_counts..gN_counts in any case"
    )
    parser.add_argument(
        "--targets",
        type=integer_option(1, MAX_TARGETS),
        default=1,
        help=f"reflectors on the swept link, 1..{MAX_TARGETS}",
    )
    parser.add_argument(
        "--arc-deg",
        type=number_option(0.0, 720.0, lo_open=True, what="deg"),
        default=None,
        help="arc centred on Home, deg (clipped to the joint's range)",
    )
    parser.add_argument(
        "--stops-per-arc",
        type=integer_option(2, MAX_STOPS),
        default=None,
        help=f"stops along the arc, 2..{MAX_STOPS}",
    )
    return parser


def _run(args: argparse.Namespace) -> int:
    if not args.out.strip():
        raise SimError("--out: empty path; give the output directory")
    nominal = robot_option(args.robot)
    n = nominal.n_joints
    check_joints(args.joints, n, "--joints")
    check_joints(args.no_home, n, "--no-home")
    swept = args.joints or tuple(range(1, n + 1))
    for j in args.no_home:
        if j not in swept:
            raise SimError(
                f"--no-home: joint {j} is not swept (--joints {','.join(map(str, swept))})"
            )
    robot_file = args.robot if Path(args.robot).exists() else None
    with OutputSet(inputs=[robot_file], error=SimError) as outputs:
        staged = outputs.directory(args.out, "--out")
        cell = TrueCell.create(nominal, args.seed, eccentricity_mm=args.eccentricity_mm)
        options = CampaignOptions(
            settling_deg=args.settling_deg,
            hysteresis_counts=args.hysteresis_counts,
            wild_points=args.wild_points,
            joints=args.joints,
            joints_without_home=args.no_home,
            torsion=args.torsion,
            backlash=args.backlash,
            effects=UndeclaredEffects.named(*args.effect),
            all_counts=args.all_counts,
            targets=args.targets,
            arc_deg=args.arc_deg,
            stops_per_arc=args.stops_per_arc,
        )
        paths = run_campaign(cell, options).write(staged)
    for p in paths.values():
        print(outputs.final(p))
    return 0


def main(argv: list[str] | None = None) -> int:
    """The command line: a user's mistake is one line on stderr and exit 2
    (:func:`edges.command.run_command`); ``--debug`` shows tracebacks."""
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return run_command(
        "python -m sim_devices.scale_campaign",
        lambda: _run(args),
        user_errors=(SimError, CalibrationError),
        debug=debug,
    )


if __name__ == "__main__":
    sys.exit(main())
