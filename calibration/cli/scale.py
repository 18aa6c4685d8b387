"""``twin scale`` and ``twin scale-apply``: grating-scale calibration from files, and its use.

``twin scale --sweep sweep.csv --home home.csv --out scale.toml [--report DIR]``
``twin scale-apply --scale scale.toml --data counts.csv --out angles.csv``
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from calibration.errors import DataFileError, OptionError, OutputFileError, ScaleError
from calibration.model.description import RobotDescription, load_robot
from calibration.model.unit_plausibility import OVERRIDE, check_sweep_units
from calibration.scales.chain_scale import ScaleCampaignResult, calibrate_scales, with_load_notes
from calibration.scales.grating_scale import TERMS, ScaleOptions, TrackerSpec, check_terms
from calibration.scales.scale_files import (
    CountsTable,
    ScaleCalibration,
    read_counts_csv,
    read_home_csv,
    read_scale_toml,
    read_sweep_csv,
    scale_document,
    write_csv,
    write_scale_toml,
)
from edges.outputs import OutputSet


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "scale",
        help="grating-scale calibration from home.csv and sweep.csv",
        description="Per joint: Home zero, 3-D circle fits of the sweeps, counts → angle "
        "relation with statistically selected terms. See docs/scale-calibration.md.",
    )
    p.add_argument(
        "--sweep", required=True, help="sweep.csv: joint,pass,step,counts,x_mm,y_mm,z_mm"
    )
    p.add_argument("--home", help="home.csv: joint,trial,counts (joints without rows: see docs)")
    p.add_argument("--out", required=True, help="scale.toml to write")
    p.add_argument("--report", help="directory for report.md, report.json and residual plots")
    p.add_argument(
        "--robot",
        help="preset name or description file: joint count, Home vector and limits "
        "(needed for a joint without Home rows)",
    )
    p.add_argument("--alpha", type=float, default=0.01, help="false-term rate per joint")
    p.add_argument(
        "--terms",
        default=",".join(TERMS),
        help=f"candidate terms, comma-separated, from: {', '.join(TERMS)} (empty: none)",
    )
    p.add_argument("--counts-per-mm", type=float, default=1000.0, help="strip resolution")
    p.add_argument("--step-deg", type=float, default=2.0, help="commanded sweep step")
    p.add_argument("--tracker-mpe-um", type=float, default=15.0)
    p.add_argument("--tracker-mpe-um-per-m", type=float, default=6.0)
    p.add_argument(
        OVERRIDE,
        action="store_true",
        help="do not refuse sweep points that do not move like millimetres (metres)",
    )
    p.add_argument(
        "--allow-out-of-range",
        action="store_true",
        help="calibrate a joint whose sweep lies outside its limits seen from Home (default: "
        "refused: Home counts that disagree with the sweep)",
    )
    p.set_defaults(func=run_scale)

    a = sub.add_parser(
        "scale-apply",
        help="turn grating counts into joint angles",
        description="Add angle_deg (relative to Home) to a CSV of joint,counts rows; an "
        "optional 'direction' column (positive/negative/unknown) applies a kept hysteresis.",
    )
    a.add_argument("--scale", required=True, help="scale.toml from `twin scale`")
    a.add_argument("--data", required=True, help="counts.csv: joint,counts[,direction,...]")
    a.add_argument("--out", required=True, help="CSV to write (input columns + angle_deg)")
    a.add_argument("--joint-angle", action="store_true", help="also add q_deg = home_deg + angle")
    a.add_argument("--std", action="store_true", help="also add angle_std_deg")
    a.add_argument(
        OUT_OF_RANGE,
        action="store_true",
        help=f"convert counts whose angle lies more than {RANGE_MARGIN_DEG:g}° outside the "
        "angles the calibration covered (default: refused, naming the row)",
    )
    a.set_defaults(func=run_apply)


def _positive(option: str, value: float, *, zero: bool = False) -> None:
    if not math.isfinite(value) or value < 0 or (value == 0 and not zero):
        need = ">= 0" if zero else "> 0"
        raise OptionError(f"{option}: need a finite value {need}, got {value}")


def _options(args: argparse.Namespace) -> ScaleOptions:
    if not 0 < args.alpha < 1:
        raise OptionError(f"--alpha: must be in (0, 1), got {args.alpha}")
    _positive("--counts-per-mm", args.counts_per_mm)
    _positive("--step-deg", args.step_deg)
    _positive("--tracker-mpe-um", args.tracker_mpe_um)
    _positive("--tracker-mpe-um-per-m", args.tracker_mpe_um_per_m, zero=True)
    terms = check_terms([t.strip() for t in args.terms.split(",") if t.strip()])
    return ScaleOptions(
        alpha=args.alpha,
        candidate_terms=terms,
        tracker=TrackerSpec(args.tracker_mpe_um, args.tracker_mpe_um_per_m),
        counts_per_mm=args.counts_per_mm,
        step_deg=args.step_deg,
    )


def calibrate_files(
    sweep_path: str | Path,
    home_path: str | Path | None,
    robot: RobotDescription | None,
    options: ScaleOptions,
    *,
    unit_check: bool = True,
) -> ScaleCampaignResult:
    """Read the campaign files and calibrate every joint in the sweep (in chain order, the
    other joints' motion taken out where sweep.csv has their readings)."""
    n_joints = robot.n_joints if robot is not None else None
    sweep = read_sweep_csv(
        sweep_path, n_joints=n_joints, min_stops_per_pass=options.min_stops_per_pass
    )
    if unit_check:
        check_sweep_units(sweep.path, {j: s.points_mm for j, s in sweep.joints.items()})
    home = read_home_csv(home_path, n_joints=n_joints) if home_path else None
    if home is not None:
        for j, rows in home.rows.items():
            if j not in sweep.joints:
                raise DataFileError(
                    f"{home.path}: row {rows.min()}, column 'joint': joint {j} has Home rows "
                    f"but no sweep in {sweep.path}"
                )
    try:
        result = calibrate_scales(
            sweep.joints,
            home.counts if home is not None else None,
            home_deg=robot.home if robot is not None else None,
            limits_deg=[(j.lower_deg, j.upper_deg) for j in robot.joints] if robot else None,
            options=options,
        )
    except ScaleError as exc:
        raise ScaleError(f"{sweep.path}: {exc}") from exc
    if robot is None:
        return result
    return with_load_notes(result, robot, deflection_taken_out=False)


def check_calibrated_ranges(
    results: ScaleCampaignResult,
    robot: RobotDescription | None,
    sweep_path: str,
    home_path: str | None,
) -> None:
    """Refuse a joint whose calibrated range (its sweep stops' angles from Home) leaves the
    joint's limits (``robot``'s, seen from its Home; without one: a turn either way) by more
    than :data:`RANGE_MARGIN_DEG`. Home counts that disagree with the sweep by millions of
    counts (another joint's, a reset counter) otherwise give a map that turns the joint
    through thousands of degrees, silently."""
    for r in results:
        used = r.stop_angle_deg[r.used]
        if not used.size:
            continue
        lo, hi = float(used.min()), float(used.max())
        if robot is not None:
            joint, home_deg = robot.joints[r.joint - 1], robot.home[r.joint - 1]
            allowed = (joint.lower_deg - home_deg, joint.upper_deg - home_deg)
            what = (
                f"joint {r.joint}'s limits {joint.lower_deg:g}..{joint.upper_deg:g}° "
                f"(Home at {home_deg:g}°, {robot.name})"
            )
        else:
            allowed, what = FALLBACK_RANGE_DEG, "a turn from Home (no --robot for its limits)"
        if allowed[0] - RANGE_MARGIN_DEG <= lo and hi <= allowed[1] + RANGE_MARGIN_DEG:
            continue
        source = f"{home_path}: joint {r.joint}" if r.home.source == "home" else sweep_path
        raise DataFileError(
            f"{source}, column 'counts': joint {r.joint}'s sweep lies {lo:.1f}..{hi:.1f}° from "
            f"Home, outside {what} (±{RANGE_MARGIN_DEG:g}°): do these Home counts belong to "
            f"this sweep (another joint's, a reset counter)? ({OUT_OF_RANGE} calibrates anyway)"
        )


def _file(name: str | None) -> str | None:
    return name if name and Path(name).exists() else None


def run_scale(args: argparse.Namespace) -> int:
    options = _options(args)
    inputs = [args.sweep, args.home, _file(args.robot)]
    with OutputSet(inputs, error=OutputFileError) as outputs:
        out_path = outputs.file(args.out, "--out")
        report_dir = outputs.directory(args.report, "--report") if args.report else None
        lines = _scale(args, options, out_path, report_dir)
    for line in lines:
        print(line)
    return 0


def _scale(
    args: argparse.Namespace, options: ScaleOptions, out_path: Path, report_dir: Path | None
) -> list[str]:
    """The calibration, written to the staged ``out_path`` (and ``report_dir``); the
    lines to print once the outputs are in place."""
    robot = load_robot(args.robot) if args.robot else None
    t0 = time.perf_counter()
    results = calibrate_files(
        args.sweep, args.home, robot, options, unit_check=not args.no_unit_check
    )
    elapsed = time.perf_counter() - t0
    if not args.allow_out_of_range:
        check_calibrated_ranges(results, robot, args.sweep, args.home)
    meta = {
        "sweep_file": Path(args.sweep).name,
        "home_file": Path(args.home).name if args.home else "",
        "alpha": options.alpha,
        "candidate_terms": list(options.candidate_terms),
        "tracker_mpe_um": options.tracker.mpe_um,
        "tracker_mpe_um_per_m": options.tracker.mpe_um_per_m,
        "step_deg": options.step_deg,
    }
    doc = scale_document(
        results,
        robot=robot.name if robot is not None else None,
        metadata=meta,
        counts_per_mm=options.counts_per_mm,
    )
    write_scale_toml(out_path, doc)
    lines = [_summary(results, options.counts_per_mm)]
    lines += [f"joint {r.joint}: {note}" for r in results for note in r.notes]
    lines.append(f"wrote {args.out} ({len(results)} joints, {elapsed:.2f} s)")
    if report_dir is not None:
        from calibration.scales.scale_report import write_report

        paths = write_report(
            results,
            report_dir,
            robot=doc.get("robot"),
            metadata=meta,
            counts_per_mm=options.counts_per_mm,
        )
        final = (Path(args.report) / Path(p).relative_to(report_dir) for p in paths.values())
        lines.append(f"wrote report: {', '.join(str(p) for p in final)}")
    return lines


def _summary(results: ScaleCampaignResult, counts_per_mm: float) -> str:
    lines = [
        f"{'joint':>5} {'zero counts':>14} {'counts/deg':>13} {'R_eff mm':>10} "
        f"{'terms':<20} {'rms arcsec':>10} {'circle R mm':>12}"
    ]
    for r in results:
        s = r.scale
        lines.append(
            f"{r.joint:>5} {s.zero_counts:>14.1f} {s.counts_per_deg:>13.3f} "
            f"{s.effective_radius_mm(counts_per_mm):>10.4f} {','.join(s.terms) or '-':<20} "
            f"{r.residual_rms_arcsec:>10.2f} {r.circle.radius_mm:>12.4f}"
        )
    return "\n".join(lines)


def run_apply(args: argparse.Namespace) -> int:
    with OutputSet([args.scale, args.data], error=OutputFileError) as outputs:
        out_path = outputs.file(args.out, "--out")
        line = _apply(args, out_path)
    print(line)
    return 0


def _apply(args: argparse.Namespace, out_path: Path) -> str:
    """Counts to angles, written to the staged ``out_path``; the line to print."""
    cal = read_scale_toml(args.scale)
    data = read_counts_csv(args.data)
    for k, j in enumerate(data.joint):
        if int(j) not in cal.joints:
            known = ", ".join(str(x) for x in sorted(cal.joints))
            raise DataFileError(
                f"{data.path}: row {data.lines[k]}, column 'joint': joint {j} is not in "
                f"{args.scale} (calibrated joints: {known})"
            )
    added = (
        ["angle_deg"]
        + (["q_deg"] if args.joint_angle else [])
        + (["angle_std_deg"] if args.std else [])
    )
    for name in added:
        if name in data.header:
            raise DataFileError(f"{data.path}: row 1, column '{name}': already present")
    angle = cal.angles_deg(data.joint, data.counts, data.direction)
    if not args.allow_out_of_range:
        _check_range(args, cal, data, angle)
    columns = [angle]
    if args.joint_angle:
        home = np.empty(angle.shape)
        for k, j in enumerate(data.joint):
            h = cal.joints[int(j)].home_deg
            if h is None:
                raise ScaleError(
                    f"{args.scale}: joint {j} has no home_deg (calibrated without --robot); "
                    "drop --joint-angle or recalibrate with --robot"
                )
            home[k] = h
        columns.append(home + angle)
    if args.std:
        std = np.empty(angle.shape)
        for j in np.unique(data.joint):
            m = data.joint == j
            d = None if data.direction is None else data.direction[m]
            std[m] = cal.joints[int(j)].angle_std_deg(data.counts[m], d)
        columns.append(std)
    rows = ([*fields, *(_fmt(c[k]) for c in columns)] for k, fields in enumerate(data.rows))
    write_csv(out_path, [*data.header, *added], rows)
    rms = math.sqrt(float(np.mean(angle**2))) if angle.size else 0.0
    return f"wrote {args.out} ({angle.size} rows; rms angle {rms:.3f} deg)"


#: How far outside the calibrated angles (deg) a converted angle may lie: the sweeps run
#: limit to limit, so beyond a few degrees past them the counts are of another joint, a
#: reset counter or a typo, and the relation would be extrapolated.
RANGE_MARGIN_DEG = 10.0
#: Without a calibrated range in scale.toml (older files): more than a turn from Home.
FALLBACK_RANGE_DEG = (-360.0, 360.0)
OUT_OF_RANGE = "--allow-out-of-range"


def _check_range(
    args: argparse.Namespace, cal: ScaleCalibration, data: CountsTable, angle: NDArray[np.float64]
) -> None:
    """Refuse the first row whose angle lies outside what the calibration covered."""
    for j in np.unique(data.joint):
        lo, hi = cal.ranges_deg.get(int(j), FALLBACK_RANGE_DEG)
        m = np.flatnonzero(data.joint == j)
        bad = m[(angle[m] < lo - RANGE_MARGIN_DEG) | (angle[m] > hi + RANGE_MARGIN_DEG)]
        if bad.size:
            k = int(bad[0])
            raise DataFileError(
                f"{data.path}: row {data.lines[k]}, column 'counts': joint {j}: "
                f"{data.rows[k][data.header.index('counts')].strip()} counts give "
                f"{angle[k]:.1f}° from Home, outside the {lo:.1f}..{hi:.1f}° the calibration in "
                f"{args.scale} covered (±{RANGE_MARGIN_DEG:g}°): the wrong joint, a reset "
                f"counter? ({bad.size} such row(s); {OUT_OF_RANGE} converts them anyway)"
            )


def _fmt(x: float) -> str:
    return f"{x:.9f}"
