"""Accuracy compensation, proven on the emulated cell: the compensated commands, driven on
the emulated robot and measured by its tracker, land within 1.2× of the twin's own
held-out prediction error; and ``twin compensate`` as a user runs it.

The twin gets only the campaign a user would have (no truth, no masses); the "before" is
the nominal geometry registered to the tracker (the calibrated base and tool: what a
cell has after a plain registration), whose inverse kinematics give the programmed
joints of each target.
"""

from __future__ import annotations

import csv
from dataclasses import replace

import numpy as np
import pytest

from calibration.effects.closed_loop import run_closed_loop
from calibration.effects.model_effects import predict_tcp
from calibration.model.description import EffectDescription, load_robot
from calibration.model.kinematics import KinematicModel, flange_poses, tcp_positions
from calibration.twin.compensation import compensate, rotation_xyz
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign, sample_reachable_poses
from sim_devices.program import compensation_trial
from tests.calibration.test_bad_input_twin import refused, twin


def calibrated_cell(robot: str, seed: int):
    data = emulated_campaign(robot, seed, CampaignSettings(n_identify=100, n_validate=150))
    desc = load_robot(robot)
    loop = run_closed_loop(desc, data.campaign)
    return data, desc, loop.calibrated_description(desc)


def mean_ap(errors) -> float:
    return float(np.mean(np.linalg.norm(errors, axis=1)))


@pytest.mark.parametrize(
    ("robot", "seed", "effects"),
    [("kr500", 1, ()), ("kr500", 2, ("gravity_deflection",)), ("hp20d", 3, ())],
)
def test_compensated_commands_realise_the_twins_prediction(robot, seed, effects):
    trial = compensation_trial(robot, seed, effects, n_targets=150)
    assert trial.refused == 0
    before, after = mean_ap(trial.before_mm), mean_ap(trial.after_mm)
    twin_error = mean_ap(trial.twin_validation_mm)
    print(f"{robot} seed {seed} {effects}: before {before:.4f} mm, after {after:.4f} mm, "
          f"twin's held-out {twin_error:.4f} mm, ratio {after / twin_error:.3f}")  # fmt: skip
    assert before > 10 * after
    assert after <= 1.2 * twin_error


