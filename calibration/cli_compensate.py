"""``twin compensate``: joint commands that put the calibrated robot on its targets.

twin compensate --model calibrated.toml --targets targets.csv --out joints.csv [--skip-bad]

See docs/compensation.md.
"""

from __future__ import annotations

import argparse
import csv
import sys

import numpy as np

from calibration.campaign_files import joint_columns, read_targets
from calibration.errors import DataFileError, OutputFileError
from calibration.model_effects import load_checked_robot
from edges.outputs import OutputSet


def register(sub: argparse._SubParsersAction) -> None:
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
        help="targets.csv: target,x_mm,y_mm,z_mm and q1_deg..qN_deg or rx_deg,ry_deg,rz_deg",
    )
    p.add_argument("--out", required=True, help="joints.csv to write")
    p.add_argument(
        "--skip-bad",
        action="store_true",
        help="leave out unreachable targets (listed on stderr) instead of refusing the file",
    )
    p.set_defaults(func=run_compensate)


def run_compensate(args: argparse.Namespace) -> int:
    from calibration.compensation import compensate

    with OutputSet([args.model, args.targets], error=OutputFileError) as outputs:
        out_path = outputs.file(args.out, "--out")
        desc = load_checked_robot(args.model)
        limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
        targets = read_targets(args.targets, desc.n_joints, limits_deg=limits)
        res = compensate(
            desc,
            targets.xyz_mm,
            q_programmed_deg=targets.q_deg,
            rpy_deg=targets.rpy_deg,
            t_s=targets.t_s,
        )
        bad = np.flatnonzero(~res.ok)
        if bad.size and not args.skip_bad:
            k = int(bad[0])
            raise DataFileError(
                f"{targets.source}: line {targets.lines[k]} (target {targets.target[k]!r}): "
                f"{res.reason[k]} ({bad.size} such target(s); --skip-bad leaves them out)"
            )
        with open(out_path, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(
                ["target", *joint_columns(desc.n_joints), "residual_mm", "branch", "travel_deg"]
            )
            for i in np.flatnonzero(res.ok):
                w.writerow(
                    [
                        targets.target[i],
                        *(f"{v:.9f}" for v in res.q_deg[i]),
                        f"{res.residual_mm[i]:.3e}",
                        int(res.branch[i]),
                        f"{res.travel_deg[i]:.6f}" if np.isfinite(res.travel_deg[i]) else "",
                    ]
                )
    for k in bad:
        print(
            f"twin compensate: skipped target {targets.target[k]!r} (line "
            f"{targets.lines[k]}): {res.reason[k]}",
            file=sys.stderr,
        )
    travel = res.travel_deg[res.ok]
    extra = f"; largest joint change {np.max(travel):.4f}°" if np.isfinite(travel).any() else ""
    print(
        f"wrote {args.out}: {int(res.ok.sum())} targets, residual ≤ "
        f"{np.nanmax(res.residual_mm[res.ok]) if res.ok.any() else 0:.1e} mm{extra}"
    )
    return 0
