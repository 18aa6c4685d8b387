"""``twin plan`` (real processes) and the cell's geometry: the files, their contracts, the
emulator's own view of the plan, the emulated tracker's line of sight, bad input."""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.cli.plan import register
from calibration.model.cell_geometry import CellGeometrySpec, resolve
from calibration.model.description import load_robot
from calibration.plan.campaign_plan import (
    PlanSettings,
    candidate_poses,
    design_problem,
    joint_speeds_rad_s,
    observability,
    order_drift,
    select_identification,
)
from calibration.plan.robot_programs import read_krl, read_rapid
from calibration.plan.travel_order import leg_times_s, tour_time_s, travel_order
from sim_devices.config import CellConfig
from sim_devices.plant import Plant
from sim_devices.tracker import TrackerInstrument
from sim_devices.tracker_view import cell_geometry, true_collision_codes, true_view_codes
from sim_devices.truth import TrueCell

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]
# the sweeps (twin plan's default) are tests/calibration/test_sweep_plan.py's
SMALL = ["--poses", "12", "--validate", "6", "--candidates", "600", "--no-sweeps"]


def twin_plan(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "calibration.cli", "plan", *args],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=110,
    )  # fmt: skip


def read_joints(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


@pytest.fixture(scope="module")
def planned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("plan")
    r = twin_plan("--robot", "kr500", *SMALL, "--seed", "3", "--out", "out", cwd=work)
    assert r.returncode == 0, r.stderr
    return work / "out"


def test_joint_list_contract(planned: Path) -> None:
    header, rows = read_joints(planned / "campaign_joints.csv")
    assert header == ["pose", "set", *[f"q{j}_deg" for j in range(1, 7)]]
    sets = [r["set"] for r in rows]
    assert sets.count("identify") == 12 and sets.count("validate") == 6
    assert [int(r["pose"]) for r in rows] == list(range(1, 19))
    robot = load_robot("kr500")
    q = np.array([[float(r[f"q{j}_deg"]) for j in range(1, 7)] for r in rows])
    lo = np.array([j.lower_deg for j in robot.joints]) + PlanSettings().limit_margin_deg
    hi = np.array([j.upper_deg for j in robot.joints]) - PlanSettings().limit_margin_deg
    assert np.all((q >= lo - 1e-5) & (q <= hi + 1e-5))
    assert (planned / "report.md").read_text().count("I-optimality") >= 1


def test_programs_parse_back_to_the_joint_list(planned: Path) -> None:
    _, rows = read_joints(planned / "campaign_joints.csv")
    q = np.array([[float(r[f"q{j}_deg"]) for j in range(1, 7)] for r in rows])
    robot = load_robot("kr500")
    src = (planned / "twin_plan.src").read_text()
    dat = (planned / "twin_plan.dat").read_text()
    mod = (planned / "twin_plan.mod").read_text()
    names_k, q_krl = read_krl(robot, src, dat)
    names_r, q_rapid = read_rapid(robot, mod)
    # a move through Home adds no pose: the programs visit exactly the listed ones, in order
    assert names_k == names_r == [f"P{r['pose']}" for r in rows]
    assert np.abs(q_krl - q).max() < 1e-9
    assert np.abs(q_rapid - q).max() < 1e-9
    assert "E6AXIS" in dat and "PTP XP1" in src
    assert "MoveAbsJ jP1, v200, fine, tool0;" in mod
    # written in the controller's convention (the preset's: A1 = -q1, A2 = q2 - 90)
    line = next(x for x in dat.splitlines() if "XP1=" in x)
    a = [float(p.split()[1]) for p in line.split("{")[1].split(",")[:6]]
    assert a[0] == pytest.approx(-q[0, 0], abs=1e-9)
    assert a[1] == pytest.approx(q[0, 1] - 90.0, abs=1e-9)


@pytest.mark.parametrize("seed", [3, 8])
def test_plan_in_view_and_clear_by_the_emulators_geometry(planned: Path, seed: int) -> None:
    """The twin planned on the nominal robot and a tape-measured station; the emulator's
    truth (its true arm, its tracker where it really is) must agree on every pose."""
    _, rows = read_joints(planned / "campaign_joints.csv")
    q = np.radians([[float(r[f"q{j}_deg"]) for j in range(1, 7)] for r in rows])
    cell = TrueCell.create(load_robot("kr500"), seed)
    geometry = cell_geometry(cell, CellConfig().geometry)
    assert np.all(true_view_codes(cell, geometry, q) == 0)
    assert np.all(true_collision_codes(cell, geometry, q) == 0)


def test_same_seed_same_file(planned: Path, tmp_path: Path) -> None:
    r = twin_plan("--robot", "kr500", *SMALL, "--seed", "3", "--out", "again", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    first = (planned / "campaign_joints.csv").read_bytes()
    assert (tmp_path / "again" / "campaign_joints.csv").read_bytes() == first
    r = twin_plan("--robot", "kr500", *SMALL, "--seed", "4", "--out", "other", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "other" / "campaign_joints.csv").read_bytes() != first


def test_passes_one_measures_the_same_poses_in_one_pass(planned: Path, tmp_path: Path) -> None:
    """The default plan (forward then back) and ``--passes 1`` hold the same poses, each set
    whole, in other orders (ids 1.. in each order), and each report says its order."""
    args = ("--robot", "kr500", *SMALL, "--seed", "3", "--passes", "1", "--out", "one")
    r = twin_plan(*args, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    header, rows = read_joints(tmp_path / "one" / "campaign_joints.csv")
    _, default = read_joints(planned / "campaign_joints.csv")
    assert [int(x["pose"]) for x in rows] == list(range(1, len(default) + 1))
    key = lambda x: (x["set"], *(x[c] for c in header[2:]))  # noqa: E731
    assert sorted(map(key, rows)) == sorted(map(key, default))
    assert list(map(key, rows)) != list(map(key, default))
    assert "One pass: " in (tmp_path / "one" / "report.md").read_text()
    report = (planned / "report.md").read_text()
    assert "Forward then back (`--passes 2`)" in report and "from pose " in report
    assert "1 mm over the campaign would leave " in report and "(one pass: " in report


def test_travel_order_beats_random_orders() -> None:
    rng = np.random.default_rng(5)
    q = rng.uniform(-2.0, 2.0, size=(60, 6))
    speeds = np.full(6, 1.5)
    order = travel_order(q, np.zeros(6), speeds, np.random.default_rng(1))
    assert sorted(order.order.tolist()) == list(range(60))
    times = leg_times_s(np.vstack([np.zeros(6), q]), speeds)
    assert order.time_s == pytest.approx(tour_time_s(times, np.append(0, order.order + 1)))
    assert order.time_s < 0.6 * order.random_time_s


def _median_time_gap_to_nearest(q: np.ndarray, order: np.ndarray, speeds: np.ndarray) -> float:
    """Median over poses of how many poses apart in time a pose and its nearest one (by
    leg time) are measured."""
    rank = np.empty(len(q), dtype=int)
    rank[order] = np.arange(len(q))
    legs = leg_times_s(q, speeds)
    np.fill_diagonal(legs, np.inf)
    return float(np.median(np.abs(rank - rank[legs.argmin(axis=1)])))


def test_forward_then_back_measures_neighbours_half_a_campaign_apart(planned: Path) -> None:
    """One pass measures a pose's nearest neighbour next to it in time, so a drift in time
    follows the pose; forward then back measures it about half the campaign later, on
    both a planned KR500 campaign's poses and random joint vectors, at a travel time
    still well under a random order's."""
    rng = np.random.default_rng(5)
    kr500 = load_robot("kr500")
    speeds_kr = np.radians([j.max_speed_deg_s for j in kr500.joints])
    _, rows = read_joints(planned / "campaign_joints.csv")
    plan_q = np.radians([[float(r[f"q{j}_deg"]) for j in range(1, 7)] for r in rows])
    for q, speeds, most in (
        (rng.uniform(-2.0, 2.0, size=(60, 6)), np.full(6, 1.5), 0.8),
        (plan_q, speeds_kr, 0.8),
    ):
        one = travel_order(q, np.zeros(6), speeds, np.random.default_rng(1), passes=1)
        two = travel_order(q, np.zeros(6), speeds, np.random.default_rng(1), passes=2)
        assert sorted(two.order.tolist()) == list(range(len(q)))
        times = leg_times_s(np.vstack([np.zeros(6), q]), speeds)
        assert two.time_s == pytest.approx(tour_time_s(times, np.append(0, two.order + 1)))
        assert _median_time_gap_to_nearest(q, one.order, speeds) <= 2
        assert _median_time_gap_to_nearest(q, two.order, speeds) >= len(q) / 4
        assert one.time_s < two.time_s < most * two.random_time_s
        # the identification poses among them, forward then back on their own
        ident = np.random.default_rng(2).random(len(q)) < 0.7
        by_set = travel_order(q, np.zeros(6), speeds, np.random.default_rng(1), 2, ident)
        in_id = by_set.order[ident[by_set.order]]  # the identification poses in time order
        gap = _median_time_gap_to_nearest(q[in_id], np.arange(len(in_id)), speeds)
        assert gap >= len(in_id) / 4
        way_out = by_set.order[: by_set.back_from]
        for in_set in (ident, ~ident):  # half of each set either way, within one
            assert abs(2 * int(in_set[way_out].sum()) - int(in_set.sum())) <= 1
        assert one.back_from == -1 and 0 < two.back_from < len(q)


def test_drift_aware_split_travels_less_and_leaves_no_more_drift_bias() -> None:
    """On a planned KR500 campaign the planner's drift criterion ranks the one-pass tour
    (time a smooth function of the pose) above random orders and forward then back below
    them; choosing which of each pair goes back by it gives an order whose travel and
    drift bias are both at most the alternate split's, and shorter travel on most seeds."""
    kr500 = load_robot("kr500")
    geometry = resolve(CellGeometrySpec(), kr500)
    speeds, home = joint_speeds_rad_s(kr500), np.radians(kr500.home)
    shorter = 0
    for seed in (1, 3, 4):  # 50 poses: with 30 the bias is the variance's, any order's
        settings = PlanSettings(n_identify=50, n_validate=10, n_candidates=1500, seed=seed)
        cands = candidate_poses(kr500, geometry, settings, np.random.default_rng(seed))
        obs = observability(kr500, geometry, cands.q_rad, settings)
        ident = select_identification(obs, 50, settings).indices
        rows = np.concatenate([ident, np.setdiff1d(np.arange(len(cands.q_rad)), ident)[:10]])
        drift = order_drift(design_problem(obs), ident, len(rows))
        group = (np.arange(len(rows)) < 50).astype(int)
        q = cands.q_rad[rows]
        orders = [
            travel_order(q, home, speeds, np.random.default_rng(1), p, group, d)
            for p, d in ((1, None), (2, None), (2, drift))
        ]
        one, alternate, aware = (drift(o.order) for o in orders)
        assert orders[2].drift_bias[:2] == (aware, one)
        rng = np.random.default_rng(seed)
        random = np.mean([drift(rng.permutation(len(rows))) for _ in range(30)])
        assert alternate < random < one
        assert aware <= alternate and orders[2].time_s <= orders[1].time_s
        assert sorted(orders[2].order.tolist()) == list(range(len(rows)))
        shorter += orders[2].time_s < 0.97 * orders[1].time_s
    assert shorter >= 2


def test_emulated_tracker_breaks_the_beam_out_of_view() -> None:
    """With line_of_sight, exactly the samples whose reflector the cell hides are broken
    (status 1, no point); without it, none are."""
    text = '[cell]\nprogram = "random"\n[tracker]\ntarget = "tcp"\nline_of_sight = '
    wall = np.linspace(0.0, 300.0, 1500)
    for on in (True, False):
        cfg = CellConfig.loads(text + ("true" if on else "false") + "\n")
        plant = Plant.from_config(cfg)
        inst = TrackerInstrument(plant, cfg.tracker, cfg.effects)
        pts, status = inst.measure(wall)
        q = plant.joint_state(plant.clock.sim_s(wall)).q_out_rad
        hidden = true_view_codes(plant.cell, cell_geometry(plant.cell, cfg.geometry), q) != 0
        assert 0 < hidden.sum() < len(wall)  # the random program shows both
        if on:
            assert np.array_equal(status == 1, hidden)
            assert np.isnan(pts[hidden]).all() and np.isfinite(pts[~hidden]).all()
        else:
            assert not (status == 1).any()


def test_default_cell_states_the_geometry() -> None:
    robot = load_robot("kr500")
    g = resolve(CellGeometrySpec(), robot)
    cell = TrueCell.create(robot, 1)
    # the station is where the emulator's tracker is, up to the base guess's error
    from sim_devices.tracker_view import true_station_mm

    assert np.linalg.norm(g.station_mm - true_station_mm(cell)) < 200.0
    assert g.cone_half_angle_deg == 30.0 and np.allclose(g.axis_flange, [0, 0, 1])
    assert g.obstacles and np.all(g.region_lo < g.region_hi)


BAD = {
    "unreachable region": (["--region", "20000,20000,0,21000,21000,500"], "", "no pose the arm"),
    "tracker sees nothing": ([], "[station]\nx_mm = 90000.0\ny_mm = 0\nz_mm = 0\n", "sees no pose"),
    "N over candidates": (["--poses", "50", "--candidates", "20"], "", "--poses 50"),
    "unknown cell key": ([], "[reflector]\ncone_deg = 30\n", "cone_deg"),
    "unknown cell table": ([], "[tracker_station]\nx_mm = 1\n", "tracker_station"),
    "cone out of range": ([], "[reflector]\ncone_half_angle_deg = 95\n", "cone_half_angle_deg"),
    "region option": (["--region", "1,2,3"], "", "--region"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_one_line_exit_2_nothing_written(case: str, tmp_path: Path) -> None:
    extra, cell, needle = BAD[case]
    args = ["--robot", "kr500", "--validate", "3"]
    if "--poses" not in extra:
        args += ["--poses", "12", "--candidates", "200"]
    if cell:
        (tmp_path / "cell.toml").write_text(cell)
        args += ["--cell", "cell.toml"]
    before = sorted(p.name for p in tmp_path.iterdir())
    r = twin_plan(*args, *extra, "--out", "out", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_the_commands_candidate_count_is_the_planners_default() -> None:
    # the command states it as a literal (it parses before the planner is imported)
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["plan", "--robot", "kr500", "--poses", "5", "--validate", "0",
                              "--out", "x"])  # fmt: skip
    assert args.candidates == PlanSettings().n_candidates
