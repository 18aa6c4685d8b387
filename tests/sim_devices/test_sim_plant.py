"""Plant: trapezoidal moves, campaign program, effects, configuration validation."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.model.description import load_robot
from sim_devices.config import CellConfig
from sim_devices.errors import SimConfigError
from sim_devices.motion import Move, Trajectory
from sim_devices.plant import Plant, campaign_moves


def test_trapezoid_reaches_targets_within_limits():
    traj = Trajectory.build(
        np.zeros(2), [Move((1.0, -0.5), 1.0, 0.5), Move((0.0, 0.0), 0.5, 0.0)], 1.0, 2.0
    )
    t = np.linspace(0, traj.end_s + 1, 20001)
    q, qd, _ = traj.evaluate(t)
    arrive = traj.start_s[0] + traj.move_s[0]
    np.testing.assert_allclose(traj.evaluate(arrive + 0.1)[0][0], [1.0, -0.5], atol=1e-12)
    assert np.max(np.abs(qd)) <= 1.0 + 1e-9
    assert np.max(np.abs(np.diff(q, axis=0))) < 1.01 * (t[1] - t[0])  # continuous
    np.testing.assert_allclose(q[-1], [0.0, 0.0], atol=1e-12)


def test_campaign_structure():
    desc = load_robot("kr500")
    moves = campaign_moves(desc, np.random.default_rng(0), n_identification=5, n_validation=7)
    labels = [m.label for m in moves]
    assert sum("home " in lab and "away" not in lab for lab in labels) == 60
    assert sum(lab.startswith("identification") for lab in labels) == 5
    assert sum(lab.startswith("validation") for lab in labels) == 7
    sweep = [m for m in moves if m.label.startswith("joint1 sweep down")]
    steps = np.degrees(np.diff([m.target_rad[0] for m in sweep]))
    np.testing.assert_allclose(steps, -2.0)


def test_torsion_seen_by_outputs_not_motors():
    cfg = CellConfig.loads('[cell]\nprogram = "random"\n')
    plant = Plant.from_config(cfg)
    st = plant.joint_state(np.linspace(0, 20, 50))
    dq = st.q_out_rad - st.q_cmd_rad
    assert np.all(np.abs(dq[:, 1]) > 0) and np.max(np.abs(dq)) < np.radians(0.2)
    np.testing.assert_allclose(st.motor_rad, st.q_cmd_rad * plant.gear_ratio)
    off = Plant.from_config(
        CellConfig.loads(
            '[cell]\nprogram = "random"\n[effects]\ntorsion = false\nbacklash = false\n'
        )
    )
    st2 = off.joint_state(np.linspace(0, 20, 50))
    np.testing.assert_array_equal(st2.q_out_rad, st2.q_cmd_rad)


@pytest.mark.parametrize(
    "text",
    [
        "[cell]\nprogram = 'dance'\n",
        "[grating]\nunit_id = 0\n",
        "[tracker]\ntarget = 'x'\n",
        "[bogus]\n",
        "[grating]\nrate_hz = 'fast'\n",
        "[encoders]\nnode_ids = [1, 1]\n",
    ],
)
def test_config_errors_name_the_key(text):
    with pytest.raises(SimConfigError):
        CellConfig.loads(text)


def test_default_config_round_trip():
    cfg = CellConfig()
    assert CellConfig.loads(cfg.dumps()) == cfg


def _segment_times(plant, prefix):
    """Mid-dwell program times of the segments whose label starts with ``prefix``."""
    sched = plant.trajectory.schedule()
    return np.array(
        [0.5 * (s["arrive_s"] + s["leave_s"]) for s in sched if s["label"].startswith(prefix)]
    )


def test_campaign_target_follows_program_phases():
    plant = Plant.from_config(CellConfig.loads("[effects]\ntorsion = false\nbacklash = false\n"))
    sched = plant.trajectory.schedule()
    for s in sched:
        lab = s["label"]
        if lab.startswith("joint"):
            assert s["target"] == f"link:{lab[5]}", lab
        elif lab.startswith(("identification", "validation", "end")):
            assert s["target"] == "tcp", lab
    changes = [s for s in sched if s["label"].startswith("target ")]
    assert [s["target"] for s in changes] == [f"link:{j}" for j in range(2, 7)] + ["tcp"]
    assert all(s["arrive_s"] == s["start_s"] and s["leave_s"] > s["start_s"] for s in changes)
    speed = plant.clock.speed
    for j in range(6):
        t = _segment_times(plant, f"joint{j + 1} sweep")
        wall = t / speed
        assert set(plant.target_at(wall)) == {f"link:{j + 1}"}
        q = plant.joint_state(t).q_out_rad
        np.testing.assert_allclose(
            plant.target_mm(q, wall), plant.cell.link_target_mm(j, q), atol=1e-9
        )
        # the circle the sweep traces is large (the wrist's TCP circles are ~29 mm)
        pts = plant.target_mm(q, wall)
        assert np.ptp(pts, axis=0).max() > 150.0, j
    t = _segment_times(plant, "validation")
    q = plant.joint_state(t).q_out_rad
    assert set(plant.target_at(t / speed)) == {"tcp"}
    np.testing.assert_allclose(plant.target_mm(q, t / speed), plant.cell.tcp_mm(q), atol=1e-9)


def test_pinned_target_and_truth_document():
    pinned = Plant.from_config(CellConfig.loads('[tracker]\ntarget = "tcp"\n'))
    t = _segment_times(pinned, "joint4 sweep")
    q = pinned.joint_state(t).q_out_rad
    np.testing.assert_allclose(pinned.target_mm(q, t / pinned.clock.speed), pinned.cell.tcp_mm(q))
    link2 = Plant.from_config(CellConfig.loads('[tracker]\ntarget = "link2"\n'))
    assert set(link2.target_at(np.array([0.0, 1e6]))) == {"link:2"}
    doc = pinned.truth_document()
    assert doc["plant"]["tracker_target"] == "tcp"
    assert {s["target"] for s in doc["program"]} == {"tcp"} | {f"link:{j}" for j in range(1, 7)}
    free = Plant.from_config(CellConfig.loads('[cell]\nprogram = "random"\n'))
    assert set(free.target_at(np.linspace(0, 1000, 50))) == {"tcp"}


def test_link_target_sees_deflection_upstream_only():
    text = "[effects]\ntorsion = false\nbacklash = false\n"
    rigid = Plant.from_config(CellConfig.loads(text))
    soft = Plant.from_config(
        CellConfig.loads(text + "[effects.undeclared]\ngravity_deflection = true\n")
    )
    q = np.radians([[10.0, -60.0, 80.0, 20.0, 40.0, 30.0]])
    # joint 1 is about the vertical: rigid, so its link's target does not move
    np.testing.assert_allclose(soft.link_target_mm(0, q, 0.0), rigid.link_target_mm(0, q, 0.0))
    for j in (2, 4):
        moved = np.linalg.norm(soft.link_target_mm(j, q, 0.0) - rigid.link_target_mm(j, q, 0.0))
        assert 1e-3 < moved < 2.0, (j, moved)
