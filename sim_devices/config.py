"""The emulated cell's configuration (``cell.toml``): devices, effects and injected faults;
and the checked option values of the sim commands (``sim-cell``, the generators).

Every table is a dataclass below; keys are checked against its fields (unknown keys are
errors that list the allowed ones). All keys are optional: an empty file is the default
cell. Units are in the key names. See docs/protocols.md for an annotated example.

Every value is checked when the file is read: its type, that a number is finite (TOML
allows ``nan`` and ``inf``), and its range (:data:`RANGES`). A mistake is one line, a
:class:`~sim_devices.errors.SimConfigError` naming the file, the table and the key
(``cell.toml: [grating]: key 'rate_hz': must be in 1..20000, got 0.0``). The file is read
bounded (:data:`edges.inputs.MAX_TOML_BYTES`); UTF-8 with or without a byte-order mark,
LF or CRLF line ends. What needs the robot (joint numbers, per-joint lists) is checked by
:func:`check_for_robot` once the robot is loaded.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import tomli_w

from calibration.model.cell_geometry import (
    EMULATOR_TABLES,
    CellGeometrySpec,
    geometry_document,
    read_cell_geometry,
)
from edges.command import one_line
from edges.toml_schema import (
    NON_NEGATIVE,
    POSITIVE,
    Range,
    build,
    parse_toml_file,
    parse_toml_text,
)
from sim_devices.drift import STEP_KINDS, CellDrift
from sim_devices.effects import EFFECT_NAMES, UndeclaredEffects
from sim_devices.errors import SimConfigError, SimError

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from calibration.model.description import RobotDescription

    FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CellSection:
    robot: str = "kr500"  # preset name or description file
    seed: int = 1
    speed: float = 1.0  # simulated clock speed (robot program time per wall second)
    program: str = "campaign"  # see PROGRAMS
    eccentricity_mm: float = 0.002
    truth_file: str = ""  # write the truth here at start ("" = don't)
    run_dir: str = ""  # where pty symlinks go ("" = a fresh temp dir)
    # a plan's campaign_joints.csv (twin plan): the campaign program's poses, identify
    # then validate, each in the file's order ("" = random poses); relative to the cell file
    plan: str = ""
    # run the plan's scale-calibration sweeps (sweeps.csv next to the plan) for the joints
    # it sweeps whole in view, the reflector the TCP's; off: every joint's sweep the
    # default (docs/planning.md: the TCP close to joint 4's and 6's axes spoils their maps)
    plan_sweeps: bool = False
    # robot seconds the campaign holds at Home before it starts (the operator starting the
    # program once every device is recorded: a daemon connecting late loses no sweep)
    start_hold_s: float = 0.0
    # program = "production": check poses visited in turn, one every check_every_s of
    # simulated time, each dwelt at for check_dwell_s with the reflector in view
    check_every_s: float = 120.0
    check_poses: int = 12
    check_dwell_s: float = 2.0


PROGRAMS = {
    "campaign": "grating calibration (home returns, 2° sweeps; tracker target on the swept "
    "link) + 100 id + 150 validation poses (TCP target; [cell] plan: a plan's poses)",
    "production": "looping production: a check pose (reflector in view) every "
    "check_every_s, dwelling check_dwell_s, working between them (reflector out of view)",
    "random": "free trajectory through random reachable poses, looping",
    "hold": "stand still at Home",
}


@dataclass(frozen=True)
class EffectsSection:
    torsion: bool = True  # joint torsion under gravity (gratings see it, encoders do not)
    backlash: bool = True
    stiffness_nmm_per_rad: tuple[float, ...] = (6e10, 4e10, 3e10, 8e9, 6e9, 3e9)
    backlash_deg: tuple[float, ...] = (0.008, 0.008, 0.008, 0.012, 0.012, 0.015)
    backlash_torque_nmm: float = 5e4  # below this load the motion direction decides the flank
    sag: bool = False  # link deflection under gravity: TCP droop (mm per m of reach)^2 model
    sag_mm_per_m2: float = 0.05
    tracker_temperature_drift_k_per_h: float = 0.0
    tracker_scale_ppm_per_k: float = 0.0  # instrument error: scale vs air temperature
    # effects the twin is not told about, shared with the campaign generator
    # ([effects.undeclared], sim_devices/effects.py; all off by default)
    undeclared: UndeclaredEffects = field(default_factory=UndeclaredEffects)
    # the truth moving during production ([effects.drift], sim_devices/drift.py; all off by
    # default): the live cell on its simulated clock from start_s, and the campaign
    # generator's --cell for its --checks file
    drift: CellDrift = field(default_factory=CellDrift)


@dataclass(frozen=True)
class ModbusFaults:
    crc_error_probability: float = 0.0
    garbage_probability: float = 0.0
    truncate_probability: float = 0.0
    exception_probability: float = 0.0
    silent_probability: float = 0.0
    silent_after_s: float = -1.0  # go silent at this wall time (s since start), < 0: never
    silent_for_s: float = 0.0
    restart_after_s: float = -1.0  # reboot (clock and sequence restart) at this time


@dataclass(frozen=True)
class GratingSection:
    enabled: bool = True
    unit_id: int = 1
    rate_hz: float = 1000.0
    buffer_samples: int = 8192
    clock_ppm: float = 0.0
    clock_start_us: int = 0
    counter_offset_counts: tuple[int, ...] = ()  # added to each channel (mod 2^32)
    noise_counts: float = 0.5
    faults: ModbusFaults = field(default_factory=ModbusFaults)


@dataclass(frozen=True)
class EncoderSection:
    enabled: bool = True
    node_ids: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
    counts_per_rev: int = 131072  # 17-bit single turn
    turns: int = 4096  # 12-bit multi-turn
    heartbeat_ms: int = 100
    channel: str = "can0"
    socketcand_port: int = 0  # 0: any free port on 127.0.0.1
    clock_ppm: float = 0.0
    stop_heartbeat_node: int = 0  # fault: this node stops (heartbeat and PDOs) ...
    stop_heartbeat_after_s: float = -1.0  # ... at this time
    stop_heartbeat_for_s: float = 0.0


@dataclass(frozen=True)
class TrackerSection:
    enabled: bool = True
    tcp_port: int = 0  # 0: any free port on 127.0.0.1
    serial: bool = True  # also serve the protocol on a pty
    # "program": the target the robot program names (campaign: link J for joint J's
    # scale calibration, TCP for the poses; free programs: TCP); "tcp" or "link1".."link6":
    # that target for the whole run
    target: str = "program"
    internal_rate_hz: float = 1000.0
    clock_ppm: float = 0.0
    beam_breaks_per_min: float = 0.0
    beam_break_duration_s: float = 0.5
    reset_after_s: float = -1.0  # fault: reset every connection (TCP RST) at this time
    temperature_c: float = 20.0
    pressure_hpa: float = 1013.25
    humidity_pct: float = 45.0
    # true: a TCP reflector out of the cell's acceptance cone or range, or behind an
    # obstacle ([station], [reflector], [[obstacle]]: calibration/model/cell_geometry.py) gives
    # a broken beam (BROKEN_OBSTRUCTED), as a real tracker does. Off by default while the
    # built-in programs drive random poses whose tool points anywhere.
    line_of_sight: bool = False


# -- value ranges -----------------------------------------------------------------------
PROBABILITY = Range(0.0, 1.0)
TIME_OR_NEVER = Range(what="s since start; < 0: never")
PPM = Range(-1000.0, 1000.0, what="ppm; a crystal drifts by tens")
PORT = Range(0, 65535, what="0: any free port")
MAX_SEED = 2**32 - 1
SEED = Range(0, MAX_SEED)

#: ``table.key`` (dotted as in the file) -> its allowed values; numbers without an entry
#: must be finite.
RANGES: dict[str, Range] = {
    "cell.seed": SEED,
    "cell.speed": Range(0.0, 1000.0, lo_open=True, what="program seconds per wall second"),
    "cell.start_hold_s": Range(0.0, 1e6, what="robot seconds"),
    "cell.check_every_s": Range(1.0, 1e6, what="simulated s between checks"),
    "cell.check_poses": Range(1, 1000, what="check poses"),
    "cell.check_dwell_s": Range(0.01, 3600.0, what="simulated s"),
    "cell.eccentricity_mm": Range(0.0, 1.0, what="mm; a strip's mounting eccentricity is µm"),
    "effects.stiffness_nmm_per_rad": Range(0.0, lo_open=True, empty=False, what="N·mm/rad"),
    "effects.backlash_deg": Range(0.0, 10.0, empty=False, what="deg, full gap"),
    "effects.backlash_torque_nmm": POSITIVE,
    "effects.sag_mm_per_m2": NON_NEGATIVE,
    "effects.undeclared.deflection_stiffness_nmm_per_rad": Range(
        0.0, lo_open=True, inf=True, what="N·mm/rad, inf: rigid"
    ),
    "effects.undeclared.deflection_rms_deg": POSITIVE,
    "effects.undeclared.coupling_joints": Range(1, 64, what="a joint number"),
    "effects.undeclared.coupling_coefficient": Range(
        -0.99, 0.99, what="ρ = c23/√(c22·c33); |ρ| < 1: a positive-definite compliance"
    ),
    "effects.undeclared.cyclic_joint": Range(1, 64, what="a joint number"),
    "effects.undeclared.cyclic_order": Range(1, 1000),
    "effects.undeclared.drift_joint": Range(1, 64, what="a joint number"),
    "effects.undeclared.drift_time_constant_s": Range(0.0, what="0: linear"),
    "effects.undeclared.lag_joint": Range(1, 64, what="a joint number"),
    "effects.undeclared.lag_time_constant_s": POSITIVE,
    "effects.undeclared.lost_motion_deg": Range(0.0, 10.0, what="deg, half width"),
    "effects.undeclared.bending_links": Range(1, 64, what="a joint number"),
    "effects.undeclared.bending_rms_deg": POSITIVE,
    "effects.undeclared.bending_stiffness_nmm_per_rad": Range(
        0.0, lo_open=True, inf=True, what="N·mm/rad, inf: rigid"
    ),
    "effects.undeclared.temp_time_constant_s": POSITIVE,
    "effects.undeclared.temp_cycle_period_s": POSITIVE,
    "effects.undeclared.temp_sensor_noise_k": NON_NEGATIVE,
    "effects.drift.thermal_ppm": Range(0.0, 1000.0, what="ppm of each link length"),
    "effects.drift.thermal_time_constant_s": POSITIVE,
    "effects.drift.creep_mm_per_h": Range(0.0, 10.0, what="mm/h"),
    "effects.drift.creep_mdeg_per_h": Range(0.0, 100.0, what="millidegrees/h"),
    "effects.drift.bump_mm": Range(0.0, 10.0, what="mm"),
    "effects.drift.bump_deg": Range(0.0, 5.0, what="deg"),
    "effects.drift.remount_mm": Range(0.0, 10.0, what="mm"),
    "effects.drift.start_s": Range(
        what="simulated s; < 0: the campaign program's end, 0 for the other programs"
    ),
    "effects.drift.span_s": Range(0.0, lo_open=True, what="simulated s of production"),
    "grating.unit_id": Range(1, 247, what="a Modbus unit id"),
    "grating.rate_hz": Range(1.0, 20000.0),
    "grating.buffer_samples": Range(1, 1_000_000),
    "grating.clock_ppm": PPM,
    "grating.clock_start_us": Range(0, 2**32 - 1, what="the 32-bit device clock"),
    "grating.counter_offset_counts": Range(
        -(2**32 - 1), 2**32 - 1, what="counts, added modulo 2^32"
    ),
    "grating.noise_counts": NON_NEGATIVE,
    "grating.faults.crc_error_probability": PROBABILITY,
    "grating.faults.garbage_probability": PROBABILITY,
    "grating.faults.truncate_probability": PROBABILITY,
    "grating.faults.exception_probability": PROBABILITY,
    "grating.faults.silent_probability": PROBABILITY,
    "grating.faults.silent_after_s": TIME_OR_NEVER,
    "grating.faults.silent_for_s": NON_NEGATIVE,
    "grating.faults.restart_after_s": TIME_OR_NEVER,
    "encoders.node_ids": Range(1, 127, empty=False, what="CANopen node ids"),
    "encoders.counts_per_rev": Range(1, 2**31, what="counts per revolution"),
    "encoders.turns": Range(1, 2**31),
    "encoders.heartbeat_ms": Range(0, 65535, what="CANopen 0x1017, 0: off"),
    "encoders.socketcand_port": PORT,
    "encoders.clock_ppm": PPM,
    "encoders.stop_heartbeat_node": Range(0, 127, what="0: none"),
    "encoders.stop_heartbeat_after_s": TIME_OR_NEVER,
    "encoders.stop_heartbeat_for_s": NON_NEGATIVE,
    "tracker.tcp_port": PORT,
    "tracker.internal_rate_hz": Range(1.0, 100000.0),
    "tracker.clock_ppm": PPM,
    "tracker.beam_breaks_per_min": Range(0.0, 600.0),
    "tracker.beam_break_duration_s": NON_NEGATIVE,
    "tracker.reset_after_s": TIME_OR_NEVER,
    "tracker.temperature_c": Range(-50.0, 80.0, what="°C, air"),
    "tracker.pressure_hpa": Range(300.0, 1200.0, what="hPa, air"),
    "tracker.humidity_pct": Range(0.0, 100.0),
}


@dataclass(frozen=True)
class CellConfig:
    cell: CellSection = field(default_factory=CellSection)
    effects: EffectsSection = field(default_factory=EffectsSection)
    grating: GratingSection = field(default_factory=GratingSection)
    encoders: EncoderSection = field(default_factory=EncoderSection)
    tracker: TrackerSection = field(default_factory=TrackerSection)
    #: the cell's geometry tables (top-level [station], [reflector], [floor], [arm],
    #: [region], [[obstacle]]), read by calibration.model.cell_geometry for both sides
    geometry: CellGeometrySpec = field(default_factory=CellGeometrySpec)

    @classmethod
    def load(cls, path: str | Path) -> CellConfig:
        """Read ``cell.toml`` (bounded); every error a :class:`SimConfigError` naming it."""
        doc = parse_toml_file(path, SimConfigError, "a cell config")
        cfg = cls.from_document(doc, str(path))
        plan = cfg.cell.plan
        if plan and not Path(plan).is_absolute():  # relative to the cell file
            cfg = replace(cfg, cell=replace(cfg.cell, plan=str(Path(path).parent / plan)))
        return cfg

    @classmethod
    def loads(cls, text: str, source: str = "<string>") -> CellConfig:
        """Parse and check the text of a ``cell.toml`` (``source`` names it in messages)."""
        return cls.from_document(parse_toml_text(text, source, SimConfigError), source)

    @classmethod
    def from_document(cls, doc: dict[str, Any], source: str) -> CellConfig:
        emulator = {k: v for k, v in doc.items() if k in EMULATOR_TABLES}
        geometry = read_cell_geometry(
            {k: v for k, v in doc.items() if k not in EMULATOR_TABLES},
            source,
            SimConfigError,
            others=EMULATOR_TABLES,
        )
        cfg = build(cls, emulator, source=source, error=SimConfigError, ranges=RANGES)
        cfg = replace(cfg, geometry=geometry)
        _check(cfg, source)
        return cfg

    def to_document(self) -> dict[str, Any]:
        doc = asdict(self)
        del doc["geometry"]
        return doc | geometry_document(self.geometry)

    def dumps(self) -> str:
        return tomli_w.dumps(self.to_document())


def _check(cfg: CellConfig, source: str) -> None:
    def fail(where: str, key: str, msg: str) -> None:
        raise SimConfigError(f"{source}: [{where}]: key {key!r}: {msg}")

    if cfg.cell.program not in PROGRAMS:
        fail("cell", "program", f"must be one of {', '.join(PROGRAMS)}, got {cfg.cell.program!r}")
    if cfg.cell.plan and cfg.cell.program != "campaign":
        fail("cell", "plan", f"only the 'campaign' program runs a plan, not {cfg.cell.program!r}")
    if cfg.cell.plan_sweeps and not cfg.cell.plan:
        fail("cell", "plan_sweeps", "needs a plan ([cell] plan): the sweeps are read next to it")
    if cfg.cell.check_dwell_s >= cfg.cell.check_every_s:
        fail(
            "cell",
            "check_dwell_s",
            f"{cfg.cell.check_dwell_s:g} s must be shorter than check_every_s "
            f"({cfg.cell.check_every_s:g} s)",
        )
    if not cfg.cell.robot.strip():
        fail("cell", "robot", "must name a preset or a robot description file")
    ids = cfg.encoders.node_ids
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        fail("encoders", "node_ids", f"node id {dup} given twice (ids must be distinct)")
    stop = cfg.encoders.stop_heartbeat_node
    if stop and stop not in ids:
        fail("encoders", "stop_heartbeat_node", f"{stop} is not one of node_ids {list(ids)}")
    if not cfg.encoders.channel.strip():
        fail("encoders", "channel", "must not be empty")
    if cfg.encoders.counts_per_rev * cfg.encoders.turns > 2**32:
        fail("encoders", "turns", "counts_per_rev × turns must fit the 32-bit position value")
    t = cfg.tracker.target
    if t not in ("tcp", "program") and not (
        t.startswith("link") and t[4:].isdigit() and t[4:].isascii() and int(t[4:]) >= 1
    ):
        fail("tracker", "target", f"must be 'program', 'tcp' or 'linkN' (N >= 1), got {t!r}")
    for kind in cfg.effects.drift.steps:
        if kind not in STEP_KINDS:
            fail("effects.drift", "steps", f"{kind!r} is not one of {', '.join(STEP_KINDS)}")
    und = cfg.effects.undeclared
    for key in ("drift_parameter", "lag_parameter"):
        if getattr(und, key) not in ("a", "d"):
            fail("effects.undeclared", key, f"must be 'a' or 'd', got {getattr(und, key)!r}")
    if und.joint_coupling and not und.gravity_deflection:
        fail("effects.undeclared", "joint_coupling", "needs gravity_deflection = true")
    if len(und.coupling_joints) != 2 or len(set(und.coupling_joints)) != 2:
        fail("effects.undeclared", "coupling_joints", "must be two different joints")
    if und.tracker_scale and und.tracker_scale_drift_ppm_per_h != 0.0:
        fail(
            "effects.undeclared",
            "tracker_scale_drift_ppm_per_h",
            "is for the campaign generator; the live tracker drifts through "
            "[effects] tracker_temperature_drift_k_per_h and tracker_scale_ppm_per_k",
        )
    if und.lost_motion:
        fail(
            "effects.undeclared",
            "lost_motion",
            "is for the campaign generator only "
            f"(live effects: {', '.join(n for n in EFFECT_NAMES if n != 'lost_motion')})",
        )


def check_for_robot(cfg: CellConfig, n_joints: int, source: str) -> None:
    """What needs the robot's joint count: joint numbers within 1..n, the tracker's pinned
    link, per-joint lists of one value (all joints) or one per joint (a list left at its
    default is resized as before), no more node ids or counter offsets than joints."""

    def fail(where: str, key: str, msg: str) -> None:
        raise SimConfigError(f"{source}: [{where}]: key {key!r}: {msg}")

    t = cfg.tracker.target
    if t.startswith("link") and int(t[4:]) > n_joints:
        fail("tracker", "target", f"{t}: the robot has {n_joints} joints")
    und = cfg.effects.undeclared
    if max(und.coupling_joints) > n_joints:
        fail("effects.undeclared", "coupling_joints", f"the robot has {n_joints} joints")
    for key in ("cyclic_joint", "drift_joint", "lag_joint"):
        if getattr(und, key) > n_joints:
            fail(
                "effects.undeclared",
                key,
                f"joint {getattr(und, key)}: the robot has {n_joints} joints",
            )
    per_joint = [
        ("effects", "stiffness_nmm_per_rad", cfg.effects, EffectsSection()),
        ("effects", "backlash_deg", cfg.effects, EffectsSection()),
        ("effects.undeclared", "deflection_stiffness_nmm_per_rad", und, UndeclaredEffects()),
    ]
    for where, key, section, default in per_joint:
        values = getattr(section, key)
        if values == getattr(default, key) or len(values) in (0, 1, n_joints):
            continue
        fail(
            where, key, f"{len(values)} values: give 1 (every joint) or {n_joints} (one per joint)"
        )
    for where, key, values in (
        ("encoders", "node_ids", cfg.encoders.node_ids),
        ("grating", "counter_offset_counts", cfg.grating.counter_offset_counts),
    ):
        if len(values) > n_joints:
            fail(where, key, f"{len(values)} values for a robot of {n_joints} joints")


#: Channels of the emulated grating box (sim_devices.grating_reader): the most joints an
#: emulated cell can have.
GRATING_CHANNELS = 6


def load_cell(path: str | None) -> CellConfig:
    """The configuration in ``path`` (None: the default cell), checked against its robot
    (:func:`check_for_robot`; a robot that cannot be loaded is named with its key, one
    with more joints than the grating box has channels is refused)."""
    cfg = CellConfig.load(path) if path else CellConfig()
    source = path or "default cell config"
    n = robot_option(cfg.cell.robot, f"{source}: [cell]: key 'robot':").n_joints
    if n > GRATING_CHANNELS:  # the plant and the devices are built for the box's channels
        raise SimConfigError(
            f"{source}: [cell]: key 'robot': {cfg.cell.robot} has {n} joints, the emulated "
            f"grating box reads {GRATING_CHANNELS} channels: the emulated cell needs a robot "
            f"of at most {GRATING_CHANNELS} joints"
        )
    check_for_robot(cfg, n, source)
    read_plan(cfg, robot_option(cfg.cell.robot), source)
    read_plan_sweeps(cfg, robot_option(cfg.cell.robot), source)
    return cfg


def read_plan(
    cfg: CellConfig, robot: RobotDescription, source: str
) -> tuple[FloatArray, FloatArray] | None:
    """The poses of ``[cell] plan`` (None: no plan): identify ``(N, n)`` and validate
    ``(M, n)`` rad, each in the file's order; a bad file is one line naming the key, the
    file, its line and column (the angles must be within the robot's limits)."""
    if not cfg.cell.plan:
        return None
    import numpy as np

    from calibration.errors import CalibrationError
    from calibration.identify.campaign_files import read_planned_poses

    where = f"{source}: [cell]: key 'plan':"
    limits = [(j.lower_deg, j.upper_deg) for j in robot.joints]
    try:
        plan = read_planned_poses(cfg.cell.plan, robot.n_joints, limits_deg=limits)
    except CalibrationError as exc:
        raise SimConfigError(f"{where} {one_line(str(exc))}") from None
    identify = np.radians(plan.of_set("identify"))
    if not len(identify):
        raise SimConfigError(f"{where} {plan.source}: no 'identify' pose")
    return identify, np.radians(plan.of_set("validate"))


def read_plan_sweeps(
    cfg: CellConfig, robot: RobotDescription, source: str
) -> dict[int, FloatArray] | None:
    """The planned scale-calibration sweeps next to ``[cell] plan`` with ``[cell]
    plan_sweeps`` on (its directory's ``sweeps.csv``, ``twin plan``'s; None: off, or no
    such file): per joint swept whole in view (1-based) its forward pass's stops ``(K, n)``
    rad, from the upper limit down. A bad file is one line naming the key, the file, its
    line and column."""
    if not (cfg.cell.plan and cfg.cell.plan_sweeps):
        return None
    path = Path(cfg.cell.plan).parent / "sweeps.csv"
    if not path.is_file():
        return None
    import numpy as np

    from calibration.errors import CalibrationError
    from calibration.identify.campaign_files import read_planned_sweeps

    limits = [(j.lower_deg, j.upper_deg) for j in robot.joints]
    try:
        plan = read_planned_sweeps(path, robot.n_joints, limits_deg=limits)
    except CalibrationError as exc:
        raise SimConfigError(f"{source}: [cell]: key 'plan': {one_line(str(exc))}") from None
    return {j: np.radians(q) for j, q in plan.q_deg.items() if plan.whole(j)}


# -- command-line options ---------------------------------------------------------------
def number_option(
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    what: str = "",
) -> Callable[[str], float]:
    """An ``argparse`` ``type=``: a finite float in ``lo..hi`` (``lo`` excluded when
    ``lo_open``); ``nan``, ``inf`` and values outside are refused naming the range."""
    rng = Range(lo, hi, lo_open=lo_open, what=what)

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not rng.admits(v):
            raise argparse.ArgumentTypeError(f"{rng.refusal(v)}, got {text!r}")
        return v

    parse.__name__ = "number"
    return parse


def integer_option(
    lo: int | None = None, hi: int | None = None, what: str = ""
) -> Callable[[str], int]:
    """An ``argparse`` ``type=``: an integer in ``lo..hi``."""
    rng = Range(lo, hi, what=what)

    def parse(text: str) -> int:
        if not re.fullmatch(r"[+-]?[0-9]+", text.strip()):
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}")
        v = int(text)
        if not rng.admits(v):
            raise argparse.ArgumentTypeError(f"must be {rng.describe()}, got {text!r}")
        return v

    parse.__name__ = "integer"
    return parse


