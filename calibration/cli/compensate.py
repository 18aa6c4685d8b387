"""``twin compensate``: joint commands that put the calibrated robot on its targets.

twin compensate --model calibrated.toml --targets targets.csv --out joints.csv [--skip-bad]

See docs/compensation.md.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibration.effects.model_effects import (
    TcpPrediction,
    load_checked_robot,
    missing_temperature_warning,
    predict_tcp_sd,
)
from calibration.errors import DataFileError, OutputFileError
from calibration.identify.campaign_files import joint_columns, read_targets
from calibration.model.kinematics import KinematicModel
from calibration.model.unit_plausibility import OVERRIDE, check_measurement_units
from edges.outputs import OutputSet

if TYPE_CHECKING:  # the solver loads when the command runs, not for --help
    from numpy.typing import NDArray

    from calibration.identify.campaign_files import Targets
    from calibration.model.description import RobotDescription
    from calibration.twin.compensation import CompensationResult


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "compensate",
        help="joint commands that put the calibrated TCP on target positions",
        description="For each target (tracker frame, mm), the joints whose calibrated "
        "prediction (every modelled effect applied) is the target, keeping the tool "
        "orientation of the programmed joints or a stated one. See docs/compensation.md.",
    )
    p.add_argument("--model", required=True, help="calibrated robot description (.toml)")
    p.add_argument(
        "--targets",
        required=True,
        help="targets.csv: target,x_mm,y_mm,z_mm and q1_deg..qN_deg or rx_deg,ry_deg,rz_deg; "
        "optional t_s, temp_c (the arm's temperature, °C) and fx_n,fy_n,fz_n (a process "
        "force on the tool, N)",
    )
    p.add_argument("--out", required=True, help="joints.csv to write")
    p.add_argument(
        "--skip-bad",
        action="store_true",
        help="leave out unreachable targets (listed on stderr) instead of refusing the file",
    )
    p.add_argument(
        OVERRIDE,
        dest="no_unit_check",
        action="store_true",
        help="skip the units check (targets in metres, programmed joints in radians)",
    )
    p.set_defaults(func=run_compensate)


def run_compensate(args: argparse.Namespace) -> int:
    from calibration.model.stiffness import states_stiffness
    from calibration.twin.compensation import compensate

    with OutputSet([args.model, args.targets], error=OutputFileError) as outputs:
        out_path = outputs.file(args.out, "--out")
        desc = load_checked_robot(args.model)
        limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
        targets = read_targets(args.targets, desc.n_joints, limits_deg=limits)
        if targets.q_deg is not None and not args.no_unit_check:
            model = KinematicModel.from_description(desc)
            check_measurement_units(
                targets.source, targets.q_deg, limits, xyz_mm=targets.xyz_mm, model=model
            )
        force = targets.force_n
        if force is not None and np.any(force) and not states_stiffness(desc):
            raise DataFileError(
                f"{targets.source}: columns fx_n,fy_n,fz_n give a process force, but "
                f"{args.model} states no joint stiffness ([[joint]] stiffness_nmm_per_rad; "
                "`twin stiffness --load-test` measures them)"
            )
        res = compensate(
            desc,
            targets.xyz_mm,
            q_programmed_deg=targets.q_deg,
            rpy_deg=targets.rpy_deg,
            t_s=targets.t_s,
            force_n=force,
            temp_c=targets.temp_c,
            skip_unreached=args.skip_bad,
        )
        bad = np.flatnonzero(~res.ok)
        if bad.size and not args.skip_bad:
            first = int(bad[0])
            raise DataFileError(
                f"{targets.source}: line {targets.lines[first]} "
                f"(target {targets.target[first]!r}): "
                f"{res.reason[first]} ({bad.size} such target(s); --skip-bad leaves them out)"
            )
        q_ok = np.where(res.ok[:, None], res.q_deg, 0.0)  # failed rows: a finite stand-in
        times = None if targets.t_s is None else np.asarray(targets.t_s, dtype=float)
        pred = predict_tcp_sd(desc, np.radians(q_ok), times, temp_c=targets.temp_c)
        _write_joints(out_path, desc.n_joints, targets.target, res, pred)
    _say_skipped_and_warnings(desc, targets, res, bad)
    travel = res.travel_deg[res.ok]
    extra = f"; largest joint change {np.max(travel):.4f}°" if np.isfinite(travel).any() else ""
    if res.force_deflection_mm is not None and res.ok.any():
        largest = np.max(np.linalg.norm(res.force_deflection_mm[res.ok], axis=1))
        extra += f"; force deflection taken out ≤ {largest:.4f} mm"
    print(
        f"wrote {args.out}: {int(res.ok.sum())} targets, residual ≤ "
        f"{np.nanmax(res.residual_mm[res.ok]) if res.ok.any() else 0:.1e} mm{extra}"
    )
    return 0


def _say_skipped_and_warnings(
    desc: RobotDescription, targets: Targets, res: CompensationResult, bad: NDArray[np.intp]
) -> None:
    """On stderr: each target left out and why, and a model's temperature terms solved
    without a temperature."""
    for k in bad:
        print(
            f"twin compensate: skipped target {targets.target[k]!r} (line "
            f"{targets.lines[k]}): {res.reason[k]}",
            file=sys.stderr,
        )
    no_temperature = missing_temperature_warning(desc, targets.temp_c)
    if no_temperature:
        print(f"twin compensate: warning: {no_temperature}", file=sys.stderr)


def _write_joints(
    path: Path, n_joints: int, ids: tuple[str, ...], res: CompensationResult, pred: TcpPrediction
) -> None:
    """joints.csv: the reached targets; ``force_deflection_mm`` (the process force's
    deflection taken out, mm) only when the targets gave a force; then ``sd_mm`` (the
    predictive standard deviation per axis of the TCP at the joints, empty where the model
    states none) and ``beyond_reach`` (1: outside the learned residual stage's data)."""
    deflection = res.force_deflection_mm
    header = ["target", *joint_columns(n_joints), "residual_mm", "branch", "travel_deg"]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        extra = [] if deflection is None else ["force_deflection_mm"]
        w.writerow([*header, *extra, "sd_mm", "beyond_reach"])
        for i in np.flatnonzero(res.ok):
            travel = f"{res.travel_deg[i]:.6f}" if np.isfinite(res.travel_deg[i]) else ""
            row: list[str | int] = [ids[i], *(f"{v:.9f}" for v in res.q_deg[i])]
            row += [f"{res.residual_mm[i]:.3e}", int(res.branch[i]), travel]
            if deflection is not None:
                row.append(f"{np.linalg.norm(deflection[i]):.6f}")
            sd = pred.sd_mm[i]
            row += ["" if np.isnan(sd) else f"{sd:.6f}", int(pred.beyond_reach[i])]
            w.writerow(row)
