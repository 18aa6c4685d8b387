"""``twin track``: the calibrated twin following the robot through production checks.

twin track --model calibrated.toml --data checks.csv --out tracked.csv [--params LIST]
    [--alarm-mm X] [--out-model M.toml] [--report DIR]

Each check is predicted from the model and the checks before it (a priori), then learned
from (:mod:`calibration.twin.tracking`); tracked.csv has one row per check in the input's order.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from calibration.effects.model_effects import load_checked_robot, missing_temperature_warning
from calibration.errors import OptionError, OutputFileError, TrackingError
from calibration.identify.campaign_files import Checks, read_checks
from calibration.model.description import RobotDescription
from calibration.model.unit_plausibility import OVERRIDE, check_campaign_units
from calibration.twin.tracking import (
    TrackingRun,
    TrackingSettings,
    TrackingSetup,
    effect_offsets,
    static_errors_mm,
    track_checks,
    tracking_setup,
)
from edges.options import number
from edges.outputs import OutputSet

FloatArray = NDArray[np.float64]

#: The leading columns of tracked.csv, before each tracked parameter and its ``_se``.
TRACKED_COLUMNS = [
    "pose",
    "t_s",
    "x_mm",
    "y_mm",
    "z_mm",
    "pred_x_mm",
    "pred_y_mm",
    "pred_z_mm",
    "err_mm",
    "state",
    "lambda",
]
#: The permutation of the shuffled-order comparison (the report's).
SHUFFLE_SEED = 0


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "track",
        help="follow the robot's drift and steps through production checks",
        description="Track a few parameters of a calibrated model through tracker checks in "
        "time order: each check predicted a priori, then learned from; steps and alarms "
        "reported (docs/tracking.md).",
    )
    p.add_argument("--model", required=True, help="calibrated robot description (.toml)")
    p.add_argument("--data", required=True, help="checks.csv: campaign.csv's columns, t_s sorted")
    p.add_argument("--out", required=True, help="tracked.csv to write")
    p.add_argument(
        "--params",
        metavar="LIST",
        help="comma-separated parameters to track, by model name (default: the identified "
        "base and tool and a length scale per long link)",
    )
    p.add_argument(
        "--alarm-mm",
        type=number(0.0, above=True),
        help="alarm when the tracked model moves the TCP at the validation poses by more "
        "than this (mm)",
    )
    p.add_argument("--out-model", metavar="M.toml", help="the model after the last check")
    p.add_argument("--report", metavar="DIR", help="write report.json, report.md, parameters.png")
    p.add_argument(OVERRIDE, action="store_true", help="do not refuse points that look like metres")
    p.set_defaults(func=run_track)


def _names(text: str | None) -> list[str] | None:
    if text is None:
        return None
    names = [n.strip() for n in text.split(",")]
    if not all(names):
        raise OptionError(f"--params: an empty name in {text!r}")
    if len(set(names)) != len(names):
        raise OptionError(f"--params: a name given twice in {text!r}")
    return names


def _fmt(v: float, digits: int) -> str:
    return f"{v:.{digits}f}"


def write_tracked(path: Path, checks: Checks, run: TrackingRun, names: tuple[str, ...]) -> None:
    """tracked.csv: the leading columns, then each parameter (absolute) and its ``_se``."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow([*TRACKED_COLUMNS, *(c for n in names for c in (n, f"{n}_se"))])
        for i, pose in enumerate(checks.pose):
            params = [
                _fmt(float(v), 12)
                for pair in zip(run.absolute[i], run.theta_se[i], strict=True)
                for v in pair
            ]
            w.writerow(
                [
                    pose,
                    _fmt(float(checks.t_s[i]), 6),
                    *(_fmt(float(v), 6) for v in checks.xyz_mm[i]),
                    *(_fmt(float(v), 6) for v in run.predicted_mm[i]),
                    _fmt(float(run.error_mm[i]), 6),
                    run.states[i],
                    _fmt(float(run.forgetting[i]), 6),
                    *params,
                ]
            )


