"""Measurement files of the identification: campaign.csv, joints.csv, points.csv.

``campaign.csv``: ``pose,set,t_s,q1_deg..qN_deg,x_mm,y_mm,z_mm`` and optionally
``e1_deg..eN_deg`` (motor-encoder angles) and ``temp_c`` (a temperature at each pose, °C:
of the arm or the air, what drives thermal terms). ``set`` is ``identify`` or ``validate``; ``t_s``
is seconds since the start of the campaign; q are the grating joint angles (degrees); x, y, z
the tracker TCP target in the tracker frame (mm). Other columns are ignored.

``campaign_joints.csv`` (``twin plan``'s joint list, the emulated cell's ``[cell] plan``):
``pose,set,q1_deg..qN_deg``; its ``sweeps.csv`` (the planned scale-calibration sweeps):
``joint,stop,q1_deg..qN_deg,in_view,torque_nm``. ``joints.csv`` (input of ``twin predict``):
``pose,t_s,q1_deg..qN_deg``; other columns ignored. ``points.csv`` (its output):
``pose,x_mm,y_mm,z_mm``. ``targets.csv`` (input of ``twin compensate``) and ``loads.csv``
(a load test, ``twin stiffness``): see their readers.

A bad row (a value that is not a finite number, a joint outside its limits, a duplicated
pose id, too few fields, an unknown set) raises :class:`DataFileError` naming the file, the
line and the column, or with ``skip_bad=True`` is left out and recorded in ``skipped``. A
missing column is always an error: no row could be read without it.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import DataFileError
from edges.inputs import read_input_bytes

FloatArray = NDArray[np.float64]

#: Valid values of the ``set`` column.
SETS = ("identify", "validate")

JointLimits = Sequence[tuple[float, float]]  # per joint (lower_deg, upper_deg)


@dataclass(frozen=True)
class SkippedRow:
    """A row left out under ``skip_bad``: its line number, pose id (if readable), reason."""

    line: int
    pose: str | None
    reason: str

    def __str__(self) -> str:
        pose = f" (pose {self.pose!r})" if self.pose else ""
        return f"line {self.line}{pose}: {self.reason}"


@dataclass(frozen=True)
class Campaign:
    """The rows of a campaign.csv, arrays of length m (degrees, mm, seconds)."""

    source: str
    pose: tuple[str, ...]
    set: tuple[str, ...]
    t_s: FloatArray  # (m,)
    q_deg: FloatArray  # (m, n) grating joint angles
    xyz_mm: FloatArray  # (m, 3) tracker points
    encoder_deg: FloatArray | None = None  # (m, n) motor-encoder joint angles
    skipped: tuple[SkippedRow, ...] = ()
    temp_c: FloatArray | None = None  # (m,) °C, the optional temp_c column

    def __len__(self) -> int:
        return len(self.pose)

    @property
    def q_rad(self) -> FloatArray:
        return np.radians(self.q_deg)

    def mask(self, set_name: str) -> NDArray[np.bool_]:
        if set_name not in SETS:
            raise DataFileError(f"unknown set {set_name!r} (valid: {', '.join(SETS)})")
        return np.array([s == set_name for s in self.set], dtype=bool)

    def subset(self, mask: ArrayLike) -> Campaign:
        """The rows where ``mask`` ``(m,)`` is True (``skipped`` is kept)."""
        m = np.asarray(mask, dtype=bool)
        idx = np.flatnonzero(m)
        return replace(
            self,
            pose=tuple(self.pose[i] for i in idx),
            set=tuple(self.set[i] for i in idx),
            t_s=self.t_s[m],
            q_deg=self.q_deg[m],
            xyz_mm=self.xyz_mm[m],
            encoder_deg=None if self.encoder_deg is None else self.encoder_deg[m],
            temp_c=None if self.temp_c is None else self.temp_c[m],
        )


@dataclass(frozen=True)
class JointReadings:
    """The rows of a joints.csv: pose ids, times (s) and joint angles ``(m, n)`` degrees;
    the temperature ``(m,)`` °C when the file has a ``temp_c`` column."""

    source: str
    pose: tuple[str, ...]
    t_s: FloatArray
    q_deg: FloatArray
    skipped: tuple[SkippedRow, ...] = ()
    temp_c: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.pose)


def joint_columns(n_joints: int, prefix: str = "q") -> list[str]:
    return [f"{prefix}{i + 1}_deg" for i in range(n_joints)]


def campaign_columns(
    n_joints: int, *, encoders: bool = False, temperature: bool = False
) -> list[str]:
    cols = ["pose", "set", "t_s", *joint_columns(n_joints), "x_mm", "y_mm", "z_mm"]
    return (
        cols
        + (joint_columns(n_joints, "e") if encoders else [])
        + ([TEMPERATURE_COLUMN] if temperature else [])
    )


#: The optional temperature column (°C) of campaign.csv.
TEMPERATURE_COLUMN = "temp_c"
#: A ``temp_c`` value outside this range (°C) is refused: a cell's arm or air is not
#: there, and 200 °C and more reads as kelvin (20 °C is 293.15 K).
TEMPERATURE_RANGE_C = (-50.0, 100.0)


# -- reading ----------------------------------------------------------------------------
class _RowError(Exception):
    def __init__(self, column: str | None, message: str) -> None:
        super().__init__(message)
        self.column = column
        self.message = message


def _read_table(path: str | Path) -> tuple[str, list[str], list[tuple[int, list[str]]]]:
    """Header and (line number, fields) of every non-blank row of a CSV file."""
    source = str(path)
    raw = read_input_bytes(path, error=DataFileError)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise DataFileError(f"{source}: line {line}: not UTF-8 text (byte {exc.start})") from None
    if "\x00" in text:
        raise DataFileError(f"{source}: contains NUL bytes: not a CSV text file")
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    rows: list[tuple[int, list[str]]] = []
    header: list[str] | None = None
    try:
        for fields in reader:
            if not fields or all(not f.strip() for f in fields):
                continue
            if header is None:
                header = [f.strip() for f in fields]
                continue
            rows.append((reader.line_num, fields))
    except csv.Error as exc:
        raise DataFileError(f"{source}: line {reader.line_num}: not valid CSV: {exc}") from exc
    if header is None:
        raise DataFileError(f"{source}: empty file: expected a header line")
    seen: set[str] = set()
    for name in header:
        if name in seen:
            raise DataFileError(f"{source}: header: column {name!r} appears twice")
        seen.add(name)
    return source, header, rows


def _check_columns(source: str, header: list[str], required: list[str], n_joints: int) -> None:
    missing = [c for c in required if c not in header]
    if missing:
        raise DataFileError(
            f"{source}: header: missing column(s) {', '.join(missing)} "
            f"(expected {', '.join(required)})"
        )
    extra_joint = f"q{n_joints + 1}_deg"
    if extra_joint in header:
        raise DataFileError(
            f"{source}: header: column {extra_joint!r} but the robot has {n_joints} joints"
        )


def _number(fields: dict[str, str], column: str) -> float:
    text = fields[column].strip()
    try:
        value = float(text)
    except ValueError:
        raise _RowError(column, f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise _RowError(column, f"{text!r} is not a finite number")
    return value


def _temperature(fields: dict[str, str]) -> float:
    value = _number(fields, TEMPERATURE_COLUMN)
    lo, hi = TEMPERATURE_RANGE_C
    if not lo <= value <= hi:
        kelvin = " (kelvin? the column is in °C)" if value >= 200.0 else ""
        raise _RowError(
            TEMPERATURE_COLUMN, f"{value:g} is not a temperature in °C in [{lo:g}, {hi:g}]{kelvin}"
        )
    return value


def _joint_angles(
    fields: dict[str, str], columns: list[str], limits: JointLimits | None
) -> list[float]:
    values = [_number(fields, c) for c in columns]
    if limits is not None:
        for c, v, (lo, hi) in zip(columns, values, limits, strict=True):
            if not lo - 1e-9 <= v <= hi + 1e-9:
                raise _RowError(c, f"{v} deg outside the joint limits [{lo}, {hi}]")
    return values


def _parse_rows(
    source: str,
    header: list[str],
    rows: list[tuple[int, list[str]]],
    parse: Callable[[dict[str, str]], tuple[float | str | list[float], ...]],
    skip_bad: bool,
    id_column: str = "pose",
) -> tuple[list[str], list[tuple[float | str | list[float], ...]], list[SkippedRow]]:
    poses: list[str] = []
    values: list[tuple[float | str | list[float], ...]] = []
    skipped: list[SkippedRow] = []
    first_line: dict[str, int] = {}
    pose_col = header.index(id_column)
    for line, raw in rows:
        pose: str | None = raw[pose_col].strip() if len(raw) > pose_col else None
        try:
            if len(raw) < len(header):
                raise _RowError(None, f"{len(raw)} fields, the header has {len(header)}")
            fields = dict(zip(header, raw, strict=False))
            pose = fields[id_column].strip()
            if not pose:
                raise _RowError(id_column, f"empty {id_column} id")
            if pose in first_line:
                raise _RowError(
                    id_column, f"duplicated {id_column} id (first on line {first_line[pose]})"
                )
            parsed = parse(fields)
        except _RowError as exc:
            where = f"column '{exc.column}': " if exc.column else ""
            reason = f"{where}{exc.message}"
            if not skip_bad:
                label = f" ({id_column} {pose!r})" if pose else ""
                raise DataFileError(f"{source}: line {line}{label}: {reason}") from None
            skipped.append(SkippedRow(line, pose or None, reason))
            continue
        first_line[pose] = line
        poses.append(pose)
        values.append(parsed)
    if not poses:
        detail = f" ({len(skipped)} bad row(s) skipped)" if skipped else ""
        raise DataFileError(f"{source}: no valid data rows{detail}")
    return poses, values, skipped


def read_campaign(
    path: str | Path,
    n_joints: int,
    *,
    limits_deg: JointLimits | None = None,
    skip_bad: bool = False,
) -> Campaign:
    """Read a campaign.csv for an ``n_joints`` robot (joint limits checked when given)."""
    source, header, rows = _read_table(path)
    qcols = joint_columns(n_joints)
    _check_columns(source, header, campaign_columns(n_joints), n_joints)
    ecols = joint_columns(n_joints, "e")
    encoders = column_group(source, header, ecols, "encoder columns")
    has_temp = TEMPERATURE_COLUMN in header

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        set_name = f["set"].strip()
        if set_name not in SETS:
            raise _RowError("set", f"{set_name!r} is not one of {', '.join(SETS)}")
        t = _number(f, "t_s")
        q = _joint_angles(f, qcols, limits_deg)
        xyz = [_number(f, c) for c in ("x_mm", "y_mm", "z_mm")]
        enc = [_number(f, c) for c in ecols] if encoders else []
        temp = _temperature(f) if has_temp else math.nan
        return set_name, t, q, xyz, enc, temp

    poses, values, skipped = _parse_rows(source, header, rows, parse, skip_bad)
    return Campaign(
        source=source,
        pose=tuple(poses),
        set=tuple(str(v[0]) for v in values),
        t_s=np.array([v[1] for v in values], dtype=float),
        q_deg=np.array([v[2] for v in values], dtype=float).reshape(len(poses), n_joints),
        xyz_mm=np.array([v[3] for v in values], dtype=float).reshape(len(poses), 3),
        encoder_deg=(
            np.array([v[4] for v in values], dtype=float).reshape(len(poses), n_joints)
            if encoders
            else None
        ),
        skipped=tuple(skipped),
        temp_c=np.array([v[5] for v in values], dtype=float) if has_temp else None,
    )


def read_joint_readings(
    path: str | Path,
    n_joints: int,
    *,
    limits_deg: JointLimits | None = None,
    skip_bad: bool = False,
) -> JointReadings:
    """Read a joints.csv (``pose,t_s,q1_deg..qN_deg``, ``temp_c`` optional as in
    campaign.csv; other columns ignored)."""
    source, header, rows = _read_table(path)
    qcols = joint_columns(n_joints)
    _check_columns(source, header, ["pose", "t_s", *qcols], n_joints)
    has_temp = TEMPERATURE_COLUMN in header

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        temp = _temperature(f) if has_temp else math.nan
        return _number(f, "t_s"), _joint_angles(f, qcols, limits_deg), temp

    poses, values, skipped = _parse_rows(source, header, rows, parse, skip_bad)
    return JointReadings(
        source=source,
        pose=tuple(poses),
        t_s=np.array([v[0] for v in values], dtype=float),
        q_deg=np.array([v[1] for v in values], dtype=float).reshape(len(poses), n_joints),
        skipped=tuple(skipped),
        temp_c=np.array([v[2] for v in values], dtype=float) if has_temp else None,
    )


@dataclass(frozen=True)
class PlannedPoses:
    """The rows of a plan's ``campaign_joints.csv`` (``twin plan``): pose ids, sets and
    joint angles ``(m, n)`` degrees, in the file's (travel) order."""

    source: str
    pose: tuple[str, ...]
    set: tuple[str, ...]
    q_deg: FloatArray

    def of_set(self, set_name: str) -> FloatArray:
        """The angles ``(k, n)`` deg of one set, in the file's order."""
        return self.q_deg[[s == set_name for s in self.set]]


