"""The emulated cell's configuration (``cell.toml``): devices, effects and injected faults.

Every table is a dataclass below; keys are checked against its fields (unknown keys are
errors that list the allowed ones). All keys are optional: an empty file is the default
cell. Units are in the key names. See docs/protocols.md for an annotated example.
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import tomli_w

from sim_devices.effects import EFFECT_NAMES, UndeclaredEffects
from sim_devices.errors import SimConfigError


@dataclass(frozen=True)
class CellSection:
    robot: str = "kr500"  # preset name or description file
    seed: int = 1
    speed: float = 1.0  # simulated clock speed (robot program time per wall second)
    program: str = "campaign"  # see PROGRAMS
    eccentricity_mm: float = 0.002
    truth_file: str = ""  # write the truth here at start ("" = don't)
    run_dir: str = ""  # where pty symlinks go ("" = a fresh temp dir)


PROGRAMS = {
    "campaign": "grating calibration (home returns, 2° sweeps; tracker target on the swept "
    "link) + 100 id + 150 validation poses (TCP target)",
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


@dataclass(frozen=True)
class CellConfig:
    cell: CellSection = field(default_factory=CellSection)
    effects: EffectsSection = field(default_factory=EffectsSection)
    grating: GratingSection = field(default_factory=GratingSection)
    encoders: EncoderSection = field(default_factory=EncoderSection)
    tracker: TrackerSection = field(default_factory=TrackerSection)

    @classmethod
    def load(cls, path: str | Path) -> CellConfig:
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise SimConfigError(f"{path}: cannot read cell config: {exc}") from exc
        return cls.loads(text, source=str(path))

    @classmethod
    def loads(cls, text: str, source: str = "<string>") -> CellConfig:
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SimConfigError(f"{source}: not valid TOML: {exc}") from exc
        cfg = _build(cls, doc, source, "top level")
        _check(cfg, source)
        return cfg

    def to_document(self) -> dict[str, Any]:
        return asdict(self)

    def dumps(self) -> str:
        return tomli_w.dumps(self.to_document())


def _build(cls: type, data: Any, source: str, where: str) -> Any:
    if not isinstance(data, dict):
        raise SimConfigError(f"{source}: {where}: expected a table")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise SimConfigError(
            f"{source}: {where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(known))})"
        )
    kwargs: dict[str, Any] = {}
    defaults = cls()
    for name, value in data.items():
        default = getattr(defaults, name)
        loc = f"{where}.{name}" if where != "top level" else f"[{name}]"
        if hasattr(default, "__dataclass_fields__"):
            kwargs[name] = _build(type(default), value, source, loc)
        else:
            kwargs[name] = _coerce(default, value, source, loc)
    return cls(**kwargs)


def _coerce(default: Any, value: Any, source: str, loc: str) -> Any:
    def bad(expected: str) -> SimConfigError:
        return SimConfigError(f"{source}: {loc}: expected {expected}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list):
            raise bad("an array")
        return tuple(value)
    raise bad(type(default).__name__)


def _check(cfg: CellConfig, source: str) -> None:
    def fail(msg: str) -> None:
        raise SimConfigError(f"{source}: {msg}")

    if cfg.cell.program not in PROGRAMS:
        fail(f"[cell].program must be one of {', '.join(PROGRAMS)}, got {cfg.cell.program!r}")
    if cfg.cell.speed <= 0:
        fail("[cell].speed must be positive")
    if not 1 <= cfg.grating.unit_id <= 247:
        fail("[grating].unit_id must be in 1..247")
    if not 1.0 <= cfg.grating.rate_hz <= 20000.0:
        fail("[grating].rate_hz must be in 1..20000")
    ids = cfg.encoders.node_ids
    if len(set(ids)) != len(ids) or not all(1 <= i <= 127 for i in ids):
        fail("[encoders].node_ids must be distinct CANopen node ids in 1..127")
    if cfg.tracker.target not in ("tcp", "program") and not (
        cfg.tracker.target.startswith("link") and cfg.tracker.target[4:].isdigit()
    ):
        fail(f"[tracker].target must be 'program', 'tcp' or 'linkN', got {cfg.tracker.target!r}")
    und = cfg.effects.undeclared
    for key in ("drift_parameter", "lag_parameter"):
        if getattr(und, key) not in ("a", "d"):
            fail(f"[effects.undeclared].{key} must be 'a' or 'd', got {getattr(und, key)!r}")
    for key in ("cyclic_joint", "drift_joint", "lag_joint"):
        if not 1 <= getattr(und, key) <= 6:
            fail(f"[effects.undeclared].{key} must be a joint number 1..6")
    if und.lag_time_constant_s <= 0:
        fail("[effects.undeclared].lag_time_constant_s must be positive")
    if und.cyclic_order < 1:
        fail("[effects.undeclared].cyclic_order must be at least 1")
    if und.tracker_scale and und.tracker_scale_drift_ppm_per_h != 0.0:
        fail(
            "[effects.undeclared].tracker_scale_drift_ppm_per_h is for the campaign generator; "
            "the live tracker drifts through tracker_temperature_drift_k_per_h and "
            "tracker_scale_ppm_per_k"
        )
    if und.lost_motion:
        fail(
            "[effects.undeclared].lost_motion is for the campaign generator only "
            f"(live effects: {', '.join(n for n in EFFECT_NAMES if n != 'lost_motion')})"
        )
    for name, p in asdict(cfg.grating.faults).items():
        if name.endswith("probability") and not 0.0 <= p <= 1.0:
            fail(f"[grating.faults].{name} must be in [0, 1]")
