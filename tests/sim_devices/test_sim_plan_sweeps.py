"""The emulated cell runs a plan's scale-calibration sweeps (``[cell] plan_sweeps = true``,
the plan's ``sweeps.csv`` next to its ``campaign_joints.csv``), and the twin calibrates
from that campaign sampled on the simulated clock (as ``benchmarks.bench_demo_seeds``).

The plan: a KR500 with its joint ranges narrowed (``tests/daq/test_demo_planned.py``'s
``narrow_kr500``), 12 + 8 poses; its sweeps whole in view are joints 4 and 6.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.bench_plan_sweeps import (
    N_IDENTIFY,
    N_VALIDATE,
    calibrate,
    cell_text,
    force_in_view,
    map_errors_arcsec,
)
from calibration.cli import main as twin_main
from calibration.identify.campaign_files import read_planned_sweeps
from calibration.model.description import load_robot
from sim_devices.config import CellConfig
from sim_devices.plant import Plant
from tests import bad_input
from tests.daq.test_demo_planned import narrow_kr500

SIM_CELL = str(Path(sys.executable).parent / "sim-cell")


@pytest.fixture(scope="module")
def plan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``DIR`` with the robot file, the plan (``DIR/plan``) and its sweeps."""
    root = tmp_path_factory.mktemp("planned")
    (root / "narrow_kr500.toml").write_text(narrow_kr500(), encoding="utf-8")
    argv = ["plan", "--robot", str(root / "narrow_kr500.toml"), "--poses", str(N_IDENTIFY)]
    argv += ["--validate", str(N_VALIDATE), "--candidates", "400", "--out", str(root / "plan")]
    assert twin_main(argv) == 0
    return root


def _cell_text(root: Path, plan_dir: Path, *, sweeps: bool, seed: int = 1) -> str:
    """The demo's planned cell (line of sight on), ``plan_sweeps`` as given."""
    return cell_text(root / "narrow_kr500.toml", plan_dir, sweeps=sweeps, seed=seed)


def _program(text: str) -> Plant:
    return Plant.from_config(CellConfig.loads(text, source="cell"))


def test_without_plan_sweeps_or_sweeps_csv_the_program_is_unchanged(plan, tmp_path):
    root = plan
    bare = tmp_path / "bare"  # the plan without its sweeps.csv
    bare.mkdir()
    shutil.copy(root / "plan" / "campaign_joints.csv", bare)
    reference = _program(_cell_text(root, bare, sweeps=False)).trajectory
    for plan_dir, sweeps in ((root / "plan", False), (bare, True)):
        got = _program(_cell_text(root, plan_dir, sweeps=sweeps)).trajectory
        assert got.labels == reference.labels
        np.testing.assert_array_equal(got.q0_rad, reference.q0_rad)
    # the default cell (no plan) is the campaign without sweeps: plan_sweeps needs a plan
    bad_input.refused(
        tmp_path,
        [SIM_CELL, "truth", "--config", _write(tmp_path, "[cell]\nplan_sweeps = true\n"),
         "--out", "truth.toml"],
        ["[cell]", "'plan_sweeps'", "needs a plan"],
    )  # fmt: skip


def _write(tmp_path: Path, text: str, name: str = "cell.toml") -> str:
    (tmp_path / name).write_text(text, encoding="utf-8")
    return name


def test_the_cell_sweeps_the_planned_joints_at_the_plans_positions_with_the_tcp(plan):
    root = plan
    planned = read_planned_sweeps(root / "plan" / "sweeps.csv", 6)
    whole = [j for j in planned.q_deg if planned.whole(j)]
    # the narrow arm's: the others leave the reflector's cone, or (joint 6) hold the TCP
    # within ~30 mm of their axis wherever it stays in view (SweepSettings.min_radius_mm)
    assert whole == [4]
    plant = _program(_cell_text(root, root / "plan", sweeps=True))
    sched = plant.trajectory.schedule()
    default = _program(_cell_text(root, root / "plan", sweeps=False)).trajectory.schedule()
    home = np.radians(load_robot(str(root / "narrow_kr500.toml")).home)
    for j in range(1, 7):
        stops = [s for s in sched if s["label"].startswith(f"joint{j} sweep")]
        mid = np.array([0.5 * (s["arrive_s"] + s["leave_s"]) for s in stops])
        q = np.degrees(plant.joint_state(mid).q_cmd_rad)
        if j in whole:  # down and back up through the plan's stops, the TCP target
            np.testing.assert_allclose(q, np.vstack([planned.q_deg[j], planned.q_deg[j][::-1]]))
            assert {s["target"] for s in stops} == {"tcp"}
            change = [s for s in sched if s["label"] == f"joint{j} target tcp"]
            assert len(change) == 1 and change[0]["target"] == "tcp"
            k = sched.index(change[0])
            assert sched[k - 1]["label"] == f"joint{j} home 10"  # after its Home returns
            continue
        # the others: today's sweep (every other joint at Home, the target on the link)
        assert [s["label"] for s in stops] == [
            s["label"] for s in default if s["label"].startswith(f"joint{j} sweep")
        ]
        assert {s["target"] for s in stops} == {f"link:{j}"}
        others = np.delete(np.radians(q), j - 1, axis=1)
        np.testing.assert_allclose(others, np.delete(home, j - 1)[None, :].repeat(len(q), 0))


