"""``twin plan``: a measurement campaign for the cell, as a joint list and robot programs.

twin plan --robot kr500 [--cell cell.toml] --poses 50 --validate 30 --out DIR
          [--region XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX] [--seed S]

writes, together and only when the plan succeeded, ``DIR/campaign_joints.csv``
(``pose,set,q1_deg..qN_deg`` in travel order, the description's angles),
``DIR/<name>.src`` + ``DIR/<name>.dat`` (KUKA KRL), ``DIR/<name>.mod`` (ABB RAPID) and
``DIR/report.md``; and the scale-calibration sweeps planned (``DIR/sweeps.csv``,
``DIR/twin_sweeps.src/.dat/.mod``; ``--no-sweeps``: not). See docs/planning.md; the
method is :mod:`calibration.plan.campaign_plan` (the sweeps: :mod:`~calibration.plan.sweep_plan`).
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from edges.options import integer
from edges.outputs import OutputSet

if TYPE_CHECKING:
    from calibration.model.cell_geometry import CellGeometry
    from calibration.model.description import RobotDescription
    from calibration.plan.robot_programs import ProgramSettings

#: The most poses either set may have (the candidate pool is this times a few).
MAX_PLAN_POSES = 2000


def _region(text: str) -> tuple[float, ...]:
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX in mm, got {text!r}"
        ) from None
    if len(values) != 6 or not all(abs(v) < 1e6 for v in values):
        raise argparse.ArgumentTypeError(
            f"expected 6 finite numbers XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX in mm, got {text!r}"
        )
    if not all(values[i] < values[i + 3] for i in range(3)):
        raise argparse.ArgumentTypeError(f"each maximum must exceed its minimum, got {text!r}")
    return values


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "plan",
        help="plan a campaign the tracker sees: joint list, KRL and RAPID programs, report",
        description="Choose identification poses in the cell's working region that the "
        "tracker sees and the arm reaches without touching the cell, best for the "
        "parameters (I-optimal over the region), plus validation poses spread over it, in "
        "the shortest travel order. See docs/planning.md.",
    )
    p.add_argument("--robot", required=True, help="nominal robot: preset or .toml")
    p.add_argument("--cell", help="cell.toml (default: the emulated cell)")
    p.add_argument(
        "--poses", type=integer(1, MAX_PLAN_POSES), required=True, help="identification poses"
    )
    p.add_argument(
        "--validate", type=integer(0, MAX_PLAN_POSES), required=True, help="validation poses"
    )
    p.add_argument("--out", required=True, metavar="DIR", help="directory for the files")
    p.add_argument(
        "--region",
        type=_region,
        metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
        help="the working region in the base frame, mm (default: the cell's [region])",
    )
    p.add_argument("--seed", type=integer(0, 2**32 - 1), default=1, help="seed (1)")
    p.add_argument(
        "--candidates",
        type=integer(10, 100_000),
        default=20000,  # PlanSettings().n_candidates, not imported before the arguments pass
        help="candidate poses in view to choose from (20000)",
    )
    p.add_argument(
        "--criterion",
        choices=("I", "D"),
        default="I",
        help="I: mean prediction variance over the region (default); D: the O1 index",
    )
    p.add_argument(
        "--passes",
        type=int,
        choices=(1, 2),
        default=2,
        help="2: forward then back (every other pose out, the rest back), so a drift in "
        "time is not taken for geometry (default); 1: one pass, the shortest tour",
    )
    p.add_argument(
        "--no-sweeps",
        action="store_true",
        help="leave the scale-calibration sweeps out (sweeps.csv, twin_sweeps.*)",
    )
    p.set_defaults(func=run_plan)


def run_plan(args: argparse.Namespace) -> int:
    """Read the robot and the cell, plan, write the five files together (long for the
    files: each is one line of staging)."""
    from dataclasses import replace

    from calibration.errors import OutputFileError, PlanError
    from calibration.model.cell_geometry import (
        EMULATOR_TABLES,
        CellGeometrySpec,
        RegionSection,
        read_cell_geometry,
        resolve,
    )
    from calibration.model.description import load_robot
    from calibration.plan.campaign_plan import PlanSettings, plan_campaign
    from calibration.plan.plan_report import plan_report
    from calibration.plan.robot_programs import ProgramSettings
    from edges.toml_schema import parse_toml_file

    robot_file = args.robot if Path(args.robot).exists() else None
    with OutputSet([robot_file, args.cell], error=OutputFileError) as outputs:
        staged = outputs.directory(args.out, "--out")
        robot = load_robot(args.robot)
        spec = CellGeometrySpec()
        if args.cell:
            doc = parse_toml_file(args.cell, PlanError, "a cell file")
            spec = read_cell_geometry(doc, args.cell, PlanError, others=EMULATOR_TABLES)
        if args.region:
            lo, hi = args.region[:3], args.region[3:]
            spec = replace(spec, region=RegionSection(min_mm=lo, max_mm=hi))
        geometry = resolve(spec, robot)
        settings = PlanSettings(
            n_identify=args.poses,
            n_validate=args.validate,
            n_candidates=args.candidates,
            seed=args.seed,
            criterion=args.criterion,
            passes=args.passes,
        )
        plan = plan_campaign(robot, geometry, settings)
        prog = ProgramSettings()
        labels = [f"P{i + 1}" for i in range(len(plan.q_rad))]
        q_deg = np.degrees(plan.q_rad)
        via = {int(i) for i in plan.travel.via_home if i < len(labels)}
        staged.mkdir(parents=True, exist_ok=True)
        (staged / "campaign_joints.csv").write_text(
            joints_csv(q_deg, plan.is_identify), encoding="utf-8"
        )
        _write_programs(staged, robot, q_deg, labels, via, prog)
        report = plan_report(robot, geometry, settings, plan, prog)
        if not args.no_sweeps:
            report += _write_sweeps(staged, robot, geometry, args.seed)
        (staged / "report.md").write_text(report, encoding="utf-8")
    t = plan.travel
    print(
        f"wrote {args.out}: {int(plan.is_identify.sum())} identify + "
        f"{int((~plan.is_identify).sum())} validate poses, travel {t.time_s:.0f} s "
        f"({t.time_s / t.random_time_s:.2f}x a random order)"
    )
    return 0


def _write_sweeps(staged: Path, robot: RobotDescription, geometry: CellGeometry, seed: int) -> str:
    """Plan the scale-calibration sweeps, stage ``sweeps.csv`` and ``twin_sweeps.*``;
    the report's section on them."""
    from calibration.plan.robot_programs import ProgramSettings
    from calibration.plan.sweep_plan import (
        SweepSettings,
        plan_sweeps,
        sweep_program_poses,
        sweep_report,
        sweeps_csv,
    )

    sweeps = plan_sweeps(robot, geometry, SweepSettings(seed=seed))
    (staged / "sweeps.csv").write_text(sweeps_csv(sweeps), encoding="utf-8")
    # the method's sweeps: 3 % speed, a stop every 2° long enough for the tracker
    prog = ProgramSettings(
        name="twin_sweeps",
        krl_velocity_pct=3,
        rapid_speed="v20",
        dwell_s=1.0,
        content="sweep stops, each joint forward then back",
    )
    q_deg, labels, via = sweep_program_poses(sweeps)
    _write_programs(staged, robot, q_deg, labels, via, prog)
    lost = [s.joint for s in sweeps.sweeps if not s.whole]
    if lost:
        print(f"sweeps: joints {lost} not swept whole in view (see report.md)")
    return sweep_report(robot, sweeps)