def _model_after(desc: RobotDescription, setup: TrackingSetup, run: TrackingRun) -> str:
    """The description as it stands after the last check (effects and [tracking] kept)."""
    return setup.model(run.state.theta).to_description(desc).dumps()


def run_track(args: argparse.Namespace) -> int:
    names = _names(args.params)
    settings = TrackingSettings(alarm_mm=args.alarm_mm)
    with OutputSet([args.data, args.model], error=OutputFileError) as outputs:
        out = outputs.file(args.out, "--out")
        out_model = outputs.file(args.out_model, "--out-model") if args.out_model else None
        report = outputs.directory(args.report, "--report") if args.report else None
        desc = load_checked_robot(args.model)
        try:
            setup = tracking_setup(desc, names, settings)
        except TrackingError as exc:
            raise TrackingError(f"{args.model}: {exc}") from None
        limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
        checks = read_checks(args.data, desc.n_joints, limits_deg=limits)
        if not args.no_unit_check:
            check_campaign_units(
                str(args.data), checks.q_deg, checks.xyz_mm, setup.template, limits
            )
        q = np.radians(checks.q_deg)
        offsets = effect_offsets(desc, q, checks.t_s, checks.temp_c)
        run = track_checks(setup, q, checks.xyz_mm, offsets)
        static = static_errors_mm(setup, q, checks.xyz_mm, offsets)
        write_tracked(out, checks, run, setup.names)
        if out_model is not None:
            out_model.write_text(_model_after(desc, setup, run), encoding="utf-8")
        if report is not None:
            _report(report, args, setup, checks, run, static, q, offsets)
    no_temperature = missing_temperature_warning(desc, checks.temp_c)
    if no_temperature:
        print(f"twin track: warning: {no_temperature}", file=sys.stderr)
    for line in _summary(run, static, checks):
        print(line)
    print(f"wrote {args.out}: {len(checks)} checks")
    return 0


def _report(
    directory: Path,
    args: argparse.Namespace,
    setup: TrackingSetup,
    checks: Checks,
    run: TrackingRun,
    static: FloatArray,
    q: FloatArray,
    offsets: FloatArray,
) -> None:
    """The report, with the same checks tracked in a shuffled order beside them."""
    from calibration.twin.tracking_report import (
        TrackingEvidence,
        build_tracking_report,
        write_tracking_report,
    )

    perm = np.random.default_rng(SHUFFLE_SEED).permutation(len(q))
    shuffled = track_checks(setup, q[perm], checks.xyz_mm[perm], offsets[perm])
    shuffled_mm = np.empty(len(q))
    shuffled_mm[perm] = shuffled.error_mm
    ev = TrackingEvidence(setup, run, checks.pose, checks.t_s, static, shuffled_mm)
    doc = build_tracking_report(ev, {"model": str(args.model), "data": str(args.data)})
    write_tracking_report(directory, doc, ev)


def _summary(run: TrackingRun, static: FloatArray, checks: Checks) -> list[str]:
    lines = [
        f"one-step-ahead mean error: static {static.mean():.4f} mm, tracked "
        f"{run.error_mm.mean():.4f} mm"
    ]
    for detected, onset in run.steps:
        lines.append(
            f"step at {checks.t_s[onset]:.0f} s (pose {checks.pose[onset]}), reported at "
            f"{checks.t_s[detected]:.0f} s (pose {checks.pose[detected]})"
        )
    alarm_rows = [i for i, s in enumerate(run.states) if s == "alarm"]
    if alarm_rows:
        first = alarm_rows[0]
        lines.append(
            f"alarm from {checks.t_s[first]:.0f} s (pose {checks.pose[first]}): the TCP moved "
            f"{run.displacement_mm[first]:.3f} mm at the validation poses"
        )
    return lines