def read_planned_poses(
    path: str | Path, n_joints: int, *, limits_deg: JointLimits | None = None
) -> PlannedPoses:
    """Read a plan's ``campaign_joints.csv`` (``pose,set,q1_deg..qN_deg``; other columns
    ignored); a bad row is a :class:`DataFileError` naming the file, line and column."""
    source, header, rows = _read_table(path)
    qcols = joint_columns(n_joints)
    _check_columns(source, header, ["pose", "set", *qcols], n_joints)

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        set_name = f["set"].strip()
        if set_name not in SETS:
            raise _RowError("set", f"{set_name!r} is not one of {', '.join(SETS)}")
        return set_name, _joint_angles(f, qcols, limits_deg)

    poses, values, _ = _parse_rows(source, header, rows, parse, False)
    return PlannedPoses(
        source=source,
        pose=tuple(poses),
        set=tuple(str(v[0]) for v in values),
        q_deg=np.array([v[1] for v in values], dtype=float).reshape(len(poses), n_joints),
    )


@dataclass(frozen=True)
class PlannedSweeps:
    """The rows of a plan's ``sweeps.csv`` (``twin plan``): per swept joint (1-based, in
    the file's order) its forward pass's stops ``(K, n)`` deg from the upper limit down
    and whether each is in view ``(K,)``."""

    source: str
    q_deg: dict[int, FloatArray]
    in_view: dict[int, NDArray[np.bool_]]

    def whole(self, joint: int) -> bool:
        """Whether every stop of ``joint``'s sweep is in view."""
        return bool(self.in_view[joint].all())