def _write_programs(
    staged: Path,
    robot: RobotDescription,
    q_deg: NDArray[np.float64],
    labels: list[str],
    via: set[int],
    prog: ProgramSettings,
) -> None:
    """Stage ``prog``'s KRL ``.src``/``.dat`` and RAPID ``.mod`` for the poses ``q_deg``
    ``(N, 6)``; none for an arm that is not 6-axis (said once, on stdout)."""
    from calibration.plan.robot_programs import krl_program, programs_refused, rapid_module

    refused = programs_refused(robot)
    if refused is not None:
        print(f"{prog.name}: no KRL or RAPID program: {refused}")
        return
    src, dat = krl_program(robot, q_deg, labels, via, prog)
    (staged / f"{prog.name}.src").write_text(src, encoding="utf-8")
    (staged / f"{prog.name}.dat").write_text(dat, encoding="utf-8")
    (staged / f"{prog.name}.mod").write_text(
        rapid_module(robot, q_deg, labels, via, prog), encoding="utf-8"
    )


def joints_csv(q_deg: NDArray[np.float64], is_identify: NDArray[np.bool_]) -> str:
    """``campaign_joints.csv``: ``pose,set,q1_deg..qN_deg``, pose ids 1.. in the given
    (travel) order, angles as :func:`calibration.plan.robot_programs.format_angle` writes them."""
    from calibration.plan.robot_programs import format_angle

    out = io.StringIO()
    n = q_deg.shape[1]
    out.write("pose,set," + ",".join(f"q{j + 1}_deg" for j in range(n)) + "\n")
    for i, (row, ident) in enumerate(zip(q_deg, is_identify, strict=True)):
        values = ",".join(format_angle(v) for v in row)
        out.write(f"{i + 1},{'identify' if ident else 'validate'},{values}\n")
    return out.getvalue()
