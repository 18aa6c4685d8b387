"""`twin plan`, the closed loop and `twin compensate` on an arm without a spherical wrist
(the UR family: joints 2, 3, 4 parallel, the wrist offset by d5), whose inverse
kinematics has no closed form here: the numeric, multi-start solve
(:mod:`calibration.model.numeric_ik`), checked by forward kinematics and by the
emulator's own cell geometry."""

from __future__ import annotations

import csv
import tomllib
from pathlib import Path

import numpy as np
import pytest

from benchmarks.bench_plan import ADMITTED, EFFECTS, PlannedArm, seed_campaigns
from calibration.effects.calibrate import calibrate
from calibration.effects.model_effects import predict_tcp
from calibration.errors import PlanError
from calibration.model.cell_geometry import (
    CellGeometrySpec,
    link_points,
    read_cell_geometry,
    resolve,
)
from calibration.model.description import RobotDescription, load_robot
from calibration.model.ik_results import JointLimits
from calibration.model.kinematics import KinematicModel, flange_poses
from calibration.model.numeric_ik import NumericIK, jacobian_conditioning, multi_start_ik
from calibration.model.pieper_closed_form import has_spherical_approximation
from calibration.twin.compensation import compensate, rotation_xyz
from sim_devices.pose_campaign import CampaignSettings, measure_campaign
from sim_devices.tracker_view import cell_geometry, true_collision_codes, true_view_codes
from sim_devices.truth import TrueCell
from tests.calibration.test_campaign_plan import ROOT, read_joints, twin_plan

# Universal Robots' published UR10 D-H in this project's modified form (a_mm, alpha_deg,
# d_mm), the reflector 93 mm out on the flange axis; the base puts the tracker 2.5 m in
# front of the robot (the emulator's tracker stands where the description's [base] says)
UR10 = [(0.0, 0.0, 127.3), (0.0, 90.0, 0.0), (-612.0, 0.0, 0.0), (-572.3, 0.0, 163.941)]
UR10 += [(0.0, 90.0, 115.7), (0.0, -90.0, 92.2)]
CELL = """
[floor]
z_mm = -400
[region]
min_mm = [300, -600, -200]
max_mm = [900, 600, 700]
[[obstacle]]
name = "cabinet"
min_mm = [-400, 1400, -400]
max_mm = [400, 1800, 200]
"""