@pytest.fixture(scope="module")
def cell_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("comp")
    _, desc, cal = calibrated_cell("kr500", 5)
    cal.save(root / "cal.toml")
    rng = np.random.default_rng(5)
    q_prog = np.degrees(sample_reachable_poses(desc, 20, rng))
    lim = np.array([(j.lower_deg + 2, j.upper_deg - 2) for j in desc.joints])
    q_prog = np.clip(q_prog, lim[:, 0], lim[:, 1])
    registered = replace(desc, base=cal.base, tool=cal.tool)
    target = tcp_positions(KinematicModel.from_description(registered), np.radians(q_prog))
    rows = [["target", "x_mm", "y_mm", "z_mm", *(f"q{i}_deg" for i in range(1, 7))]]
    rows += [[f"T{i}", *(f"{v:.6f}" for v in target[i]), *(f"{v:.9f}" for v in q_prog[i])]
             for i in range(20)]  # fmt: skip
    with open(root / "targets.csv", "w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    return root, cal, target[:20], q_prog[:20]


def read_joints(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def test_twin_compensate_writes_joints_on_target(cell_files, tmp_path):
    root, cal, target, _ = cell_files
    proc = twin(root, "compensate", "--model", "cal.toml", "--targets", "targets.csv",
                "--out", str(tmp_path / "joints.csv"))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    header, rows = read_joints(tmp_path / "joints.csv")
    assert header[:7] == ["target", *(f"q{i}_deg" for i in range(1, 7))]
    assert header[7:] == ["residual_mm", "branch", "travel_deg", "sd_mm", "beyond_reach"]
    q = np.array([[float(v) for v in r[1:7]] for r in rows])
    assert np.max(np.linalg.norm(predict_tcp(cal, np.radians(q)) - target, axis=1)) < 1e-5
    travel = np.array([float(r[9]) for r in rows])
    assert np.all(travel > 0) and np.all(travel < 1.0)  # a correction, not another pose


def test_a_stated_orientation_is_kept(cell_files):
    _, cal, target, q_prog = cell_files
    model = KinematicModel.from_description(cal)
    r = flange_poses(model, np.radians(q_prog))[:, :3, :3]
    ry = np.degrees(np.arcsin(-r[:, 2, 0]))
    rx = np.degrees(np.arctan2(r[:, 2, 1], r[:, 2, 2]))
    rz = np.degrees(np.arctan2(r[:, 1, 0], r[:, 0, 0]))
    rpy = np.stack([rx, ry, rz], 1)
    np.testing.assert_allclose(rotation_xyz(rpy), r, atol=1e-12)
    res = compensate(cal, target, rpy_deg=rpy)
    assert res.ok.all(), res.reason
    got = flange_poses(model, np.radians(res.q_deg))[:, :3, :3]
    np.testing.assert_allclose(got, r, atol=1e-8)
    assert np.max(res.residual_mm) < 1e-5


def test_lost_motion_targets_are_solved_in_program_order():
    """A lost-motion term takes each joint's approach direction from the target before it.
    Every target is reached whose lost-motion joints move more than the lost motion's full
    width from the one before it; one that moves less has no direct move (the joint
    stands off by the half-width in its direction of motion) and is named as such.
    Predicting only the unfinished targets left 6-9 of 40 per seed 2-6 mm off. A target
    left out, the rest are solved again without it: the program runs without it."""
    desc = load_robot("kr500")
    half_width = 0.05
    lost = tuple(
        EffectDescription("lost_motion", {"joint": float(j), "half_width_deg": half_width})
        for j in (1, 2, 3)
    )
    cal = replace(desc, effects=lost)
    for seed in (1, 2, 3, 4):
        q = np.degrees(sample_reachable_poses(desc, 40, np.random.default_rng(seed)))
        target = tcp_positions(KinematicModel.from_description(desc), np.radians(q))
        res = compensate(cal, target, q_programmed_deg=q, skip_unreached=True)
        moves = np.abs(np.diff(np.vstack([desc.home, q]), axis=0))[:, :3]
        clear = np.all(moves > 4 * half_width, axis=1)
        assert res.ok[clear].all(), [r for r in res.reason if r]
        assert res.ok.sum() >= 38
        for i in np.flatnonzero(~res.ok):
            assert "inside its lost motion" in res.reason[i], res.reason[i]
        # the program the robot runs: the reached targets alone, in their order
        pred = predict_tcp(cal, np.radians(res.q_deg[res.ok]))
        assert np.max(np.linalg.norm(pred - target[res.ok], axis=1)) < 1e-5


def test_unreachable_and_out_of_limits_targets_are_named(cell_files, tmp_path):
    root, cal, _, q_prog = cell_files
    for f in ("cal.toml", "targets.csv"):
        (tmp_path / f).write_bytes((root / f).read_bytes())
    lines = (tmp_path / "targets.csv").read_text().splitlines()
    far = lines[3].split(",")
    far[1] = "90000"
    lines[3] = ",".join(far)
    # joint 1 programmed at its limit, the target 2° further round axis 1
    lim = cal.joints[0].upper_deg
    q_edge = q_prog[5].copy()
    q_edge[0] = lim - 0.5
    beyond = q_edge.copy()
    beyond[0] = lim + 1.5
    p = predict_tcp(cal, np.radians(beyond)[None])[0]
    lines[6] = ",".join(["T5", *(f"{v:.6f}" for v in p), *(f"{v:.9f}" for v in q_edge)])
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    base = ["compensate", "--model", "cal.toml", "--targets", "bad.csv", "--out", "j.csv"]
    refused(tmp_path, base, "bad.csv", "line 4", "'T2'", "unreachable", "--skip-bad")
    proc = twin(tmp_path, *base, "--skip-bad")
    assert proc.returncode == 0, proc.stderr
    assert "'T2'" in proc.stderr and "'T5'" in proc.stderr and "joint 1" in proc.stderr
    _, rows = read_joints(tmp_path / "j.csv")
    assert len(rows) == 18 and {"T2", "T5"}.isdisjoint(r[0] for r in rows)


@pytest.mark.parametrize(
    ("edit", "keywords"),
    [
        (lambda t: t.replace("q6_deg", "q7_deg", 1), ["bad.csv", "q1_deg", "missing q6_deg"]),
        (lambda t: t.replace("x_mm", "xx", 1), ["bad.csv", "x_mm"]),
        (lambda t: t.replace("T3,", "T2,", 1), ["bad.csv", "line 5", "duplicated target"]),
        (lambda t: t.split("\n", 1)[0] + "\n", ["bad.csv", "no valid data rows"]),
    ],
)
def test_twin_compensate_refuses_broken_targets(cell_files, tmp_path, edit, keywords):
    root = cell_files[0]
    (tmp_path / "cal.toml").write_bytes((root / "cal.toml").read_bytes())
    (tmp_path / "bad.csv").write_text(edit((root / "targets.csv").read_text()))
    refused(tmp_path, ["compensate", "--model", "cal.toml", "--targets", "bad.csv", "--out",
                       "j.csv"], *keywords)  # fmt: skip
    refused(tmp_path, ["compensate", "--model", "cal.toml", "--targets", "bad.csv", "--out",
                       "bad.csv"], "--out", "input")  # fmt: skip
