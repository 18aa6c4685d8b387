"""The cell around the robot: tracker station, reflector, obstacles, floor, working region.

Read from the geometry tables of ``cell.toml`` (the same file the emulated cell reads; its
own tables ``[cell]``, ``[effects]``, ``[grating]``, ``[encoders]``, ``[tracker]`` are the
emulator's and are not read here). Every length is mm in the robot's **base frame**, every
angle degrees. All keys are optional; an empty file is the default cell, derived from the
robot (the emulator's cell: the tracker where the description's base puts it, at the
instrument frame's origin).

``[station]``  ``x_mm``, ``y_mm``, ``z_mm``: the tracker head (default: the instrument
frame's origin as the description's ``[base]`` places it; without a base, 1.1 reach in
front of the robot at 0.4 reach height); ``min_range_mm`` (1000), ``max_range_mm``
(25000): the distances it measures over.
``[reflector]``  ``axis``: the reflector's axis in the flange frame (``[0, 0, 1]``: the
tool's z); ``cone_half_angle_deg`` (30: a 1.5" SMR's acceptance, ±30° about its axis).
``[floor]``  ``z_mm`` (0): the floor plane; ``clearance_mm`` (50) kept above it.
``[arm]``  ``link_radius_mm``: each link as a capsule of this radius around the line
joining consecutive joint origins (default 6 % of the reach: 170 mm on a KR500).
``[region]``  ``min_mm``, ``max_mm`` ``[x, y, z]``: the box where the robot works, which
the calibration must serve best (default, in reach R: x 0.35R..0.85R, y −0.5R..0.5R,
z 0.1R..0.75R).
``[[obstacle]]``  ``name``, ``min_mm``, ``max_mm`` ``[x, y, z]``: a box the arm must not
touch and the beam cannot pass (default: one fixture table behind the robot,
x −0.45R..−0.25R, y −0.25R..0.25R, z 0..0.3R).

A pose is **in view** when the reflector's axis points within the cone of the station,
the station's distance is within range, and the line from the station to the reflector
crosses no obstacle. A pose is **clear** when no link capsule touches an obstacle or
comes below the floor's clearance (the links from the base to joint 2, which stand on the
floor, are exempt from the floor).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.description import RobotDescription
from calibration.model.kinematics import (
    KinematicModel,
    flange_poses,
    rotation_from_fixed_xyz,
)
from edges.toml_schema import NON_NEGATIVE, POSITIVE, Range, build, key_spec

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: The emulator's tables of ``cell.toml`` (read by ``sim_devices.config``, not here).
EMULATOR_TABLES = ("cell", "effects", "grating", "encoders", "tracker")
#: The tables this module reads.
GEOMETRY_TABLES = ("station", "reflector", "floor", "arm", "region", "obstacle")

_CONE = Range(0.0, 90.0, lo_open=True, what="deg, half angle")


@dataclass(frozen=True)
class StationSection:
    x_mm: float | None = None
    y_mm: float | None = None
    z_mm: float | None = None
    min_range_mm: float = field(default=1000.0, metadata=key_spec(range=NON_NEGATIVE))
    max_range_mm: float = field(default=25000.0, metadata=key_spec(range=POSITIVE))


@dataclass(frozen=True)
class ReflectorSection:
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    cone_half_angle_deg: float = field(default=30.0, metadata=key_spec(range=_CONE))


@dataclass(frozen=True)
class FloorSection:
    z_mm: float = 0.0
    clearance_mm: float = field(default=50.0, metadata=key_spec(range=NON_NEGATIVE))


@dataclass(frozen=True)
class ArmSection:
    link_radius_mm: float | None = field(
        default=None, metadata=key_spec(range=Range(0.0, what="mm"))
    )


@dataclass(frozen=True)
class RegionSection:
    min_mm: tuple[float, float, float] | None = None
    max_mm: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class ObstacleSection:
    name: str = ""
    min_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CellGeometrySpec:
    """The geometry tables as the file states them (None: the robot's default)."""

    station: StationSection = StationSection()
    reflector: ReflectorSection = ReflectorSection()
    floor: FloorSection = FloorSection()
    arm: ArmSection = ArmSection()
    region: RegionSection = RegionSection()
    obstacles: tuple[ObstacleSection, ...] | None = None


@dataclass(frozen=True, eq=False)
class Box:
    """An axis-aligned box in the base frame (mm)."""

    name: str
    lo: FloatArray  # (3,)
    hi: FloatArray  # (3,)


@dataclass(frozen=True, eq=False)
class CellGeometry:
    """The resolved cell of one robot; every array in the base frame, mm."""

    station_mm: FloatArray  # (3,)
    min_range_mm: float
    max_range_mm: float
    axis_flange: FloatArray  # (3,) unit reflector axis in the flange frame
    cone_half_angle_deg: float
    floor_z_mm: float
    floor_clearance_mm: float
    link_radius_mm: float
    region_lo: FloatArray  # (3,)
    region_hi: FloatArray  # (3,)
    obstacles: tuple[Box, ...]


def read_cell_geometry(
    doc: Mapping[str, Any], source: str, error: type[Exception], *, others: tuple[str, ...] = ()
) -> CellGeometrySpec:
    """The geometry tables of a parsed ``cell.toml``. A top-level table that is neither a
    geometry table nor one of ``others`` (the tables a caller reads or allows) is
    ``error``, as is any unknown key, wrong type or value out of range."""
    allowed = (*others, *GEOMETRY_TABLES)
    unknown = sorted(set(doc) - set(allowed))
    if unknown:
        raise error(f"{source}: unknown table {unknown[0]!r} (allowed: {', '.join(allowed)})")
    tables: dict[str, Any] = {}
    for key, cls in (
        ("station", StationSection),
        ("reflector", ReflectorSection),
        ("floor", FloorSection),
        ("arm", ArmSection),
        ("region", RegionSection),
    ):
        if key in doc:
            tables[key] = build(cls, doc[key], source=source, error=error, path=(key,))
    obstacles = None
    if "obstacle" in doc:
        items = doc["obstacle"]
        if not isinstance(items, list):
            raise error(f"{source}: 'obstacle': expected an array of tables ([[obstacle]])")
        obstacles = tuple(
            build(ObstacleSection, item, source=source, error=error, name=f"[[obstacle]] #{i}")
            for i, item in enumerate(items, 1)
        )
    spec = CellGeometrySpec(**tables, obstacles=obstacles)
    _check_spec(spec, source, error)
    return spec


def _check_spec(spec: CellGeometrySpec, source: str, error: type[Exception]) -> None:
    def fail(where: str, key: str, msg: str) -> None:
        raise error(f"{source}: {where}: key {key!r}: {msg}")

    st = spec.station
    if (st.x_mm, st.y_mm, st.z_mm).count(None) not in (0, 3):
        fail("[station]", "x_mm", "give x_mm, y_mm and z_mm together (or none: the default)")
    if st.max_range_mm <= st.min_range_mm:
        fail("[station]", "max_range_mm", f"must exceed min_range_mm ({st.min_range_mm:g})")
    if float(np.linalg.norm(spec.reflector.axis)) < 1e-9:
        fail("[reflector]", "axis", "must not be the zero vector")
    reg = spec.region
    if (reg.min_mm is None) != (reg.max_mm is None):
        fail("[region]", "max_mm", "give min_mm and max_mm together (or neither)")
    if (
        reg.min_mm is not None
        and reg.max_mm is not None
        and not all(a < b for a, b in zip(reg.min_mm, reg.max_mm, strict=True))
    ):
        fail("[region]", "max_mm", "must exceed min_mm on every axis")
    for i, box in enumerate(spec.obstacles or (), 1):
        if not all(a < b for a, b in zip(box.min_mm, box.max_mm, strict=True)):
            fail(f"[[obstacle]] #{i}", "max_mm", "must exceed min_mm on every axis")


def robot_reach_mm(description: RobotDescription) -> float:
    """The arm's reach (mm): the lengths of joints 2..4 (a and d), as the emulator scales."""
    return float(sum(abs(j.a_mm) + abs(j.d_mm) for j in description.joints[1:4]))


def default_station_mm(description: RobotDescription) -> FloatArray:
    """Where the emulator's tracker sits, in the base frame: the instrument frame's origin
    as the description's base places it (mm, ``(3,)``)."""
    base = description.base
    if base is None:
        r = robot_reach_mm(description)
        return np.array([1.1 * r, 0.0, 0.4 * r])
    rot = rotation_from_fixed_xyz(*np.radians([base.rx_deg, base.ry_deg, base.rz_deg]))
    origin: FloatArray = -rot.T @ np.array([base.x_mm, base.y_mm, base.z_mm])
    return origin


def resolve(spec: CellGeometrySpec, description: RobotDescription) -> CellGeometry:
    """The cell of ``description`` with every default filled in (see the module text)."""
    r = robot_reach_mm(description)
    st = spec.station
    station = (
        default_station_mm(description)
        if st.x_mm is None or st.y_mm is None or st.z_mm is None
        else np.array([st.x_mm, st.y_mm, st.z_mm])
    )
    reg = spec.region
    lo = np.array(reg.min_mm) if reg.min_mm is not None else r * np.array([0.35, -0.5, 0.1])
    hi = np.array(reg.max_mm) if reg.max_mm is not None else r * np.array([0.85, 0.5, 0.75])
    if spec.obstacles is None:
        boxes: tuple[Box, ...] = (
            Box(
                "fixture table", r * np.array([-0.45, -0.25, 0.0]), r * np.array([-0.25, 0.25, 0.3])
            ),
        )
    else:
        boxes = tuple(
            Box(o.name or f"obstacle {i}", np.array(o.min_mm), np.array(o.max_mm))
            for i, o in enumerate(spec.obstacles, 1)
        )
    axis = np.array(spec.reflector.axis, dtype=float)
    return CellGeometry(
        station_mm=station,
        min_range_mm=st.min_range_mm,
        max_range_mm=st.max_range_mm,
        axis_flange=axis / np.linalg.norm(axis),
        cone_half_angle_deg=spec.reflector.cone_half_angle_deg,
        floor_z_mm=spec.floor.z_mm,
        floor_clearance_mm=spec.floor.clearance_mm,
        link_radius_mm=(
            spec.arm.link_radius_mm if spec.arm.link_radius_mm is not None else 0.06 * r
        ),
        region_lo=lo,
        region_hi=hi,
        obstacles=boxes,
    )


# -- view ----------------------------------------------------------------------------------
#: Why a pose is not in view, by code (0: in view).
VIEW_REASONS = {
    1: "reflector out of its acceptance cone",
    2: "reflector out of the tracker's range",
    3: "beam blocked by an obstacle",
}


def segment_hits_box(a: FloatArray, b: FloatArray, box: Box) -> BoolArray:
    """Whether each segment ``a[i]``–``b[i]`` ``(N, 3)`` crosses ``box`` (slab test)."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (box.lo - a) / d
        t2 = (box.hi - a) / d
    inside_slab = (a >= box.lo) & (a <= box.hi)
    parallel = d == 0
    t_lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    t_hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    enter = np.max(t_lo, axis=1)
    leave = np.min(t_hi, axis=1)
    hit: BoolArray = (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)
    return hit


def view_codes(
    geometry: CellGeometry,
    reflector_mm: ArrayLike,
    axis_base: ArrayLike,
    station_mm: ArrayLike | None = None,
) -> NDArray[np.int8]:
    """Per pose, 0 (in view) or the first reason of :data:`VIEW_REASONS` it is not.

    ``reflector_mm`` ``(N, 3)`` and its unit axis ``axis_base`` ``(N, 3)`` in the base
    frame; ``station_mm`` ``(3,)``: the tracker (default: the cell's)."""
    p = np.atleast_2d(np.asarray(reflector_mm, dtype=float))
    ax = np.atleast_2d(np.asarray(axis_base, dtype=float))
    st = geometry.station_mm if station_mm is None else np.asarray(station_mm, dtype=float)
    to_station = st - p
    dist = np.linalg.norm(to_station, axis=1)
    cos = np.sum(ax * to_station, axis=1) / np.maximum(dist, 1e-12)
    codes = np.zeros(len(p), dtype=np.int8)
    blocked = np.zeros(len(p), dtype=bool)
    for box in geometry.obstacles:
        blocked |= segment_hits_box(p, np.broadcast_to(st, p.shape), box)
    codes[blocked] = 3
    codes[(dist < geometry.min_range_mm) | (dist > geometry.max_range_mm)] = 2
    codes[cos < np.cos(np.radians(geometry.cone_half_angle_deg))] = 1
    return codes


def reflector_in_base(
    model: KinematicModel, geometry: CellGeometry, q_rad: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """The reflector (the model's tool point) ``(N, 3)`` and its unit axis ``(N, 3)`` in
    the base frame at joint vectors ``(N, n)`` rad."""
    f = flange_poses(model, np.atleast_2d(np.asarray(q_rad, dtype=float)), world=False)
    pos = f[:, :3, 3] + f[:, :3, :3] @ np.asarray(model.tool_mm, dtype=float)
    axis = f[:, :3, :3] @ geometry.axis_flange
    return pos, axis


# -- collisions ------------------------------------------------------------------------------
#: Points sampled along each link's segment for the capsule test.
POINTS_PER_LINK = 6


def link_points(model: KinematicModel, q_rad: ArrayLike) -> FloatArray:
    """Points along the arm ``(N, L, POINTS_PER_LINK, 3)`` mm, base frame: on the segments
    joining the joint origins 1..n, the flange and the tool point (L = n + 1 links)."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    n = model.n_joints
    origins = [
        flange_poses(model.truncated(k), q[:, :k], world=False)[:, :3, 3] for k in range(1, n + 1)
    ]
    f = flange_poses(model, q, world=False)
    origins.append(f[:, :3, 3] + f[:, :3, :3] @ np.asarray(model.tool_mm, dtype=float))
    ends = np.stack(origins, axis=1)  # (N, n + 1, 3)
    a, b = ends[:, :-1], ends[:, 1:]
    t = np.linspace(0.0, 1.0, POINTS_PER_LINK)[None, None, :, None]
    pts: FloatArray = a[:, :, None, :] + t * (b - a)[:, :, None, :]
    return pts


def collision_codes(
    model: KinematicModel, geometry: CellGeometry, q_rad: ArrayLike
) -> NDArray[np.int8]:
    """Per joint vector ``(N, n)`` rad: 0 clear, 1 below the floor's clearance, 2 + i
    touching obstacle i (the first one found)."""
    pts = link_points(model, q_rad)
    r = geometry.link_radius_mm
    codes = np.zeros(pts.shape[0], dtype=np.int8)
    # links from joint 2's origin outward (the first segment stands on the floor); that
    # origin itself only turns about joint 1's axis, at the height the mount gives it,
    # which is no pose's doing (a UR's shoulder sits 127 mm above its table)
    above = pts[:, 1:, :, 2] - r - geometry.floor_clearance_mm
    above[:, 0, 0] = np.inf
    codes[np.any(above < geometry.floor_z_mm, axis=(1, 2))] = 1
    for i, box in enumerate(geometry.obstacles):
        gap = np.maximum(np.maximum(box.lo - pts, pts - box.hi), 0.0)
        touch = np.any(np.linalg.norm(gap, axis=-1) <= r, axis=(1, 2))
        codes[touch & (codes == 0)] = 2 + i
    return codes


def collision_reason(geometry: CellGeometry, code: int) -> str:
    """The words for a :func:`collision_codes` value."""
    if code == 1:
        return "arm below the floor's clearance"
    return f"arm touches obstacle {geometry.obstacles[code - 2].name!r}"


#: Joint-space points checked along a straight-line joint move.
MOVE_SAMPLES = 12


def move_collision_codes(
    model: KinematicModel, geometry: CellGeometry, q_from: ArrayLike, q_to: ArrayLike
) -> NDArray[np.int8]:
    """The first non-zero :func:`collision_codes` along each straight joint move
    ``q_from[i] -> q_to[i]`` ``(N, n)`` rad (sampled at :data:`MOVE_SAMPLES` points)."""
    a = np.atleast_2d(np.asarray(q_from, dtype=float))
    b = np.atleast_2d(np.asarray(q_to, dtype=float))
    a, b = np.broadcast_arrays(a, b)
    n_pose = len(b)
    t = np.linspace(0.0, 1.0, MOVE_SAMPLES)[:, None, None]
    path = (a[None] + t * (b - a)[None]).reshape(-1, b.shape[1])
    codes = collision_codes(model, geometry, path).reshape(MOVE_SAMPLES, n_pose)
    first = np.argmax(codes != 0, axis=0)
    out: NDArray[np.int8] = codes[first, np.arange(n_pose)]
    return out


def geometry_document(spec: CellGeometrySpec) -> dict[str, Any]:
    """The tables of ``spec`` as a TOML document states them (keys left at their robot
    default omitted), so that reading it back gives ``spec``."""
    doc: dict[str, Any] = {}
    for key in ("station", "reflector", "floor", "arm", "region"):
        table = {k: v for k, v in asdict(getattr(spec, key)).items() if v is not None}
        doc[key] = {k: list(v) if isinstance(v, tuple) else v for k, v in table.items()}
    if spec.obstacles is not None:
        doc["obstacle"] = [
            {"name": o.name, "min_mm": list(o.min_mm), "max_mm": list(o.max_mm)}
            for o in spec.obstacles
        ]
    return doc