def write_ur10(path: Path, home: str = "") -> Path:
    lines = ['name = "UR10 (nominal)"', *([f"home_deg = {home}"] if home else [])]
    lines += ["[base]", "x_mm = -2500.0", "y_mm = 0.0"]
    lines += ["z_mm = -300.0", "rx_deg = 0.0", "ry_deg = 0.0", "rz_deg = 0.0"]
    lines += ["[tool]", "x_mm = 0.0", "y_mm = 0.0", "z_mm = 93.0"]
    for a, alpha, d in UR10:
        lines += ["[[joint]]", f"a_mm = {a}", f"alpha_deg = {alpha}", f"d_mm = {d}"]
        lines += ["theta_offset_deg = 0.0", "lower_deg = -360.0", "upper_deg = 360.0"]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def ur10(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_ur10(tmp_path_factory.mktemp("ur10") / "ur10.toml")


def test_multi_start_ik_reaches_the_poses_of_a_ur10(ur10: Path) -> None:
    robot = load_robot(str(ur10))
    model = KinematicModel.from_description(robot)
    assert not has_spherical_approximation(model)
    rng = np.random.default_rng(5)
    q_true = rng.uniform(-np.pi, np.pi, size=(300, 6))
    q_true = q_true[jacobian_conditioning(model, q_true) > 0.01]
    t = flange_poses(model, q_true, world=False)
    limits = JointLimits.from_description(robot)
    ik = multi_start_ik(model, t[:, :3, :3], t[:, :3, 3], limits, rng, n_starts=8)
    assert_poses_reached(model, ik, t, limits)


def assert_poses_reached(
    model: KinematicModel, ik: NumericIK, flange: np.ndarray, limits: JointLimits
) -> None:
    """Most poses (``flange`` ``(N, 4, 4)``, base frame) reached from one of the starts
    (the rest: starts that ran into a singularity); every solution reported reproduces its
    pose by forward kinematics, inside the limits."""
    assert ik.within_limits.any(axis=1).mean() > 0.9
    q = ik.solutions_rad[ik.within_limits]
    rows = np.nonzero(ik.within_limits)[0]
    back = flange_poses(model, q, world=False)
    assert np.abs(back[:, :3, 3] - flange[rows, :3, 3]).max() < 1e-5
    assert np.abs(back[:, :3, :3] - flange[rows, :3, :3]).max() < 1e-8
    assert np.all((q >= limits.lower_rad) & (q <= limits.upper_rad))


def test_twin_plan_on_a_ur10_in_view_and_clear_by_the_emulator(ur10: Path, tmp_path: Path) -> None:
    (tmp_path / "cell.toml").write_text(CELL)
    args = ["--poses", "12", "--validate", "6", "--candidates", "500", "--no-sweeps"]
    r = twin_plan("--robot", str(ur10), "--cell", "cell.toml", *args, "--out", "o", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _, rows = read_joints(tmp_path / "o" / "campaign_joints.csv")
    assert [row["set"] for row in rows].count("identify") == 12 and len(rows) == 18
    q = np.radians([[float(row[f"q{j}_deg"]) for j in range(1, 7)] for row in rows])
    assert np.all(np.abs(np.degrees(q)) <= 358.0 + 1e-5)
    robot = load_robot(str(ur10))
    model = KinematicModel.from_description(robot)
    flange = flange_poses(model, q, world=False)
    tcp = flange[:, :3, :3] @ model.tool_mm + flange[:, :3, 3]
    assert np.all((tcp >= [300, -600, -200]) & (tcp <= [900, 600, 700]))
    spec = read_cell_geometry(tomllib.loads(CELL), "cell.toml", PlanError)
    for seed in (1, 4):
        cell = TrueCell.create(robot, seed)
        geometry = cell_geometry(cell, spec)
        assert np.all(true_view_codes(cell, geometry, q) == 0)
        assert np.all(true_collision_codes(cell, geometry, q) == 0)
    report = (tmp_path / "o" / "report.md").read_text()
    assert "inverse kinematics numeric" in report
    # the reflector on joint 6's axis: its cyclic error is stated as not designed for
    assert "Not designed for" in report and "cyclic error of joint 6" in report
    # its rounding-noise column no longer swamps the design (O1 was 0, every σ 0)
    assert float(report.split("| O1 (D-optimality) | ")[1].split(" |")[0]) > 1.0
    assert "| 0 µm |" not in report and "RuntimeWarning" not in r.stderr
    with (tmp_path / "o" / "campaign_joints.csv").open() as f:
        assert next(csv.reader(f))[0] == "pose"


def test_the_loop_retries_a_failed_step_from_the_last_stage_on_a_ur10() -> None:
    """On the emulated UR10's random 150 poses (seed 1) the gravity term's re-identification
    from the nominal start (its base ~66 mm off) stalls ~58 mm off its own points, though
    the geometric fit converged from there. The loop, offered that term without its
    validation guard (``ADMITTED``), must not keep such a step (it kept a twin 59 mm off),
    and identified again from the last stage's geometry the term is worth adding."""
    robot, cell = (str(ROOT / "benchmarks/ur10_cell" / f) for f in ("robot.toml", "cell.toml"))
    sc = seed_campaigns(1, 400, 50, PlannedArm.from_files(robot, cell), passes=1)
    settings = CampaignSettings(effects=EFFECTS)
    data = measure_campaign(sc.cell, sc.random, sc.q_val, np.random.default_rng([1, 7]), settings)
    said: list[str] = []
    fitted = calibrate(
        sc.nominal, data.campaign, effects=True, loop_settings=ADMITTED, learned=False,
        say=said.append,
    )  # fmt: skip
    geometric = calibrate(sc.nominal, data.campaign, effects=False)
    held = measure_campaign(sc.cell, sc.held[:0], sc.held, np.random.default_rng([1, 8]), settings)

    def error(description: RobotDescription) -> float:
        p = predict_tcp(description, held.campaign.q_rad, held.campaign.t_s)
        return float(np.mean(np.linalg.norm(p - held.true_prediction_mm, axis=1)))

    assert any("re-identification failed" in line for line in said)
    assert any("identified again from the last stage" in line for line in said)
    assert fitted.loop is not None
    assert any(s.kind == "gravity_deflection" for s in fitted.loop.final.specs)
    assert error(fitted.description) < 0.5 * error(geometric.description)


def fixed_xyz_deg(rot: np.ndarray) -> np.ndarray:
    """Fixed-axis X-Y-Z angles ``(N, 3)`` deg of rotations ``(N, 3, 3)``, as
    `twin compensate`'s ``rx_deg,ry_deg,rz_deg`` state them (R = Rz·Ry·Rx)."""
    return np.degrees(
        np.stack(
            [np.arctan2(rot[:, 2, 1], rot[:, 2, 2]), -np.arcsin(rot[:, 2, 0]),
             np.arctan2(rot[:, 1, 0], rot[:, 0, 0])],
            axis=1,
        )
    )  # fmt: skip


def test_compensate_with_an_orientation_on_a_ur10() -> None:
    """`twin compensate`'s orientation targets need the inverse kinematics as a start; on a
    UR10 it is the numeric one (16 fixed starts, the shortest travel from zero)."""
    robot = load_robot(str(ROOT / "benchmarks/ur10_cell/robot.toml"))
    model = KinematicModel.from_description(robot)
    rng = np.random.default_rng(11)
    q = rng.uniform(-np.pi, np.pi, size=(40, 6))
    q = q[jacobian_conditioning(model, q) > 0.02][:20]
    t = flange_poses(model, q)  # the tracker frame, as targets are given
    rot = t[:, :3, :3]
    tcp = t[:, :3, 3] + rot @ model.tool_mm
    rpy = fixed_xyz_deg(rot)
    assert np.allclose(rotation_xyz(rpy), rot, atol=1e-12)
    out = compensate(robot, tcp, rpy_deg=rpy)
    assert out.ok.all(), out.reason
    assert np.abs(out.residual_mm).max() < 1e-5
    back = flange_poses(model, np.radians(out.q_deg))
    assert np.abs(back[:, :3, :3] - rot).max() < 1e-8  # the stated orientation kept
    again = compensate(robot, tcp, rpy_deg=rpy)
    assert np.array_equal(again.q_deg, out.q_deg)  # the same starts every time


def test_an_unreachable_region_is_one_line_on_a_ur10(tmp_path: Path) -> None:
    robot, cell = (str(ROOT / "benchmarks/ur10_cell" / f) for f in ("robot.toml", "cell.toml"))
    far = ["--region", "5000,5000,5000,6000,6000,6000", "--no-sweeps"]
    r = twin_plan("--robot", robot, "--cell", cell, "--poses", "6", "--validate", "2", *far,
                  "--out", "o", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 2 and not (tmp_path / "o").exists()
    assert len(r.stderr.strip().splitlines()) == 1 and "no pose the arm reaches" in r.stderr


def test_a_ur10_on_its_table_plans_in_the_default_cell(tmp_path: Path) -> None:
    """The default cell's floor at the robot's base, as a UR stands on its table: its
    shoulder (joint 2's origin, 127 mm up) is closer to the floor than a link's radius and
    the clearance, at every pose alike; only what the pose moves may count (no pose was
    clear before). Home upright, as a UR's usually is."""
    ur10 = write_ur10(tmp_path / "ur10.toml", home="[0.0, -90.0, 0.0, -90.0, 0.0, 0.0]")
    args = ["--poses", "12", "--validate", "6", "--candidates", "500", "--no-sweeps"]
    r = twin_plan("--robot", str(ur10), *args, "--out", "o", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _, rows = read_joints(tmp_path / "o" / "campaign_joints.csv")
    q = np.radians([[float(row[f"q{j}_deg"]) for j in range(1, 7)] for row in rows])
    robot = load_robot(str(ur10))
    for seed in (1, 2):
        cell = TrueCell.create(robot, seed)
        geometry = cell_geometry(cell, CellGeometrySpec())
        assert np.all(true_view_codes(cell, geometry, q) == 0)
        assert np.all(true_collision_codes(cell, geometry, q) == 0)
    # the arm itself still keeps clear of the floor: every link point but the shoulder
    z = link_points(KinematicModel.from_description(robot), q)[:, 1:, :, 2].copy()
    assert np.allclose(z[:, 0, 0], 127.3)  # joint 2's origin: the mount's, not the pose's
    z[:, 0, 0] = np.inf
    assert np.all(z.min(axis=(1, 2)) >= resolve(CellGeometrySpec(), robot).link_radius_mm + 50.0)


def test_the_ratio_refit_starts_from_the_steps_geometry_on_a_ur10() -> None:
    """On the emulated UR10's planned 50 poses (seed 6) the gravity term's compliance
    ratios, refitted once joint 1's cyclic error is in, were identified from the nominal
    start (the base ~66 mm off): the refit stalled, was not significant, and the ratios
    fitted beside no cyclic error stayed (held-out 0.0170 mm). From the step's own geometry
    the refit goes through and the twin is 0.0137 mm."""
    robot, cell = (str(ROOT / "benchmarks/ur10_cell" / f) for f in ("robot.toml", "cell.toml"))
    sc = seed_campaigns(6, 5000, 50, PlannedArm.from_files(robot, cell), passes=1)
    settings = CampaignSettings(effects=EFFECTS)
    data = measure_campaign(sc.cell, sc.q_id, sc.q_val, np.random.default_rng([6, 7]), settings)
    said: list[str] = []
    twin = calibrate(sc.nominal, data.campaign, effects=True, say=said.append)
    held = measure_campaign(sc.cell, sc.held[:0], sc.held, np.random.default_rng([6, 8]), settings)
    p = predict_tcp(twin.description, held.campaign.q_rad, held.campaign.t_s)
    error = float(np.mean(np.linalg.norm(p - held.true_prediction_mm, axis=1)))
    assert any("ratios refitted beside cyclic error of joint 1" in line for line in said)
    assert error < 0.015