def _integer(fields: dict[str, str], column: str) -> int:
    text = fields[column].strip()
    if not text.isdigit():
        raise _RowError(column, f"{text!r} is not a non-negative integer")
    return int(text)


def read_planned_sweeps(
    path: str | Path, n_joints: int, *, limits_deg: JointLimits | None = None
) -> PlannedSweeps:
    """Read a plan's ``sweeps.csv`` (``joint,stop,q1_deg..qN_deg,in_view``; ``torque_nm``
    and other columns ignored). Each joint's rows come together, stops numbered 0, 1, …,
    its angle decreasing and the other joints held (a sweep moves its joint alone); a bad
    row is a :class:`DataFileError` naming the file, line and column."""
    source, header, rows = _read_table(path)
    qcols = joint_columns(n_joints)
    _check_columns(source, header, ["joint", "stop", *qcols, "in_view"], n_joints)
    q_deg: dict[int, list[list[float]]] = {}
    in_view: dict[int, list[bool]] = {}
    last = 0
    for line, raw in rows:
        try:
            if len(raw) < len(header):
                raise _RowError(None, f"{len(raw)} fields, the header has {len(header)}")
            f = dict(zip(header, raw, strict=False))
            joint, stop = _integer(f, "joint"), _integer(f, "stop")
            if not 1 <= joint <= n_joints:
                raise _RowError("joint", f"joint {joint}: the robot has {n_joints} joints")
            if joint != last and joint in q_deg:
                raise _RowError("joint", f"joint {joint}'s rows do not come together")
            if stop != len(q_deg.get(joint, [])):
                raise _RowError("stop", f"stop {stop}, expected {len(q_deg.get(joint, []))}")
            q = _joint_angles(f, qcols, limits_deg)
            flag = f["in_view"].strip()
            if flag not in ("0", "1"):
                raise _RowError("in_view", f"{flag!r} is not 0 or 1")
            _check_sweep_stop(q, q_deg.get(joint, []), joint, qcols)
        except _RowError as exc:
            where = f"column '{exc.column}': " if exc.column else ""
            raise DataFileError(f"{source}: line {line}: {where}{exc.message}") from None
        last = joint
        q_deg.setdefault(joint, []).append(q)
        in_view.setdefault(joint, []).append(flag == "1")
    if not q_deg:
        raise DataFileError(f"{source}: no valid data rows")
    return PlannedSweeps(
        source,
        {j: np.array(v, dtype=float) for j, v in q_deg.items()},
        {j: np.array(v, dtype=bool) for j, v in in_view.items()},
    )


