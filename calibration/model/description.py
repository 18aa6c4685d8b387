"""Robot description files: a TOML a person can write, and the calibrated model written back.

Units are mm and degrees. Craig's modified D-H with a Hayati ``beta``: row i of
``[[joint]]`` is the transform from frame i-1 to frame i,

    T_i = Rot_x(alpha) · Trans_x(a) · Rot_y(beta) · Rot_z(theta + theta_offset) · Trans_z(d)

``[base]`` is the robot base in the measuring-instrument (tracker) frame, fixed-axis XYZ
angles (R = Rz(rz) · Ry(ry) · Rx(rx)); ``[tool]`` is the tracker target in the flange frame.
See docs/robot-description.md for the full schema.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import tomli_w

from calibration.errors import DescriptionError
from edges.toml_schema import (
    REQUIRED,
    Range,
    TomlTable,
    build,
    key_spec,
    parse_toml_file,
    parse_toml_text,
)

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

PRESET_PACKAGE = "calibration.presets"
_T = TypeVar("_T", bound="DataclassInstance")


#: A joint's top speed (deg/s) assumed where a description states none.
DEFAULT_JOINT_SPEED_DEG_S = 90.0

#: Motor turns per joint turn assumed for a joint whose description states none.
DEFAULT_GEAR_RATIO = 100.0


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
    mass_kg: float | None = field(
        default=None, metadata=key_spec(range=Range(0.0, what="kg, not negative"))
    )
    com_mm: tuple[float, float, float] | None = None
    #: a spring or gas counterbalance acts on this joint (heavy arms, joint 2): the twin's
    #: gravity term then allows it a torque profile of its own angle
    counterbalance: bool = False
    #: the joint's torsional stiffness (N·mm/rad), stated or identified by a load test
    #: (``twin stiffness --load-test``); None: not known (taken as rigid under a force)
    stiffness_nmm_per_rad: float | None = field(
        default=None, metadata=key_spec(range=Range(0.0, lo_open=True, what="N·mm/rad, positive"))
    )
    #: the joint's top speed (deg/s, the data sheet's); None: not stated (a planner then
    #: assumes :data:`DEFAULT_JOINT_SPEED_DEG_S`)
    max_speed_deg_s: float | None = field(
        default=None, metadata=key_spec(range=Range(0.0, 3600.0, lo_open=True, what="deg/s"))
    )
    #: the controller's angle of this joint is ``controller_sign · q + controller_offset_deg``
    #: (q: this description's angle, deg); what robot programs (KRL, RAPID) are written in
    controller_offset_deg: float = 0.0
    controller_sign: Literal[1, -1] = 1


@dataclass(frozen=True)
class ToolDescription:
    """Tracker target in the flange frame (mm) and optional payload mass (kg)."""

    x_mm: float = field(default=0.0, metadata=REQUIRED)
    y_mm: float = field(default=0.0, metadata=REQUIRED)
    z_mm: float = field(default=0.0, metadata=REQUIRED)
    mass_kg: float | None = None


@dataclass(frozen=True)
class BaseDescription:
    """Robot base pose in the instrument frame: mm and fixed-axis XYZ degrees; optionally
    the direction of gravity in the robot base frame (None: −z, a floor-mounted arm)."""

    x_mm: float = field(default=0.0, metadata=REQUIRED)
    y_mm: float = field(default=0.0, metadata=REQUIRED)
    z_mm: float = field(default=0.0, metadata=REQUIRED)
    rx_deg: float = field(default=0.0, metadata=REQUIRED)
    ry_deg: float = field(default=0.0, metadata=REQUIRED)
    rz_deg: float = field(default=0.0, metadata=REQUIRED)
    gravity: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class TrackingDescription:
    """What ``twin track`` needs from the campaign that calibrated the model (``[tracking]``,
    written by :func:`calibration.effects.calibrate.calibrate`; absent in files of earlier
    versions).

    ``identified``: the geometric parameters the campaign identified (model names,
    :meth:`calibration.model.kinematics.KinematicModel.parameter_names`); ``sigma_mm``: the
    per-axis error σ of the final fit; ``identify_deg`` ``(m, n)``: the identification
    poses (the information the campaign gave); ``reference_deg`` ``(r, n)``: the validation
    poses at which a tracked model's TCP is compared with the calibrated one's (the alarm).
    """

    identified: tuple[str, ...]
    sigma_mm: float
    identify_deg: tuple[tuple[float, ...], ...]
    reference_deg: tuple[tuple[float, ...], ...]


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


@dataclass(frozen=True, eq=False)
class LearnedResidualDescription:
    """The learned residual stage's Gaussian process (:mod:`calibration.effects.learned_residual`):
    its hyperparameters and training points, joint angles ``q_deg`` ``(N, n)`` and the
    traced model's residuals ``residual_mm`` ``(N, 3)`` (tracker − traced model), and
    ``extra_sd_mm``, added in quadrature to every predictive standard deviation (from the
    validation poses; 0 when a file has none). Compared by identity (it is the key of the
    factored model's cache)."""

    kernel: str
    length_scales_rad: tuple[float, ...]
    signal_sd_mm: float
    noise_sd_mm: float
    reach: float
    q_deg: tuple[tuple[float, ...], ...] = field(repr=False)
    residual_mm: tuple[tuple[float, ...], ...] = field(repr=False)
    extra_sd_mm: float = 0.0


@dataclass(frozen=True)
class ResidualDescription:
    """What the model does not explain: the traced model's per-axis standard deviation
    (mm, the identification residuals' RMS), and the learned stage when it was accepted."""

    traced_sd_mm: float
    learned: LearnedResidualDescription | None = None


@dataclass(frozen=True)
class RobotDescription:
    """A whole robot: joints from base to flange, tool, optional base guess, Home."""

    name: str
    joints: tuple[JointDescription, ...]
    tool: ToolDescription = ToolDescription()
    base: BaseDescription | None = None
    home_deg: tuple[float, ...] | None = None
    effects: tuple[EffectDescription, ...] = ()
    tracking: TrackingDescription | None = None
    residual: ResidualDescription | None = None

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def home(self) -> tuple[float, ...]:
        """The Home joint vector in degrees (zeros when the file gives none)."""
        return self.home_deg if self.home_deg is not None else (0.0,) * self.n_joints

    @property
    def gear_ratios(self) -> tuple[float, ...]:
        """Motor turns per joint turn, per joint (:data:`DEFAULT_GEAR_RATIO` where the
        file gives none): how the motor encoders' counts become joint angles."""
        return tuple(j.gear_ratio or DEFAULT_GEAR_RATIO for j in self.joints)

    # -- I/O ---------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> RobotDescription:
        """Read a description file; errors name the file, table and key."""
        doc = parse_toml_file(path, DescriptionError, "a robot description")
        return _parse(doc, str(path))

    @classmethod
    def loads(cls, text: str, source: str = "<string>") -> RobotDescription:
        return _parse(parse_toml_text(text, source, DescriptionError), source)

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
_TOP_KEYS = {"name", "home_deg", "joint", "tool", "base", "effect", "tracking", "residual"}


def _parse_joint(data: Any, source: str, index: int) -> JointDescription:
    name = f"[[joint]] #{index + 1}"
    joint = build(JointDescription, data, source=source, error=DescriptionError, name=name)
    t = TomlTable(data, source, name, DescriptionError)
    if joint.lower_deg >= joint.upper_deg:
        raise t.fail("upper_deg", f"must exceed lower_deg ({joint.lower_deg})")
    if joint.gear_ratio is not None and joint.gear_ratio == 0:
        raise t.fail("gear_ratio", "must not be zero")
    return joint


def _parse_effect(data: Any, source: str, index: int) -> EffectDescription:
    """Numbers, names and arrays of either; what they mean is the effect library's to
    check (:func:`calibration.effects.model_effects.description_effects`)."""
    t = TomlTable(data, source, f"[[effect]] #{index + 1}", DescriptionError)
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
            params[key] = t.numbers(key)
        else:
            params[key] = t.number(key)
    return EffectDescription(kind=kind, parameters=params)


def _pose_rows(t: TomlTable, key: str, n_joints: int) -> tuple[tuple[float, ...], ...]:
    rows = t.get(key)
    if not isinstance(rows, list) or not rows:
        raise t.fail(key, "expected a non-empty array of joint vectors (degrees)")
    return tuple(tuple(float(v) for v in t.numbers(key, r, length=n_joints)) for r in rows)


def _parse_tracking(doc: dict[str, Any], source: str, n_joints: int) -> TrackingDescription:
    t = TomlTable(doc["tracking"], source, "[tracking]", DescriptionError)
    t.check_keys({"identified", "sigma_mm", "identify_deg", "reference_deg"})
    return TrackingDescription(
        identified=t.strings("identified"),
        sigma_mm=t.number("sigma_mm", rng=Range(0.0, lo_open=True, what="mm, positive")),
        identify_deg=_pose_rows(t, "identify_deg", n_joints),
        reference_deg=_pose_rows(t, "reference_deg", n_joints),
    )


def _parse(doc: dict[str, Any], source: str) -> RobotDescription:
    top = TomlTable(doc, source, "top level", DescriptionError)
    top.check_keys(_TOP_KEYS)
    name = top.string("name")
    raw_joints = doc.get("joint")
    if not isinstance(raw_joints, list) or not raw_joints:
        raise top.fail("joint", "expected one or more [[joint]] tables")
    joints = tuple(_parse_joint(j, source, i) for i, j in enumerate(raw_joints))

    home = top.numbers("home_deg", length=len(joints)) if "home_deg" in doc else None
    for i, (h, j) in enumerate(zip(home or (), joints, strict=False)):
        if not j.lower_deg <= h <= j.upper_deg:
            raise top.fail(
                "home_deg", f"joint {i + 1} Home {h} outside [{j.lower_deg}, {j.upper_deg}]"
            )

    def table(cls: type[_T], key: str) -> _T:
        return build(cls, doc[key], source=source, error=DescriptionError, path=(key,))

    tool = table(ToolDescription, "tool") if "tool" in doc else ToolDescription()
    base = table(BaseDescription, "base") if "base" in doc else None
    if base is not None and base.gravity is not None and not any(base.gravity):
        raise top.table("base").fail("gravity", "must be a direction, not [0, 0, 0]")
    raw_effects = doc.get("effect", [])
    if not isinstance(raw_effects, list):
        raise top.fail("effect", "expected [[effect]] tables")
    effects = tuple(_parse_effect(e, source, i) for i, e in enumerate(raw_effects))
    tracking = _parse_tracking(doc, source, len(joints)) if "tracking" in doc else None
    residual = _parse_residual(top.table("residual"), len(joints)) if "residual" in doc else None
    return RobotDescription(
        name=name,
        joints=joints,
        tool=tool,
        base=base,
        home_deg=home,
        effects=effects,
        tracking=tracking,
        residual=residual,
    )


_POSITIVE = Range(0.0, lo_open=True, what="positive")
_NOT_NEGATIVE = Range(0.0, what="not negative")


def _rows(t: TomlTable, key: str, width: int) -> tuple[tuple[float, ...], ...]:
    """An array of ``width``-number arrays (one per training point)."""
    value = t.get(key)
    if not isinstance(value, list) or not value:
        raise t.fail(key, f"expected a non-empty array of {width}-number arrays")
    return tuple(t.numbers(key, row, length=width) for row in value)


def _parse_residual(t: TomlTable, n_joints: int) -> ResidualDescription:
    """``[residual]`` and its optional ``[residual.learned]``; the training points must
    be as many as their residuals."""
    t.check_keys({"traced_sd_mm", "learned"})
    traced = t.number("traced_sd_mm", rng=_POSITIVE)
    if "learned" not in t.data:
        return ResidualDescription(traced_sd_mm=traced)
    g = t.table("learned")
    keys = ("kernel", "length_scales_rad", "signal_sd_mm", "noise_sd_mm", "reach")
    g.check_keys({*keys, "q_deg", "residual_mm", "extra_sd_mm"})
    kernel = g.string("kernel")
    if kernel != "periodic_ard_se":
        raise g.fail("kernel", f"unknown kernel {kernel!r} (known: periodic_ard_se)")
    q, r = _rows(g, "q_deg", n_joints), _rows(g, "residual_mm", 3)
    if len(q) != len(r):
        raise g.fail("residual_mm", f"{len(r)} rows for {len(q)} rows of q_deg")
    learned = LearnedResidualDescription(
        kernel=kernel,
        length_scales_rad=g.numbers("length_scales_rad", length=n_joints, rng=_POSITIVE),
        signal_sd_mm=g.number("signal_sd_mm", rng=_POSITIVE),
        noise_sd_mm=g.number("noise_sd_mm", rng=_POSITIVE),
        reach=g.number("reach", rng=_POSITIVE),
        q_deg=q,
        residual_mm=r,
        extra_sd_mm=g.number("extra_sd_mm", rng=_NOT_NEGATIVE, default=0.0),
    )
    return ResidualDescription(traced_sd_mm=traced, learned=learned)


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
            if (k != "counterbalance" or v)  # written only where there is one
            and not (k == "controller_offset_deg" and v == 0.0)
            and not (k == "controller_sign" and v == 1)
        }
        for j in desc.joints
    ]
    if desc.effects:
        doc["effect"] = [{"kind": e.kind, **_drop_none(dict(e.parameters))} for e in desc.effects]
    if desc.tracking is not None:
        tr = desc.tracking
        doc["tracking"] = {
            "identified": list(tr.identified),
            "sigma_mm": tr.sigma_mm,
            "identify_deg": [list(r) for r in tr.identify_deg],
            "reference_deg": [list(r) for r in tr.reference_deg],
        }
    if desc.residual is not None:
        doc["residual"] = {"traced_sd_mm": desc.residual.traced_sd_mm}
        g = desc.residual.learned
        if g is not None:
            doc["residual"]["learned"] = {
                "kernel": g.kernel,
                "length_scales_rad": list(g.length_scales_rad),
                "signal_sd_mm": g.signal_sd_mm,
                "noise_sd_mm": g.noise_sd_mm,
                "reach": g.reach,
                "extra_sd_mm": g.extra_sd_mm,
                "q_deg": [list(row) for row in g.q_deg],
                "residual_mm": [list(row) for row in g.residual_mm],
            }
    return doc
