"""``twin stiffness``: the calibrated robot's Cartesian compliance, and a load test.

twin stiffness --model M --data joints.csv [--out compliance.csv] [--feed X,Y,Z]
twin stiffness --model M --load-test loads.csv --out-model M2.toml

See docs/compensation.md ("Process force and stiffness").
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from calibration.effects.model_effects import load_checked_robot
from calibration.errors import DataFileError, OptionError, OutputFileError, StiffnessError
from calibration.identify.campaign_files import joint_columns, read_load_test, read_poses
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel
from calibration.model.unit_plausibility import OVERRIDE, check_measurement_units
from edges.options import path_text
from edges.outputs import OutputSet

FloatArray = NDArray[np.float64]
UM_PER_MM = 1000.0


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "stiffness",
        help="Cartesian compliance C = J K⁻¹ Jᵀ at poses, or joint stiffness from a load test",
        description="With --data: the TCP's compliance (µm/N) at each pose from the model's "
        "joint stiffnesses, its softest direction, and with --feed the compliance along a "
        "feed direction (which poses are stiffest along it). With --load-test: the joint "
        "stiffnesses from TCP deflections measured under known forces, written into a copy "
        "of the model. See docs/compensation.md.",
    )
    p.add_argument("--model", required=True, type=path_text, help="robot description (.toml)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--data", type=path_text, help="joints.csv: pose (or target), q1_deg..qN_deg")
    what.add_argument(
        "--load-test",
        type=path_text,
        help="loads.csv: load, q1_deg..qN_deg, fx_n,fy_n,fz_n, x0_mm,y0_mm,z0_mm (unloaded), "
        "x_mm,y_mm,z_mm (loaded)",
    )
    p.add_argument("--out", type=path_text, help="with --data: compliance.csv to write")
    p.add_argument(
        "--feed",
        type=_direction,
        help="with --data: a feed direction X,Y,Z in the tracker frame (any length)",
    )
    p.add_argument(
        "--out-model",
        type=path_text,
        help="with --load-test: the model with the identified stiffnesses (.toml)",
    )
    p.add_argument(
        OVERRIDE,
        dest="no_unit_check",
        action="store_true",
        help="skip the units check (joints in radians, tracker points in metres)",
    )
    p.set_defaults(func=run_stiffness)


def _direction(text: str) -> FloatArray:
    parts = text.split(",")
    try:
        v = np.array([float(x) for x in parts], dtype=float)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z numbers, got {text!r}") from None
    if len(v) != 3 or not np.all(np.isfinite(v)) or not np.any(v):
        raise argparse.ArgumentTypeError(f"expected a non-zero finite X,Y,Z, got {text!r}")
    unit: FloatArray = v / np.linalg.norm(v)
    return unit


def run_stiffness(args: argparse.Namespace) -> int:
    if args.data is not None:
        if args.out_model is not None:
            raise OptionError("--out-model goes with --load-test, not --data")
        return _compliance_at_poses(args)
    if args.out is not None or args.feed is not None:
        raise OptionError("--out and --feed go with --data; a load test writes --out-model")
    if args.out_model is None:
        raise OptionError("--load-test needs --out-model (the model with the stiffnesses)")
    return _load_test(args)


def _compliance_at_poses(args: argparse.Namespace) -> int:
    from calibration.model.stiffness import cartesian_compliance, joint_compliance, states_stiffness

    inputs = [args.model, args.data]
    with OutputSet(inputs, error=OutputFileError) as outputs:
        out_path = None if args.out is None else outputs.file(args.out, "--out")
        desc = load_checked_robot(args.model)
        if not states_stiffness(desc):
            raise DataFileError(
                f"{args.model}: no joint states a stiffness ([[joint]] stiffness_nmm_per_rad; "
                "`twin stiffness --load-test` measures them)"
            )
        limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
        poses = read_poses(args.data, desc.n_joints, limits_deg=limits)
        if not args.no_unit_check:
            check_measurement_units(poses.source, poses.q_deg, limits)
        c = cartesian_compliance(desc, np.radians(poses.q_deg))[:, :3, :3] * UM_PER_MM
        eigval, eigvec = np.linalg.eigh(c)  # ascending; C is symmetric positive semi-definite
        feed = None if args.feed is None else np.einsum("i,mij,j->m", args.feed, c, args.feed)
        if out_path is not None:
            _write_compliance(out_path, desc, poses.pose, poses.q_deg, c, eigval, eigvec, feed)
    rigid = [str(i + 1) for i, v in enumerate(joint_compliance(desc)) if v == 0]
    if rigid:
        print(f"joints {', '.join(rigid)} state no stiffness: taken as rigid")
    softest = eigval[:, -1]
    print(
        f"{len(poses)} poses: softest direction {softest.min():.3f}–{softest.max():.3f} µm/N"
        + ("" if out_path is None else f"; wrote {args.out}")
    )
    if feed is not None:
        order = np.argsort(feed)
        shown = ", ".join(f"{poses.pose[i]} {feed[i]:.3f}" for i in order[:3])
        print(f"along the feed: stiffest poses (µm/N) {shown}; softest {feed[order[-1]]:.3f}")
    elif out_path is None:
        for i, pose in enumerate(poses.pose):
            print(f"  {pose}: softest {softest[i]:.4f} µm/N along {_fmt_dir(eigvec[i, :, -1])}")
    return 0


def _fmt_dir(v: FloatArray) -> str:
    return "(" + ", ".join(f"{x:+.3f}" for x in v) + ")"


def _write_compliance(
    path: Path,
    desc: RobotDescription,
    ids: tuple[str, ...],
    q_deg: FloatArray,
    c: FloatArray,
    eigval: FloatArray,
    eigvec: FloatArray,
    feed: FloatArray | None,
) -> None:
    """compliance.csv: per pose the joints, C's six entries (µm/N), its softest value and
    direction, its stiffest value, and the compliance along the feed when given."""
    entries = [(0, 0, "cxx"), (0, 1, "cxy"), (0, 2, "cxz"), (1, 1, "cyy"), (1, 2, "cyz")]
    entries.append((2, 2, "czz"))
    header = ["pose", *joint_columns(desc.n_joints), *(f"{n}_um_per_n" for *_, n in entries)]
    header += ["softest_um_per_n", "softest_x", "softest_y", "softest_z", "stiffest_um_per_n"]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow([*header, *([] if feed is None else ["feed_um_per_n"])])
        for k, pose in enumerate(ids):
            row = [pose, *(f"{v:.9f}" for v in q_deg[k])]
            row += [f"{c[k, i, j]:.6g}" for i, j, _ in entries]
            row += [f"{eigval[k, -1]:.6g}", *(f"{v:.6f}" for v in eigvec[k, :, -1])]
            row.append(f"{eigval[k, 0]:.6g}")
            if feed is not None:
                row.append(f"{feed[k]:.6g}")
            w.writerow(row)


def _load_test(args: argparse.Namespace) -> int:
    from calibration.model.stiffness import fit_joint_compliance

    with OutputSet([args.model, args.load_test], error=OutputFileError) as outputs:
        out_path = outputs.file(args.out_model, "--out-model")
        desc = load_checked_robot(args.model)
        limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
        test = read_load_test(args.load_test, desc.n_joints, limits_deg=limits)
        if not args.no_unit_check:
            model = KinematicModel.from_description(desc)
            check_measurement_units(
                test.source, test.q_deg, limits, xyz_mm=test.unloaded_mm, model=model
            )
        try:
            fit = fit_joint_compliance(
                desc, np.radians(test.q_deg), test.force_n, test.loaded_mm - test.unloaded_mm
            )
        except StiffnessError as exc:
            raise DataFileError(f"{test.source}: {exc}") from None
        fitted = fit.applied_to(desc)
        fitted.save(out_path)
    k = fit.stiffness_nmm_per_rad
    print(f"{fit.n_loads} loads, deflection residual rms {fit.rms_residual_mm * 1e3:.2f} µm")
    kept = "its stiffness is left as stated"
    for j in range(desc.n_joints):
        if not fit.excited[j]:
            print(f"  joint {j + 1}: not loaded by the test's forces ({kept})")
        elif not math.isfinite(k[j]):
            print(f"  joint {j + 1}: no measurable compliance ({kept})")
        else:
            rel = fit.std_error[j] / fit.compliance[j]
            note = "" if fit.determined[j] else f": not determined by this test ({kept})"
            print(f"  joint {j + 1}: {k[j]:.4g} N·mm/rad (± {100 * rel:.1f} %){note}")
    print(f"wrote {args.out_model}")
    return 0