def _check_sweep_stop(
    q: list[float], before: list[list[float]], joint: int, qcols: list[str]
) -> None:
    """A stop after the first moves the swept joint down and no other joint."""
    if not before:
        return
    first, prev = before[0], before[-1]
    if not q[joint - 1] < prev[joint - 1]:
        raise _RowError(
            qcols[joint - 1],
            f"{q[joint - 1]} deg not below the previous stop's {prev[joint - 1]} "
            "(the sweep runs from the upper limit down)",
        )
    for k, (a, b) in enumerate(zip(q, first, strict=True)):
        if k != joint - 1 and abs(a - b) > 1e-6:
            raise _RowError(
                qcols[k],
                f"{a} deg, the sweep's first stop {b}: a sweep of joint {joint} moves it alone",
            )


@dataclass(frozen=True)
class Targets:
    """The rows of a targets.csv (``twin compensate``): ids, positions ``(m, 3)`` mm in
    the tracker frame, and either programmed joints ``(m, n)`` deg or orientations
    ``(m, 3)`` deg (fixed-axis X-Y-Z), optional times ``(m,)`` s."""

    source: str
    target: tuple[str, ...]
    xyz_mm: FloatArray
    q_deg: FloatArray | None
    rpy_deg: FloatArray | None
    t_s: FloatArray | None
    lines: tuple[int, ...]
    force_n: FloatArray | None = None  # (m, 3) N: a process force on the tool
    temp_c: FloatArray | None = None  # (m,) °C: the arm's temperature (``temp_c``)