SEED_OPTION = integer_option(0, MAX_SEED, "a seed")
#: The most poses, stops or points a generator option may ask for (a typo of 1e6 would
#: otherwise run for hours).
MAX_COUNT = 100_000


def joint_list(text: str) -> tuple[int, ...]:
    """An ``argparse`` ``type=``: joint numbers ``1,2,3`` (1-based, distinct, at least
    one); whether they exist on the robot is :func:`check_joints`'s job."""
    items = [t.strip() for t in text.split(",")]
    if not text.strip():
        raise argparse.ArgumentTypeError("expected joint numbers like 1,2,3, got nothing")
    out: list[int] = []
    for item in items:
        if not item.isascii() or not item.isdigit():
            whole = f" in {text!r}" if item != text.strip() else ""
            raise argparse.ArgumentTypeError(
                f"expected joint numbers like 1,2,3, got {item!r}{whole}"
            )
        j = int(item)
        if j < 1:
            raise argparse.ArgumentTypeError(f"joint {j}: joints are numbered from 1")
        if j in out:
            raise argparse.ArgumentTypeError(f"joint {j} given twice in {text!r}")
        out.append(j)
    return tuple(out)


def check_joints(joints: tuple[int, ...] | None, n_joints: int, option: str) -> None:
    """Refuse a joint number the robot does not have (``option`` names the option)."""
    for j in joints or ():
        if j > n_joints:
            raise SimError(f"{option}: joint {j}: the robot has joints 1..{n_joints}")


def robot_option(name: str, prefix: str = "--robot") -> RobotDescription:
    """The robot description ``name`` (preset or file), its errors a :class:`SimError`
    starting with ``prefix`` (the option, or file and key)."""
    from calibration.errors import CalibrationError
    from calibration.model.description import load_robot

    try:
        return load_robot(name)
    except CalibrationError as exc:
        text = one_line(str(exc))
        if not text.startswith(str(name)):
            text = f"{name}: {text}"
        raise SimError(f"{prefix} {text}") from None
