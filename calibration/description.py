"""Robot description files: a TOML a person can write, and the calibrated model written back.

Units are mm and degrees. Craig's modified D-H with a Hayati ``beta``: row i of
``[[joint]]`` is the transform from frame i-1 to frame i,

    T_i = Rot_x(alpha) · Trans_x(a) · Rot_y(beta) · Rot_z(theta + theta_offset) · Trans_z(d)

``[base]`` is the robot base in the measuring-instrument (tracker) frame, fixed-axis XYZ
angles (R = Rz(rz) · Ry(ry) · Rx(rx)); ``[tool]`` is the tracker target in the flange frame.
See docs/robot-description.md for the full schema.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any

import tomli_w

from calibration.errors import DescriptionError
from edges.command import one_line
from edges.inputs import MAX_TOML_BYTES, read_input_bytes

PRESET_PACKAGE = "calibration.presets"


@dataclass(frozen=True)
class JointDescription:
    """One revolute joint: modified D-H row (mm, degrees), limits and optional mass model."""

    a_mm: float
    alpha_deg: float
    d_mm: float
    theta_offset_deg: float
    lower_deg: float
    upper_deg: float
    beta_deg: float = 0.0
    gear_ratio: float | None = None
    mass_kg: float | None = None
    com_mm: tuple[float, float, float] | None = None
    #: a spring or gas counterbalance acts on this joint (heavy arms, joint 2): the twin's
    #: gravity term then allows it a torque profile of its own angle
    counterbalance: bool = False
    #: the joint's torsional stiffness (N·mm/rad), stated or identified by a load test
    #: (``twin stiffness --load-test``); None: not known (taken as rigid under a force)
    stiffness_nmm_per_rad: float | None = None


@dataclass(frozen=True)
class ToolDescription:
    """Tracker target in the flange frame (mm) and optional payload mass (kg)."""

    x_mm: float = 0.0
    y_mm: float = 0.0
    z_mm: float = 0.0
    mass_kg: float | None = None


@dataclass(frozen=True)
class BaseDescription:
    """Robot base pose in the instrument frame: mm and fixed-axis XYZ degrees; optionally
    the direction of gravity in the robot base frame (None: −z, a floor-mounted arm)."""

    x_mm: float = 0.0
    y_mm: float = 0.0
    z_mm: float = 0.0
    rx_deg: float = 0.0
    ry_deg: float = 0.0
    rz_deg: float = 0.0
    gravity: tuple[float, float, float] | None = None


#: An ``[[effect]]`` value: a number, a name, or an array of numbers or of names.
EffectValue = float | str | tuple[float, ...] | tuple[str, ...]


@dataclass(frozen=True)
class EffectDescription:
    """A non-geometric effect term of a calibrated model (written by the closed loop).

    ``kind`` names the effect (validated by the effect library that applies it);
    ``parameters`` maps parameter names to values, in the units their names carry.
    """

    kind: str
    parameters: Mapping[str, EffectValue] = field(default_factory=dict)


@dataclass(frozen=True)
class RobotDescription:
    """A whole robot: joints from base to flange, tool, optional base guess, Home."""

    name: str
    joints: tuple[JointDescription, ...]
    tool: ToolDescription = ToolDescription()
    base: BaseDescription | None = None
    home_deg: tuple[float, ...] | None = None
    effects: tuple[EffectDescription, ...] = ()

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def home(self) -> tuple[float, ...]:
        """The Home joint vector in degrees (zeros when the file gives none)."""
        return self.home_deg if self.home_deg is not None else (0.0,) * self.n_joints

    # -- I/O ---------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> RobotDescription:
        """Read a description file; errors name the file, table and key."""
        path = Path(path)
        raw = read_input_bytes(path, limit=MAX_TOML_BYTES, error=DescriptionError)
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise DescriptionError(
                f"{path}: not UTF-8 text (byte {exc.start}): not a robot description"
            ) from None
        return cls.loads(text, source=str(path))

    @classmethod
    def loads(cls, text: str, source: str = "<string>") -> RobotDescription:
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise DescriptionError(f"{source}: not valid TOML: {one_line(str(exc))}") from None
        return _parse(doc, source)

    def dumps(self) -> str:
        return tomli_w.dumps(_to_document(self))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.dumps(), encoding="utf-8")

    def with_joints(self, joints: tuple[JointDescription, ...]) -> RobotDescription:
        return replace(self, joints=joints)


def preset_names() -> list[str]:
    """Names of the robot descriptions shipped in ``calibration/presets``."""
    root = resources.files(PRESET_PACKAGE)
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def load_robot(name_or_path: str | Path) -> RobotDescription:
    """Load a description from a file path, or a shipped preset by name (e.g. ``kr500``)."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        return RobotDescription.load(path)
    name = str(name_or_path)
    if name in preset_names():
        res = resources.files(PRESET_PACKAGE) / f"{name}.toml"
        return RobotDescription.loads(res.read_text(encoding="utf-8"), source=f"preset:{name}")
    raise DescriptionError(
        f"{name_or_path}: no such file and no preset of that name "
        f"(presets: {', '.join(preset_names())})"
    )