#: A process force on the tool, N in the tracker frame (targets.csv, loads.csv).
FORCE_COLUMNS = ["fx_n", "fy_n", "fz_n"]


#: A tool orientation, fixed-axis X-Y-Z degrees (targets.csv).
ORIENTATION_COLUMNS = ["rx_deg", "ry_deg", "rz_deg"]


def column_group(source: str, header: Sequence[str], columns: Sequence[str], what: str) -> bool:
    """Whether the header has the optional column group ``columns`` (all or none: one
    rule for every group). Some but not all is refused, naming the missing columns: a
    group read in part would be ignored or misread without a word."""
    present = [c for c in columns if c in header]
    if 0 < len(present) < len(columns):
        missing = [c for c in columns if c not in header]
        raise DataFileError(
            f"{source}: header: {what} incomplete: all of {','.join(columns)} or none; "
            f"{','.join(present)} given, missing {', '.join(missing)}"
        )
    return bool(present)


def _force_columns(source: str, header: list[str]) -> bool:
    """Whether the header has the force columns (all three or none)."""
    return column_group(source, header, FORCE_COLUMNS, "force columns")


def read_targets(
    path: str | Path, n_joints: int, *, limits_deg: JointLimits | None = None
) -> Targets:
    """Read a targets.csv: ``target,x_mm,y_mm,z_mm`` and ``q1_deg..qN_deg`` or
    ``rx_deg,ry_deg,rz_deg`` (``t_s``, ``temp_c`` and ``fx_n,fy_n,fz_n`` optional; other
    columns ignored)."""
    source, header, rows = _read_table(path)
    xyz = ["x_mm", "y_mm", "z_mm"]
    qcols, rcols = joint_columns(n_joints), ORIENTATION_COLUMNS
    missing = [c for c in ["target", *xyz] if c not in header]
    has_q = column_group(source, header, qcols, "joint columns")
    has_r = column_group(source, header, rcols, "orientation columns")
    if missing or has_q == has_r:
        what = "both" if has_q and has_r else "neither"
        raise DataFileError(
            f"{source}: header: need target,x_mm,y_mm,z_mm and either {qcols[0]}..{qcols[-1]} "
            f"or rx_deg,ry_deg,rz_deg"
            + (f" (missing {', '.join(missing)})" if missing else f" ({what} given)")
        )
    has_t = "t_s" in header
    has_temp = TEMPERATURE_COLUMN in header
    has_f = _force_columns(source, header)

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        p = [_number(f, c) for c in xyz]
        o = _joint_angles(f, qcols, limits_deg) if has_q else [_number(f, c) for c in rcols]
        force = [_number(f, c) for c in FORCE_COLUMNS] if has_f else []
        temp = _temperature(f) if has_temp else math.nan
        return p, o, (_number(f, "t_s") if has_t else math.nan), force, temp

    ids, values, _ = _parse_rows(source, header, rows, parse, False, id_column="target")
    m = len(ids)
    orient = np.array([v[1] for v in values], dtype=float).reshape(m, -1)
    return Targets(
        source=source,
        target=tuple(ids),
        xyz_mm=np.array([v[0] for v in values], dtype=float).reshape(m, 3),
        q_deg=orient if has_q else None,
        rpy_deg=None if has_q else orient,
        t_s=np.array([v[2] for v in values], dtype=float) if has_t else None,
        lines=tuple(line for line, _ in rows),
        force_n=np.array([v[3] for v in values], dtype=float).reshape(m, 3) if has_f else None,
        temp_c=np.array([v[4] for v in values], dtype=float) if has_temp else None,
    )


