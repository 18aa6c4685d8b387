"""Files of the grating-scale calibration: the campaign's CSVs and ``scale.toml``.

CSV files have a header row; rows are numbered as lines in the file (the header is row 1)
and every error names the file, the row and the column:

* ``sweep.csv``: ``joint,pass,step,counts,x_mm,y_mm,z_mm``. ``joint`` 1..n, ``pass``
  ``forward`` (positive limit → negative limit) or ``backward``, ``step`` the stop index
  from the start of the pass (0, 1, ...), ``counts`` the raw grating reading (integer,
  32-bit counter; negative values are taken as signed 32-bit), x, y, z the tracker target
  (mm, tracker frame). Optional ``g1_counts..gN_counts``: every joint's raw reading at
  the stop (all N or none; the swept joint's equals ``counts``), for taking the other
  joints' motion out through the kinematic chain. Optional ``target``: which reflector
  (1, 2, ...) when the tracker measures several on the swept link, one row per stop and
  target (the readings repeat); each stop's angle then comes from the rigid rotation of
  the target set. Without it, one target.
* ``home.csv``: ``joint,trial,counts``.
* ``counts.csv`` (for ``twin scale-apply``): ``joint,counts`` and optionally
  ``direction`` (``positive``/``negative``/``unknown``, or ``backward``/``forward`` as in
  the sweep); other columns pass through.

``scale.toml`` holds, per joint, everything :class:`~calibration.scales.scale_relation.GratingScale`
needs (units in key names); see docs/scale-calibration.md.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
from numpy.typing import ArrayLike, NDArray

from calibration.errors import CalibrationError, DataFileError, ScaleFileError
from calibration.scales.joint_scale_result import JointScaleResult
from calibration.scales.scale_relation import (
    COUNTER_MODULUS,
    DIRECTIONS,
    SCALE_NAME,
    TERMS,
    GratingScale,
    RelationBasis,
    UnmodelledTerm,
    check_terms,
)
from calibration.scales.sweep_inputs import MIN_STOPS_PER_PASS, PASSES, JointSweep
from edges.inputs import read_input_bytes
from edges.toml_schema import TomlTable, parse_toml_file

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

SWEEP_COLUMNS: tuple[str, ...] = ("joint", "pass", "step", "counts", "x_mm", "y_mm", "z_mm")
#: Optional sweep.csv columns: every joint's reading at the stop, g1_counts..gN_counts.
MAX_CHAIN_JOINTS = 32
CHAIN_COLUMNS: tuple[str, ...] = tuple(f"g{i}_counts" for i in range(1, MAX_CHAIN_JOINTS + 1))
HOME_COLUMNS: tuple[str, ...] = ("joint", "trial", "counts")
COUNTS_COLUMNS: tuple[str, ...] = ("joint", "counts")
SCALE_FORMAT = "twin-grating-scale/1"
ANGLE_CONVENTION = (
    "angle_deg is the joint rotation from Home (where the joint sits at zero_counts), "
    "positive in the joint's positive direction; the robot description's joint angle is "
    "q_deg = home_deg + angle_deg"
)

_INTEGER = re.compile(r"^[+-]?[0-9]+$")


# -- CSV ----------------------------------------------------------------------------------
@dataclass
class _Csv:
    """A parsed CSV with its header; every error names file, row and column."""

    path: str
    header: list[str]
    rows: list[tuple[int, list[str]]]  # (line number, fields)
    index: dict[str, int] = field(default_factory=dict)

    def fail(self, row: int | str, column: str | None, message: str) -> DataFileError:
        plural = isinstance(row, str) and "-" in row
        where = f"{self.path}: {'rows' if plural else 'row'} {row}"
        if column is not None:
            where += f", column '{column}'"
            if column in self.index:
                where += f" ({self.index[column] + 1})"
        return DataFileError(f"{where}: {message}")

    def value(self, line: int, fields: list[str], column: str) -> str:
        return fields[self.index[column]].strip()

    def integer(
        self, line: int, fields: list[str], column: str, *, minimum: int | None = None
    ) -> int:
        text = self.value(line, fields, column)
        if not _INTEGER.match(text):
            kind = "NaN" if text.lower() in {"nan", "+nan", "-nan"} else repr(text)
            raise self.fail(line, column, f"expected an integer, got {kind}")
        number = int(text)
        if minimum is not None and number < minimum:
            raise self.fail(line, column, f"must be ≥ {minimum}, got {number}")
        return number

    def counts(self, line: int, fields: list[str], column: str = "counts") -> int:
        number = self.integer(line, fields, column)
        if not -(2**31) <= number < COUNTER_MODULUS:
            raise self.fail(line, column, f"{number} is not a 32-bit counter value")
        return number % COUNTER_MODULUS

    def real(self, line: int, fields: list[str], column: str) -> float:
        text = self.value(line, fields, column)
        try:
            number = float(text)
        except ValueError:
            raise self.fail(line, column, f"expected a number, got {text!r}") from None
        if not math.isfinite(number):
            raise self.fail(line, column, f"must be finite, got {text!r}")
        return number

    def joint(self, line: int, fields: list[str], n_joints: int | None) -> int:
        j = self.integer(line, fields, "joint")
        if j < 1 or (n_joints is not None and j > n_joints):
            known = f"joints 1..{n_joints}" if n_joints is not None else "joints from 1"
            raise self.fail(line, "joint", f"unknown joint {j} (the robot has {known})")
        return j


def _read_csv(
    path: str | Path,
    required: Sequence[str],
    *,
    optional: Sequence[str] = (),
    extra_allowed: bool = False,
) -> _Csv:
    name = str(path)
    raw = read_input_bytes(path, error=DataFileError)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        row = raw[: exc.start].count(b"\n") + 1
        raise DataFileError(f"{name}: row {row}: not UTF-8 text (byte {exc.start})") from None
    if "\x00" in text:
        row = text[: text.index("\x00")].count("\n") + 1
        raise DataFileError(f"{name}: row {row}: contains NUL bytes: not a CSV text file")
    return parse_csv_text(text, name, required, optional=optional, extra_allowed=extra_allowed)


def parse_csv_text(
    text: str,
    name: str,
    required: Sequence[str],
    *,
    optional: Sequence[str] = (),
    extra_allowed: bool = False,
) -> _Csv:
    """Parse CSV text and check its header (the readers' common part)."""
    expected = ",".join(required)
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    rows: list[tuple[int, list[str]]] = []
    header: list[str] | None = None
    header_line = 1
    try:
        for fields in reader:
            if not fields or all(not f.strip() for f in fields):
                continue
            if header is None:
                header, header_line = [f.strip() for f in fields], reader.line_num
            else:
                rows.append((reader.line_num, fields))
    except csv.Error as exc:
        raise DataFileError(f"{name}: row {reader.line_num}: not valid CSV: {exc}") from exc
    if header is None:
        raise DataFileError(f"{name}: row 1: empty file, expected the header '{expected}'")
    table = _Csv(name, header, rows, {h: i for i, h in enumerate(header)})
    seen: dict[str, int] = {}
    for i, h in enumerate(header):
        if not h:
            raise table.fail(header_line, f"#{i + 1}", f"empty column name (expected '{expected}')")
        if h in seen:
            raise table.fail(header_line, h, f"column given twice (columns {seen[h] + 1}, {i + 1})")
        seen[h] = i
    for col in required:
        if col not in table.index:
            raise table.fail(
                header_line,
                col,
                f"missing from the header '{','.join(header)}' (expected '{expected}')",
            )
    if not extra_allowed:
        allowed = set(required) | set(optional)
        for h in header:
            if h not in allowed:
                raise table.fail(header_line, h, f"unknown column (expected '{expected}')")
    for line, fields in rows:
        if len(fields) != len(header):
            raise table.fail(line, None, f"expected {len(header)} fields, got {len(fields)}")
    return table


@dataclass(frozen=True, eq=False)
class HomeTable:
    """Home returns per joint: raw counts ``(H,)`` and their file rows."""

    path: str
    counts: Mapping[int, IntArray]
    rows: Mapping[int, IntArray]


@dataclass(frozen=True, eq=False)
class SweepTable:
    """Sweep stops per joint, and the file they came from."""

    path: str
    joints: Mapping[int, JointSweep]


def read_sweep_csv(
    path: str | Path,
    *,
    n_joints: int | None = None,
    min_stops_per_pass: int = MIN_STOPS_PER_PASS,
) -> SweepTable:
    """Read ``sweep.csv``; raises :class:`DataFileError` naming file, row and column."""
    t = _read_csv(path, SWEEP_COLUMNS, optional=(*CHAIN_COLUMNS, "target"))
    if not t.rows:
        raise DataFileError(f"{t.path}: row 2: no data rows after the header")
    chain_columns = _chain_columns(t, n_joints)
    has_target = "target" in t.index
    stops = _SweepStops(has_target)
    parsed = []
    for line, f in t.rows:
        row = _sweep_row(t, line, f, n_joints, chain_columns, has_target)
        stops.check(t, row)
        parsed.append(row)
    joint = np.array([r.joint for r in parsed], dtype=np.int64)
    step = np.array([r.step for r in parsed], dtype=np.int64)
    counts = np.array([r.counts for r in parsed], dtype=np.int64)
    xyz = np.array([r.xyz_mm for r in parsed], dtype=float)
    pass_name = np.array([r.pass_name for r in parsed], dtype=object).astype(str)
    lines = np.array([r.line for r in parsed], dtype=np.int64)
    target = np.array([r.target for r in parsed], dtype=np.int64)
    chain = np.array([r.chain for r in parsed], dtype=np.int64).reshape(len(parsed), -1)
    joints = {}
    for j in sorted(set(joint.tolist())):
        m = joint == j
        _check_pass_sizes(t, j, step, pass_name, lines, m, min_stops_per_pass)
        joints[j] = JointSweep(
            joint=j,
            pass_name=pass_name[m],
            step=step[m],
            counts=counts[m],
            points_mm=xyz[m],
            rows=lines[m],
            chain_counts=chain[m] if chain_columns else None,
            target=target[m] if has_target else None,
        )
    return SweepTable(t.path, joints)


@dataclass(frozen=True)
class _SweepRow:
    """One row of sweep.csv, read and checked."""

    line: int
    joint: int
    pass_name: str
    step: int
    counts: int
    xyz_mm: tuple[float, float, float]
    chain: tuple[int, ...]  # g1_counts..gN_counts (empty without them)
    target: int  # 1 without a target column


def _sweep_row(
    t: _Csv,
    line: int,
    f: list[str],
    n_joints: int | None,
    chain_columns: tuple[str, ...],
    has_target: bool,
) -> _SweepRow:
    joint = t.joint(line, f, n_joints)
    p = t.value(line, f, "pass")
    if p not in PASSES:
        raise t.fail(line, "pass", f"expected one of {', '.join(PASSES)}, got {p!r}")
    step = t.integer(line, f, "step", minimum=0)
    counts = t.counts(line, f)
    x, y, z = (t.real(line, f, c) for c in ("x_mm", "y_mm", "z_mm"))
    chain: tuple[int, ...] = ()
    if chain_columns:
        chain = tuple(t.counts(line, f, c) for c in chain_columns)
        own = chain_columns[joint - 1] if joint <= len(chain_columns) else None
        if own is None:
            raise t.fail(line, "joint", f"joint {joint} has no g{joint}_counts column")
        if chain[joint - 1] != counts:
            raise t.fail(line, own, f"differs from 'counts' ({chain[joint - 1]} != {counts})")
    target = t.integer(line, f, "target", minimum=1) if has_target else 1
    return _SweepRow(line, joint, p, step, counts, (x, y, z), chain, target)


@dataclass(frozen=True)
class _SweepStops:
    """The stops seen so far: each (joint, pass, step, target) once, and the targets of a
    stop with the same reading."""

    has_target: bool
    first: dict[tuple[int, str, int, int], int] = field(default_factory=dict)
    counts: dict[tuple[int, str, int], tuple[int, int]] = field(default_factory=dict)

    def check(self, t: _Csv, row: _SweepRow) -> None:
        line, p = row.line, row.pass_name
        key = (row.joint, p, row.step, row.target)
        if key in self.first:
            what = f" target {key[3]}" if self.has_target else ""
            raise t.fail(
                line,
                "step",
                f"joint {key[0]} {p} step {key[2]}{what} already given in row {self.first[key]}",
            )
        self.first[key] = line
        seen = self.counts.setdefault(key[:3], (row.counts, line))
        if seen[0] != row.counts:
            raise t.fail(
                line, "counts", f"differs from the same stop's reading in row {seen[1]} "
                f"({row.counts} != {seen[0]}): the targets of a stop share its readings"
            )  # fmt: skip


def _check_pass_sizes(
    t: _Csv,
    j: int,
    step: IntArray,
    pass_name: NDArray[np.str_],
    lines: IntArray,
    m: NDArray[np.bool_],
    min_stops_per_pass: int,
) -> None:
    """Each pass of joint ``j`` (its rows ``m``) has none or enough stops."""
    for p in PASSES:
        mp = m & (pass_name == p)
        n_stops = len(set(step[mp].tolist()))
        if 0 < n_stops < min_stops_per_pass:
            raise t.fail(
                _row_span(lines[mp]),
                "step",
                f"joint {j} {p} sweep has {n_stops} stops; a circle fit and the "
                f"relation need at least {min_stops_per_pass}",
            )


def _chain_columns(t: _Csv, n_joints: int | None) -> tuple[str, ...]:
    """The ``g1_counts..gN_counts`` columns present: none, or exactly 1..N (N the robot's)."""
    present = [c for c in CHAIN_COLUMNS if c in t.index]
    if not present:
        return ()
    n = len(present)
    expected = CHAIN_COLUMNS[:n]
    if tuple(present) != expected or (n_joints is not None and n != n_joints):
        want = n_joints if n_joints is not None else n
        raise t.fail(
            1,
            present[0] if tuple(present) == expected else present[-1],
            f"expected every joint's reading g1_counts..g{want}_counts or none, got "
            f"{', '.join(present)}",
        )
    return expected


def _row_span(rows: NDArray[np.int64]) -> str:
    return f"{rows.min()}" if rows.min() == rows.max() else f"{rows.min()}-{rows.max()}"


def read_home_csv(path: str | Path, *, n_joints: int | None = None) -> HomeTable:
    """Read ``home.csv`` (may have no data rows); errors name file, row and column."""
    t = _read_csv(path, HOME_COLUMNS)
    per_joint: dict[int, list[tuple[int, int]]] = {}
    seen: dict[tuple[int, int], int] = {}
    for line, f in t.rows:
        j = t.joint(line, f, n_joints)
        trial = t.integer(line, f, "trial")
        if (j, trial) in seen:
            raise t.fail(
                line, "trial", f"joint {j} trial {trial} already given in row {seen[j, trial]}"
            )
        seen[j, trial] = line
        per_joint.setdefault(j, []).append((t.counts(line, f), line))
    return HomeTable(
        t.path,
        {j: np.array([c for c, _ in v], dtype=np.int64) for j, v in per_joint.items()},
        {j: np.array([r for _, r in v], dtype=np.int64) for j, v in per_joint.items()},
    )


@dataclass(frozen=True, eq=False)
class CountsTable:
    """``counts.csv`` for ``scale-apply``: rows kept as text for pass-through."""

    path: str
    header: list[str]
    rows: list[list[str]]
    lines: IntArray  # (N,) file rows
    joint: IntArray  # (N,)
    counts: IntArray  # (N,) raw, wrapped to [0, 2³²)
    direction: FloatArray | None  # (N,) +1 / −1 / 0, or None without the column


def read_counts_csv(path: str | Path) -> CountsTable:
    """Read ``counts.csv``: ``joint,counts`` [``direction``] plus any pass-through columns."""
    t = _read_csv(path, COUNTS_COLUMNS, extra_allowed=True)
    n = len(t.rows)
    joint = np.empty(n, dtype=np.int64)
    counts = np.empty(n, dtype=np.int64)
    has_direction = "direction" in t.index
    direction = np.zeros(n) if has_direction else None
    if n == 0:
        raise t.fail(2, None, "no data rows (only the header)")
    for k, (line, f) in enumerate(t.rows):
        joint[k] = t.joint(line, f, None)
        counts[k] = t.counts(line, f)
        if direction is not None:
            d = t.value(line, f, "direction").lower()
            if d not in DIRECTIONS:
                known = ", ".join(k for k in DIRECTIONS if k)
                raise t.fail(line, "direction", f"expected one of {known} or empty, got {d!r}")
            direction[k] = DIRECTIONS[d]
    return CountsTable(
        t.path,
        t.header,
        [f for _, f in t.rows],
        np.array([line for line, _ in t.rows], dtype=np.int64),
        joint,
        counts,
        direction,
    )


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    with Path(path).open("w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


# -- scale.toml ------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ScaleCalibration:
    """All calibrated joints of one robot: what ``scale.toml`` holds."""

    joints: Mapping[int, GratingScale]
    robot: str | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    #: per joint, the angles relative to Home (deg) its sweep stops covered, when the
    #: file says (``calibrated_range_deg``; files before it do not)
    ranges_deg: Mapping[int, tuple[float, float]] = field(default_factory=dict)

    def scale(self, joint: int) -> GratingScale:
        if joint not in self.joints:
            raise ScaleFileError(
                f"joint {joint} is not calibrated (calibrated: {_joint_list(self.joints)})"
            )
        return self.joints[joint]

    def angles_deg(
        self, joint: NDArray[np.int64], counts: ArrayLike, direction: ArrayLike | None = None
    ) -> FloatArray:
        """Angles relative to Home (deg) for rows of (joint, counts[, direction]), ``(N,)``."""
        joint = np.asarray(joint)
        out = np.empty(joint.shape)
        for j in np.unique(joint):
            m = joint == j
            d = None if direction is None else np.asarray(direction)[m]
            out[m] = self.scale(int(j)).counts_to_angle_deg(np.asarray(counts)[m], d)
        return out


def _joint_list(joints: Mapping[int, Any]) -> str:
    return ", ".join(str(j) for j in sorted(joints)) or "none"


def _matrix(a: FloatArray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.atleast_2d(a)]


def scale_document(
    results: Sequence[JointScaleResult],
    *,
    robot: str | None = None,
    metadata: Mapping[str, Any] | None = None,
    counts_per_mm: float = 1000.0,
) -> dict[str, Any]:
    """The ``scale.toml`` document of calibrated joints (plain TOML types)."""
    doc: dict[str, Any] = {"format": SCALE_FORMAT, "angle_convention": ANGLE_CONVENTION}
    if robot:
        doc["robot"] = robot
    doc["counter_modulus"] = COUNTER_MODULUS
    doc["counts_per_mm"] = counts_per_mm
    if metadata:
        doc["calibration"] = dict(metadata)
    doc["joint"] = [_joint_table(r, counts_per_mm) for r in results]
    return doc


def _joint_table(r: JointScaleResult, counts_per_mm: float) -> dict[str, Any]:
    s = r.scale
    table: dict[str, Any] = {"joint": r.joint}
    if s.home_deg is not None:
        table["home_deg"] = s.home_deg
    used = r.stop_angle_deg[r.used]
    if used.size:
        table["calibrated_range_deg"] = [float(used.min()), float(used.max())]
    table.update(
        zero_counts=s.zero_counts,
        zero_std_counts=s.zero_std_counts,
        terms=list(s.terms),
        phase_rad_per_count=s.basis.phase_rad_per_count,
        nonlinear_centre_counts=s.basis.nonlinear_centre_counts,
        nonlinear_half_span_counts=s.basis.nonlinear_half_span_counts,
        coefficients=dict(s.coefficients),
        covariance={"names": list(s.coefficients), "deg2": _matrix(s.covariance_deg2)},
        summary={  # for people: not read back
            "zero_source": r.home.source,
            "zero_spread_counts": r.home.spread_counts,
            "zero_readings": r.home.n,
            "counts_per_deg": s.counts_per_deg,
            "effective_radius_mm": s.effective_radius_mm(counts_per_mm),
            "strip_direction": r.strip_direction,
            "hysteresis_counts": s.hysteresis_counts,
            "residual_rms_arcsec": r.residual_rms_arcsec,
            "stops_used": int(r.used.sum()),
            "stops_dropped": len(r.dropped),
        },
    )
    if s.unmodelled:
        table["unmodelled"] = {
            term: {
                "p_value": un.p_value,
                "delta": dict(un.delta),
                "delta_covariance_deg2": _matrix(un.delta_covariance_deg2),
            }
            for term, un in s.unmodelled.items()
        }
    return table


def write_scale_toml(path: str | Path, document: Mapping[str, Any]) -> None:
    header = (
        "# Grating-scale calibration written by `twin scale` (docs/scale-calibration.md).\n"
        "# angle_deg(counts) relative to Home; joint angle q_deg = home_deg + angle_deg.\n"
    )
    Path(path).write_text(header + tomli_w.dumps(dict(document)), encoding="utf-8")


def read_scale_toml(path: str | Path) -> ScaleCalibration:
    """Read ``scale.toml``; raises :class:`ScaleFileError` naming file, table and key."""
    source = str(path)
    doc = parse_toml_file(path, ScaleFileError, "a scale calibration")
    top = TomlTable(doc, source, "top level", ScaleFileError)
    if top.get("format") != SCALE_FORMAT:
        raise top.fail("format", f"expected {SCALE_FORMAT!r}, got {doc.get('format')!r}")
    if top.number("counter_modulus") != COUNTER_MODULUS:
        raise top.fail("counter_modulus", f"only {COUNTER_MODULUS} (32-bit) is supported")
    raw = top.get("joint")
    if not isinstance(raw, list) or not raw:
        raise top.fail("joint", "expected one or more [[joint]] tables")
    joints: dict[int, GratingScale] = {}
    ranges: dict[int, tuple[float, float]] = {}
    for i, data in enumerate(raw):
        table = TomlTable(data, source, f"[[joint]] #{i + 1}", ScaleFileError)
        scale = _parse_joint(table)
        if scale.joint in joints:
            raise ScaleFileError(f"{source}: [[joint]] #{i + 1}: joint {scale.joint} given twice")
        joints[scale.joint] = scale
        if "calibrated_range_deg" in table.data:
            ranges[scale.joint] = _range(table, "calibrated_range_deg")
    robot = doc.get("robot") if isinstance(doc.get("robot"), str) else None
    meta = doc.get("calibration", {}) if isinstance(doc.get("calibration"), dict) else {}
    return ScaleCalibration(joints, robot, meta, ranges)


def _range(t: TomlTable, key: str) -> tuple[float, float]:
    value = t.get(key)
    ok = isinstance(value, list) and len(value) == 2
    ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    if not ok or not all(math.isfinite(v) for v in value) or value[0] > value[1]:
        raise t.fail(key, f"expected [low, high] finite degrees, got {value!r}")
    return float(value[0]), float(value[1])


def _parse_joint(t: TomlTable) -> GratingScale:
    joint = t.get("joint")
    if isinstance(joint, bool) or not isinstance(joint, int) or joint < 1:
        raise t.fail("joint", f"expected a joint number ≥ 1, got {joint!r}")
    terms = _terms(t)
    names = [SCALE_NAME] + [n for term in terms for n in TERMS[term][0]]
    coefficients = _coefficients(t, names, terms)
    cov_table = t.table("covariance")
    if cov_table.get("names") != names:
        raise cov_table.fail("names", f"expected {names}")
    covariance = cov_table.matrix("deg2", len(names))
    zero = t.number("zero_counts")
    if not 0 <= zero < COUNTER_MODULUS:
        raise t.fail("zero_counts", f"must be in [0, {COUNTER_MODULUS}), got {zero}")
    half_span = t.number("nonlinear_half_span_counts", default=1.0)
    if half_span <= 0:
        raise t.fail("nonlinear_half_span_counts", "must be positive")
    unmodelled = _unmodelled(t, names, terms)
    home = t.data.get("home_deg")
    return GratingScale(
        joint=joint,
        zero_counts=zero,
        zero_std_counts=t.number("zero_std_counts", default=0.0),
        terms=terms,
        coefficients=coefficients,
        basis=RelationBasis(
            phase_rad_per_count=t.number("phase_rad_per_count", default=0.0),
            nonlinear_centre_counts=t.number("nonlinear_centre_counts", default=0.0),
            nonlinear_half_span_counts=half_span,
        ),
        covariance_deg2=covariance,
        unmodelled=unmodelled,
        home_deg=None if home is None else t.number("home_deg"),
    )


def _terms(t: TomlTable) -> tuple[str, ...]:
    terms_raw = t.get("terms")
    if not isinstance(terms_raw, list) or not all(isinstance(x, str) for x in terms_raw):
        raise t.fail("terms", "expected an array of term names")
    try:
        return check_terms(terms_raw)
    except CalibrationError as exc:
        raise t.fail("terms", str(exc)) from None


def _coefficients(t: TomlTable, names: list[str], terms: tuple[str, ...]) -> dict[str, float]:
    """The relation's coefficients (deg per unit), exactly ``names``, in their order."""
    coefficients = t.number_table("coefficients")
    for n in names:
        if n not in coefficients:
            raise t.fail("coefficients", f"missing coefficient '{n}' for terms {terms}")
    coefficients = {n: coefficients[n] for n in names}
    if coefficients[SCALE_NAME] == 0:
        raise t.fail("coefficients", f"'{SCALE_NAME}' must not be zero")
    return coefficients


def _unmodelled(
    t: TomlTable, names: list[str], terms: tuple[str, ...]
) -> dict[str, UnmodelledTerm]:
    """The ``[unmodelled.<term>]`` tables: candidate terms left out of the relation."""
    unmodelled = {}
    un_table = t.table("unmodelled", t.data.get("unmodelled", {}))
    for term, data in un_table.data.items():
        if term not in TERMS or term in terms:
            raise un_table.fail(term, "not a candidate term left out of the relation")
        sub = un_table.table(term, data)
        wide = [*names, *TERMS[term][0]]
        delta = sub.number_table("delta")
        if set(delta) != set(wide):
            raise sub.fail("delta", f"expected the coefficients {wide}")
        unmodelled[term] = UnmodelledTerm(
            p_value=sub.number("p_value"),
            delta={n: delta[n] for n in _canonical(terms, term)},
            delta_covariance_deg2=sub.matrix("delta_covariance_deg2", len(wide)),
        )
    return unmodelled


def _canonical(terms: Sequence[str], extra: str) -> list[str]:
    """Coefficient names of ``terms`` plus ``extra``, in the order the basis builds them."""
    return [SCALE_NAME] + [n for term in (*terms, extra) for n in TERMS[term][0]]