# -- parsing ----------------------------------------------------------------------------
_TOP_KEYS = {"name", "home_deg", "joint", "tool", "base", "effect"}


class _Table:
    """Reads typed keys from one TOML table and reports errors with their location."""

    def __init__(self, data: Any, source: str, where: str) -> None:
        self.source, self.where = source, where
        if not isinstance(data, dict):
            self.fail(None, f"expected a table, got {type(data).__name__}")
        self.data: dict[str, Any] = data

    def fail(self, key: str | None, message: str) -> None:
        loc = f"{self.source}: {self.where}" + (f": key '{key}'" if key else "")
        raise DescriptionError(f"{loc}: {message}")

    def check_keys(self, allowed: set[str]) -> None:
        unknown = sorted(set(self.data) - allowed)
        if unknown:
            self.fail(unknown[0], f"unknown key (allowed: {', '.join(sorted(allowed))})")

    def number(self, key: str, default: float | None = None, *, required: bool = True) -> Any:
        if key not in self.data:
            if required and default is None:
                self.fail(key, "missing")
            return default
        return self._finite(key, self.data[key])

    def _finite(self, key: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            self.fail(key, f"expected a number, got {type(value).__name__} {value!r}")
        if not math.isfinite(value):
            self.fail(key, f"must be finite, got {value!r}")
        return float(value)

    def vector(self, key: str, length: int | None) -> tuple[float, ...] | None:
        if key not in self.data:
            return None
        value = self.data[key]
        if not isinstance(value, list):
            self.fail(key, f"expected an array of numbers, got {type(value).__name__}")
        if length is not None and len(value) != length:
            self.fail(key, f"expected {length} numbers, got {len(value)}")
        return tuple(self._finite(key, v) for v in value)

    def string(self, key: str) -> str:
        value = self.data.get(key)
        if value is None:
            self.fail(key, "missing")
        if not isinstance(value, str) or not value.strip():
            self.fail(key, f"expected a non-empty string, got {value!r}")
        return value


_JOINT_REQUIRED = ("a_mm", "alpha_deg", "d_mm", "theta_offset_deg", "lower_deg", "upper_deg")
_JOINT_KEYS = {
    *_JOINT_REQUIRED,
    "beta_deg",
    "gear_ratio",
    "mass_kg",
    "com_mm",
    "counterbalance",
    "stiffness_nmm_per_rad",
}


def _parse_joint(data: Any, source: str, index: int) -> JointDescription:
    t = _Table(data, source, f"[[joint]] #{index + 1}")
    t.check_keys(_JOINT_KEYS)
    values = {k: t.number(k) for k in _JOINT_REQUIRED}
    if values["lower_deg"] >= values["upper_deg"]:
        t.fail("upper_deg", f"must exceed lower_deg ({values['lower_deg']})")
    gear = t.number("gear_ratio", required=False)
    if gear is not None and gear == 0:
        t.fail("gear_ratio", "must not be zero")
    mass = t.number("mass_kg", required=False)
    if mass is not None and mass < 0:
        t.fail("mass_kg", "must not be negative")
    com = t.vector("com_mm", 3)
    stiffness = t.number("stiffness_nmm_per_rad", required=False)
    if stiffness is not None and stiffness <= 0:
        t.fail("stiffness_nmm_per_rad", f"must be positive, got {stiffness!r}")
    counterbalance = t.data.get("counterbalance", False)
    if not isinstance(counterbalance, bool):
        t.fail("counterbalance", f"expected true or false, got {counterbalance!r}")
    return JointDescription(
        **values,
        beta_deg=t.number("beta_deg", 0.0),
        gear_ratio=gear,
        mass_kg=mass,
        com_mm=com,  # type: ignore[arg-type]
        counterbalance=counterbalance,
        stiffness_nmm_per_rad=stiffness,
    )


def _parse_effect(data: Any, source: str, index: int) -> EffectDescription:
    """Numbers, names and arrays of either; what they mean is the effect library's to
    check (:func:`calibration.model_effects.description_effects`)."""
    t = _Table(data, source, f"[[effect]] #{index + 1}")
    kind = t.string("kind")
    params: dict[str, EffectValue] = {}
    for key, value in t.data.items():
        if key == "kind":
            continue
        if isinstance(value, str):
            params[key] = t.string(key)
        elif isinstance(value, list) and value and all(isinstance(v, str) for v in value):
            params[key] = tuple(value)
        elif isinstance(value, list):
            vec = t.vector(key, None)
            assert vec is not None
            params[key] = vec
        else:
            params[key] = t.number(key)
    return EffectDescription(kind=kind, parameters=params)


def _parse(doc: dict[str, Any], source: str) -> RobotDescription:
    top = _Table(doc, source, "top level")
    top.check_keys(_TOP_KEYS)
    name = top.string("name")
    raw_joints = doc.get("joint")
    if not isinstance(raw_joints, list) or not raw_joints:
        top.fail("joint", "expected one or more [[joint]] tables")
    joints = tuple(_parse_joint(j, source, i) for i, j in enumerate(raw_joints))

    home = top.vector("home_deg", len(joints))
    if home is not None:
        for i, (h, j) in enumerate(zip(home, joints, strict=True)):
            if not j.lower_deg <= h <= j.upper_deg:
                top.fail(
                    "home_deg", f"joint {i + 1} Home {h} outside [{j.lower_deg}, {j.upper_deg}]"
                )

    tool = ToolDescription()
    if "tool" in doc:
        tt = _Table(doc["tool"], source, "[tool]")
        tt.check_keys({"x_mm", "y_mm", "z_mm", "mass_kg"})
        tool = ToolDescription(
            x_mm=tt.number("x_mm"),
            y_mm=tt.number("y_mm"),
            z_mm=tt.number("z_mm"),
            mass_kg=tt.number("mass_kg", required=False),
        )
    base = None
    if "base" in doc:
        bt = _Table(doc["base"], source, "[base]")
        keys = [f.name for f in fields(BaseDescription) if f.name != "gravity"]
        bt.check_keys({*keys, "gravity"})
        gravity = bt.vector("gravity", 3)
        if gravity is not None and not any(gravity):
            bt.fail("gravity", "must be a direction, not [0, 0, 0]")
        base = BaseDescription(**{k: bt.number(k) for k in keys}, gravity=gravity)  # type: ignore[arg-type]
    raw_effects = doc.get("effect", [])
    if not isinstance(raw_effects, list):
        top.fail("effect", "expected [[effect]] tables")
    effects = tuple(_parse_effect(e, source, i) for i, e in enumerate(raw_effects))
    return RobotDescription(
        name=name, joints=joints, tool=tool, base=base, home_deg=home, effects=effects
    )


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items() if v is not None}


def _to_document(desc: RobotDescription) -> dict[str, Any]:
    doc: dict[str, Any] = {"name": desc.name}
    if desc.home_deg is not None:
        doc["home_deg"] = list(desc.home_deg)
    doc["tool"] = _drop_none({f.name: getattr(desc.tool, f.name) for f in fields(ToolDescription)})
    if desc.base is not None:
        doc["base"] = _drop_none(
            {f.name: getattr(desc.base, f.name) for f in fields(BaseDescription)}
        )
    doc["joint"] = [
        {
            k: v
            for k, v in _drop_none(
                {f.name: getattr(j, f.name) for f in fields(JointDescription)}
            ).items()
            if k != "counterbalance" or v  # written only where there is one
        }
        for j in desc.joints
    ]
    if desc.effects:
        doc["effect"] = [{"kind": e.kind, **_drop_none(dict(e.parameters))} for e in desc.effects]
    return doc