def read_poses(
    path: str | Path, n_joints: int, *, limits_deg: JointLimits | None = None
) -> JointReadings:
    """Read joints to evaluate at: an id column (``pose``, or ``target`` as in the
    joints.csv of ``twin compensate``) and ``q1_deg..qN_deg``; ``t_s`` optional (NaN)."""
    source, header, rows = _read_table(path)
    id_column = next((c for c in ("pose", "target") if c in header), "pose")
    qcols = joint_columns(n_joints)
    _check_columns(source, header, [id_column, *qcols], n_joints)
    has_t = "t_s" in header

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        return (_number(f, "t_s") if has_t else math.nan), _joint_angles(f, qcols, limits_deg)

    ids, values, _ = _parse_rows(source, header, rows, parse, False, id_column=id_column)
    return JointReadings(
        source=source,
        pose=tuple(ids),
        t_s=np.array([v[0] for v in values], dtype=float),
        q_deg=np.array([v[1] for v in values], dtype=float).reshape(len(ids), n_joints),
    )


@dataclass(frozen=True)
class LoadTestRows:
    """The rows of a loads.csv: ids, poses ``(m, n)`` deg, forces ``(m, 3)`` N and the
    tracker's TCP unloaded and loaded ``(m, 3)`` mm (tracker frame)."""

    source: str
    load: tuple[str, ...]
    q_deg: FloatArray
    force_n: FloatArray
    unloaded_mm: FloatArray
    loaded_mm: FloatArray


