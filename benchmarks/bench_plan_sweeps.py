"""The planned scale-calibration sweeps on the emulated cell: what they do to the twin.

A narrowed KR500 (``tests/daq/test_demo_planned.py``'s ranges) is planned (``twin plan
--poses 12 --validate 8 --candidates 400``, seed 1, with its sweeps); its campaign runs on
the emulated cell with the demo's planned-cell settings (line of sight on, gravity
deflection undeclared, 160x, 1 kHz), sampled on the **simulated clock** as
:mod:`benchmarks.bench_demo_seeds` does, then ``run_twin``. Per cell seed, three variants:

* ``default``: ``[cell] plan_sweeps = false`` (every sweep the default one);
* ``planned``: ``plan_sweeps = true`` (the joints the plan sweeps whole in view, 4 and 6 on
  this arm, at the plan's positions with the TCP reflector);
* ``planned 2,3``: the plan's sweeps of joints 2 and 3 (not whole in view on this arm)
  flagged in view, the others not, the tracker's line of sight off: sweeps away from Home
  with a reflector far from the swept axis.

Printed per row: the sweep stops found per joint, Home returns, poses, the validation mean
per stage (mm), each joint fit round's final validation mean (mm) and what its loop added,
and each scale map's error against the emulator's strip (the map read at the strip's ideal
counts over the joint's range less the true angle: RMS about its mean, arcsec), of the
twin (``map_rms_arcsec``) and of each round (``rounds_map_rms_arcsec``).

    python -m benchmarks.bench_plan_sweeps [--seeds 1-5] [--poses 12 --validate 8]
        [--variants default planned "planned 2,3"]

With 12 + 8 poses the loop adds no gravity term; ``--poses 40 --validate 40`` gives it
enough poses to find one (the gravity term's sweep reference then matters).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_demo_seeds import RATE_HZ, TRACKER_STATUS, _SampledPlant, _stream
from calibration.model.description import RobotDescription, load_robot
from calibration.twin.pairing import VALID_BIT
from calibration.twin.phase_detection import PhaseOptions
from calibration.twin.streams import CellStreams
from calibration.twin.twin_run import TwinRun, run_twin
from daq.demo import sim_config_text
from sim_devices.config import CellConfig
from sim_devices.tracker import TrackerInstrument

SPEED = 160.0
N_IDENTIFY, N_VALIDATE = 12, 8


def cell_text(robot: Path, plan: Path, *, sweeps: bool, seed: int, sight: bool = True) -> str:
    """The demo's planned cell (``daq.demo --plan``) for ``plan``'s ``campaign_joints.csv``,
    ``plan_sweeps`` as given, the tracker's line of sight on or off."""
    text = sim_config_text(
        str(robot), seed, SPEED, "gravity_deflection",
        encoders=False, rate_hz=RATE_HZ, plan=str(plan / "campaign_joints.csv"),
    )  # fmt: skip
    keys = f'program = "campaign"\nplan_sweeps = {str(sweeps).lower()}'
    text = text.replace('program = "campaign"', keys)
    return text if sight else text.replace("line_of_sight = true", "line_of_sight = false")


def sampled(text: str) -> tuple[CellStreams, _SampledPlant]:
    """The cell's grating and tracker streams on the simulated clock, and its plant."""
    config = CellConfig.loads(text, source="cell")
    plant = _SampledPlant.from_config(config)
    wall = np.arange(0.0, plant.trajectory.end_s / SPEED + 2.0, 1.0 / RATE_HZ)
    state = plant.joint_state(plant.clock.sim_s(wall))
    rng = np.random.default_rng(plant.cell.seed + 11)  # the grating reader's generator
    counts = plant.grating_counts(state.q_out_rad, rng, config.grating.noise_counts)
    names = [f"grating{j}_counts" for j in range(1, counts.shape[1] + 1)]
    valid = np.full(counts.shape, VALID_BIT, dtype=np.uint16)
    grating = _stream("cell/grating/samples", "grating", names, wall, counts, valid)
    points, codes = TrackerInstrument(plant, config.tracker, config.effects).measure(wall)
    status = np.array([TRACKER_STATUS[c] for c in range(3)], dtype=np.uint16)[codes]
    tracker = _stream(
        "cell/tracker/samples", "tracker", ["x_mm", "y_mm", "z_mm"],
        wall, points, np.repeat(status[:, None], 3, axis=1),
    )  # fmt: skip
    return CellStreams(grating, tracker, None, "planned cell, simulated"), plant


def calibrate(
    text: str, robot: RobotDescription, n_identify: int = N_IDENTIFY
) -> tuple[TwinRun, _SampledPlant]:
    streams, plant = sampled(text)
    options = PhaseOptions(identify_count=n_identify)
    return run_twin(streams, robot, phase_options=options), plant


