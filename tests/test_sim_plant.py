"""Plant: trapezoidal moves, campaign program, effects, configuration validation."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.description import load_robot
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