LOAD_TEST_POINTS = (["x0_mm", "y0_mm", "z0_mm"], ["x_mm", "y_mm", "z_mm"])


def read_load_test(
    path: str | Path, n_joints: int, *, limits_deg: JointLimits | None = None
) -> LoadTestRows:
    """Read a loads.csv: ``load`` (id), ``q1_deg..qN_deg``, ``fx_n,fy_n,fz_n`` (the force
    on the tool), ``x0_mm,y0_mm,z0_mm`` (the TCP unloaded) and ``x_mm,y_mm,z_mm`` (loaded)."""
    source, header, rows = _read_table(path)
    qcols = joint_columns(n_joints)
    unloaded, loaded = LOAD_TEST_POINTS
    _check_columns(source, header, ["load", *qcols, *FORCE_COLUMNS, *unloaded, *loaded], n_joints)

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        return (
            _joint_angles(f, qcols, limits_deg),
            [_number(f, c) for c in FORCE_COLUMNS],
            [_number(f, c) for c in unloaded],
            [_number(f, c) for c in loaded],
        )

    ids, values, _ = _parse_rows(source, header, rows, parse, False, id_column="load")
    m = len(ids)

    def column(k: int, width: int) -> FloatArray:
        return np.array([v[k] for v in values], dtype=float).reshape(m, width)

    return LoadTestRows(
        source, tuple(ids), column(0, n_joints), column(1, 3), column(2, 3), column(3, 3)
    )


def read_points(path: str | Path) -> tuple[tuple[str, ...], FloatArray]:
    """Read a points.csv: pose ids and ``(m, 3)`` mm."""
    source, header, rows = _read_table(path)
    cols = ["pose", "x_mm", "y_mm", "z_mm"]
    missing = [c for c in cols if c not in header]
    if missing:
        raise DataFileError(f"{source}: header: missing column(s) {', '.join(missing)}")

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        return ([_number(f, c) for c in cols[1:]],)

    poses, values, _ = _parse_rows(source, header, rows, parse, False)
    return tuple(poses), np.array([v[0] for v in values], dtype=float).reshape(-1, 3)


# -- writing ----------------------------------------------------------------------------
def _fmt(v: float, digits: int) -> str:
    return f"{v:.{digits}f}" if math.isfinite(v) else "nan"


def write_campaign(path: str | Path, campaign: Campaign) -> None:
    """Write a campaign.csv (degrees to 1e-9, mm to 1 nm, seconds to 1 ms, °C to 1e-4)."""
    n = campaign.q_deg.shape[1]
    encoders = campaign.encoder_deg is not None
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(campaign_columns(n, encoders=encoders, temperature=campaign.temp_c is not None))
        for i, pose in enumerate(campaign.pose):
            row = [pose, campaign.set[i], _fmt(campaign.t_s[i], 3)]
            row += [_fmt(v, 9) for v in campaign.q_deg[i]]
            row += [_fmt(v, 6) for v in campaign.xyz_mm[i]]
            if campaign.encoder_deg is not None:
                row += [_fmt(v, 9) for v in campaign.encoder_deg[i]]
            if campaign.temp_c is not None:
                row.append(_fmt(campaign.temp_c[i], 4))
            w.writerow(row)


def write_joint_readings(path: str | Path, readings: JointReadings) -> None:
    n = readings.q_deg.shape[1]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["pose", "t_s", *joint_columns(n)])
        for i, pose in enumerate(readings.pose):
            w.writerow([pose, _fmt(readings.t_s[i], 3), *(_fmt(v, 9) for v in readings.q_deg[i])])