def map_errors_arcsec(
    run: TwinRun, plant: _SampledPlant, robot: RobotDescription, round_index: int = -1
) -> list[float]:
    """Each joint's scale map (of joint fit round ``round_index``, the last by default)
    against the emulator's strip: RMS about the mean, arcsec."""
    by_joint = {r.joint: r.scale for r in run.calibration.rounds[round_index].scales}
    out = []
    for j, joint in enumerate(robot.joints):
        q = np.radians(np.linspace(joint.lower_deg, joint.upper_deg, 400))
        read = by_joint[j + 1].counts_to_joint_deg(plant.cell.strips[j].ideal_counts(q))
        err = (read - np.degrees(q)) * 3600.0
        out.append(round(float(np.std(err)), 2))
    return out


def row(variant: str, seed: int, run: TwinRun, plant: _SampledPlant) -> dict[str, Any]:
    phases = run.measurements.phases.summary()
    loop = run.calibration.final.loop
    stages = [] if loop is None else [round(s.mean_ap("validate"), 4) for s in loop.stages]
    rounds = [r.loop for r in run.calibration.rounds]
    return {
        "variant": variant,
        "seed": seed,
        "stops": {j: p["forward"] for j, p in phases["sweep_stops"].items()},
        "home_returns": phases["home_returns"],
        "poses": phases["poses"],
        "validate_mean_mm": stages,
        "rounds_validate_mm": [
            None if r is None else round(r.stages[-1].mean_ap("validate"), 4) for r in rounds
        ],
        "rounds_added": [[] if r is None else [s.label for s in r.stages[2:]] for r in rounds],
        "map_rms_arcsec": map_errors_arcsec(run, plant, run.robot),
        "rounds_map_rms_arcsec": [
            map_errors_arcsec(run, plant, run.robot, k) for k in range(len(rounds))
        ],
    }


def force_in_view(plan: Path, out: Path, joints: tuple[int, ...]) -> Path:
    """A copy of ``plan`` in ``out`` whose ``sweeps.csv`` flags the stops of ``joints`` in
    view and every other stop out of view (the cell then runs those joints' planned
    sweeps only); returns ``out``."""
    out.mkdir()
    (out / "campaign_joints.csv").write_bytes((plan / "campaign_joints.csv").read_bytes())
    lines = (plan / "sweeps.csv").read_text(encoding="utf-8").splitlines()
    fields = [x.split(",") for x in lines[1:]]
    for f in fields:
        f[-2] = "1" if int(f[0]) in joints else "0"
    text = "\n".join([lines[0], *(",".join(f) for f in fields)]) + "\n"
    (out / "sweeps.csv").write_text(text, encoding="utf-8")
    return out


VARIANTS = ("default", "planned", "planned 2,3")


def rows(
    seeds: list[int],
    poses: tuple[int, int] = (N_IDENTIFY, N_VALIDATE),
    variants: tuple[str, ...] = VARIANTS,
) -> list[dict[str, Any]]:
    """The module docstring's rows for the cell seeds ``seeds`` (the plan made here, of
    ``poses`` identification + validation poses), the ``variants`` named (of
    :data:`VARIANTS`) only."""
    from calibration.cli import main as twin_main
    from tests.daq.test_demo_planned import narrow_kr500

    out: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        robot_file = root / "narrow_kr500.toml"
        robot_file.write_text(narrow_kr500(), encoding="utf-8")
        plan = root / "plan"
        argv_plan = ["plan", "--robot", str(robot_file), "--poses", str(poses[0])]
        argv_plan += ["--validate", str(poses[1]), "--candidates", "400", "--out", str(plan)]
        if twin_main(argv_plan) != 0:
            raise RuntimeError("twin plan failed")
        forced = force_in_view(plan, root / "forced", (2, 3))
        robot = load_robot(str(robot_file))
        table = (
            ("default", plan, False, True),
            ("planned", plan, True, True),
            ("planned 2,3, no line of sight", forced, True, False),
        )
        chosen = [v for v, key in zip(table, VARIANTS, strict=True) if key in variants]
        for seed in seeds:
            for name, where, sweeps, sight in chosen:
                text = cell_text(robot_file, where, sweeps=sweeps, seed=seed, sight=sight)
                out.append(row(name, seed, *calibrate(text, robot, poses[0])))
                print(json.dumps(out[-1]), flush=True)
    return out


def run(quick: bool) -> list[dict[str, Any]]:
    """``python -m benchmarks``'s entry: cell seed 1 (quick) or 1-5."""
    return rows([1] if quick else list(range(1, 6)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1-5", help="cell seeds, a-b")
    parser.add_argument("--poses", type=int, default=N_IDENTIFY, help="identification poses")
    parser.add_argument("--validate", type=int, default=N_VALIDATE, help="validation poses")
    parser.add_argument(
        "--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS),
        help="the variants to run (default: all three)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    a, _, b = args.seeds.partition("-")
    seeds = list(range(int(a), int(b or a) + 1))
    rows(seeds, (args.poses, args.validate), tuple(args.variants))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