BAD_SWEEPS = [
    # (case, rows after the header, key words of the one line)
    ("joint", "7,0,{row},1,0\n", ["line 2", "column 'joint'", "6 joints"]),
    ("stop", "4,0,{row},1,0\n4,2,{row2},1,0\n", ["line 3", "column 'stop'", "expected 1"]),
    ("held", "4,0,{row},1,0\n4,1,{row_q1},1,0\n", ["line 3", "'q1_deg'", "moves it alone"]),
    ("down", "4,0,{row},1,0\n4,1,{row},1,0\n", ["line 3", "'q4_deg'", "not below"]),
    ("in_view", "4,0,{row},yes,0\n", ["line 2", "'in_view'", "'yes'"]),
    ("limits", "4,0,{row_far},1,0\n", ["line 2", "'q4_deg'", "joint limits"]),
]


@pytest.mark.parametrize(("case", "rows", "words"), BAD_SWEEPS, ids=[c[0] for c in BAD_SWEEPS])
def test_a_bad_sweeps_file_is_one_line_naming_file_line_and_column(tmp_path, case, rows, words):
    q = ",".join(f"q{j}_deg" for j in range(1, 7))
    (tmp_path / "campaign_joints.csv").write_text(
        f"pose,set,{q}\n1,identify,10,20,-30,5,40,0\n", encoding="utf-8"
    )
    body = rows.format(
        row="10,20,-30,5,40,0", row2="10,20,-30,1,40,0", row_q1="11,20,-30,3,40,0",
        row_far="10,20,-30,500,40,0",
    )  # fmt: skip
    (tmp_path / "sweeps.csv").write_text(f"joint,stop,{q},in_view,torque_nm\n{body}", "utf-8")
    cell = _write(tmp_path, '[cell]\nplan = "campaign_joints.csv"\nplan_sweeps = true\n')
    argv = [SIM_CELL, "truth", "--config", cell, "--out", "truth.toml"]
    bad_input.refused(tmp_path, argv, ["cell.toml", "'plan'", "sweeps.csv", *words])


def test_the_twin_calibrates_from_the_planned_sweeps_campaign(plan):
    root = plan
    robot = load_robot(str(root / "narrow_kr500.toml"))
    planned = read_planned_sweeps(root / "plan" / "sweeps.csv", 6)
    run, _ = calibrate(_cell_text(root, root / "plan", sweeps=True), robot)
    phases = run.measurements.phases.summary()
    for j, q in planned.q_deg.items():  # the plan's stops for its sweeps, today's otherwise
        lo, hi = robot.joints[j - 1].lower_deg + 1, robot.joints[j - 1].upper_deg - 1
        k = len(q) if planned.whole(j) else int(np.floor((hi - lo) / 2.0)) + 1
        assert phases["sweep_stops"][str(j)] == {"forward": k, "backward": k}, j
    assert all(v >= 9 for v in phases["home_returns"].values()), phases  # of 10
    assert phases["poses"] == {"identify": N_IDENTIFY, "validate": N_VALIDATE}
    assert run.success
    loop = run.calibration.final.loop
    assert loop is not None
    val = [s.mean_ap("validate") for s in loop.stages]
    assert val[-1] < 0.5 * val[0], val  # calibrated: nominal -> final


def test_sweeps_away_from_home_with_the_tcp_far_from_the_axis_calibrate_the_maps(plan, tmp_path):
    """Joints 2 and 3 swept at the plan's positions of the others (their stops flagged in
    view, the tracker's line of sight off: on this arm the cone loses some), the TCP 1.2 to
    1.9 m from their axes: their maps against the emulator's strips as good as the default
    sweeps' (5 seeds of ``bench_plan_sweeps``: 3-13″ RMS, the default's 3-17″)."""
    root = plan
    robot = load_robot(str(root / "narrow_kr500.toml"))
    forced = force_in_view(root / "plan", tmp_path / "forced", (2, 3))
    text = cell_text(root / "narrow_kr500.toml", forced, sweeps=True, seed=2, sight=False)
    run, plant = calibrate(text, robot)
    planned = read_planned_sweeps(forced / "sweeps.csv", 6)
    stops = run.measurements.phases.summary()["sweep_stops"]
    assert [stops[str(j)]["forward"] for j in (2, 3)] == [len(planned.q_deg[j]) for j in (2, 3)]
    errors = map_errors_arcsec(run, plant, robot)
    assert max(errors[1], errors[2]) < 20.0, errors  # arcsec RMS over the joint's range
    loop = run.calibration.final.loop
    assert loop is not None
    assert loop.stages[-1].mean_ap("validate") < 0.05  # mm (the default sweeps': 0.026)