def write_points(
    path: str | Path,
    pose: Sequence[str],
    xyz_mm: ArrayLike,
    sd_mm: ArrayLike | None = None,
    beyond_reach: ArrayLike | None = None,
) -> None:
    """Write a points.csv: ``pose,x_mm,y_mm,z_mm`` (mm to 1 nm); with ``sd_mm`` ``(m,)``
    also ``sd_mm`` (per axis, empty where unknown) and ``beyond_reach`` (1: the learned
    residual stage did not apply, outside its data's reach)."""
    xyz = np.asarray(xyz_mm, dtype=float).reshape(-1, 3)
    m = len(xyz)
    sd = None if sd_mm is None else np.broadcast_to(np.asarray(sd_mm, dtype=float), (m,))
    far = np.zeros(m, dtype=bool) if beyond_reach is None else np.asarray(beyond_reach, bool)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(
            ["pose", "x_mm", "y_mm", "z_mm", *(["sd_mm", "beyond_reach"] if sd is not None else [])]
        )
        for i, (p, row) in enumerate(zip(pose, xyz, strict=True)):
            extra = [] if sd is None else ["" if np.isnan(sd[i]) else _fmt(sd[i], 6), int(far[i])]
            w.writerow([p, *(_fmt(v, 6) for v in row), *extra])


@dataclass(frozen=True)
class Checks:
    """The rows of a checks.csv (``twin track``'s input): production checks in time order,
    arrays of length m (seconds on the calibration campaign's clock, degrees, mm)."""

    source: str
    pose: tuple[str, ...]
    t_s: FloatArray  # (m,) strictly increasing
    q_deg: FloatArray  # (m, n)
    xyz_mm: FloatArray  # (m, 3)
    temp_c: FloatArray | None = None  # (m,) °C, the optional temp_c column

    def __len__(self) -> int:
        return len(self.pose)


def read_checks(
    path: str | Path, n_joints: int, *, limits_deg: JointLimits | None = None
) -> Checks:
    """Read a checks.csv: campaign.csv's columns, ``set`` optional and ignored, ``t_s``
    required and strictly increasing (a row out of time order or at a repeated time is
    refused, naming both rows)."""
    source, header, rows = _read_table(path)
    qcols = joint_columns(n_joints)
    _check_columns(source, header, ["pose", "t_s", *qcols, "x_mm", "y_mm", "z_mm"], n_joints)
    has_temp = TEMPERATURE_COLUMN in header

    def parse(f: dict[str, str]) -> tuple[float | str | list[float], ...]:
        xyz = [_number(f, c) for c in ("x_mm", "y_mm", "z_mm")]
        temp = _temperature(f) if has_temp else math.nan
        return _number(f, "t_s"), _joint_angles(f, qcols, limits_deg), xyz, temp

    poses, values, _ = _parse_rows(source, header, rows, parse, skip_bad=False)
    t_s = np.array([v[0] for v in values], dtype=float)
    lines = [line for line, _ in rows]
    for k in np.flatnonzero(np.diff(t_s) <= 0.0):
        what = "repeats the time of" if t_s[k + 1] == t_s[k] else "is earlier than"
        raise DataFileError(
            f"{source}: line {lines[k + 1]} (pose {poses[k + 1]!r}): column 't_s': "
            f"{t_s[k + 1]:g} s {what} the row before it (pose {poses[k]!r}, {t_s[k]:g} s); "
            "checks must be in strictly increasing time order"
        )
    return Checks(
        source=source,
        pose=tuple(poses),
        t_s=t_s,
        q_deg=np.array([v[1] for v in values], dtype=float).reshape(len(poses), n_joints),
        xyz_mm=np.array([v[2] for v in values], dtype=float).reshape(len(poses), 3),
        temp_c=np.array([v[3] for v in values], dtype=float) if has_temp else None,
    )
