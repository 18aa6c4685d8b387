"""The live cell's drifting truth and its production program (issue 28, "Emulator").

The plant's points are checked against the drift physics of :mod:`sim_devices.drift`
applied to the undrifted plant of the same seed (one implementation, reused); the
production program's timing and tracker targets against its configuration; the tracker
reports a broken beam while the reflector is out of view.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_devices.config import CellConfig
from sim_devices.drift import rigid_drift_mm
from sim_devices.errors import SimConfigError
from sim_devices.plant import Plant, SimClock
from sim_devices.tracker import TrackerInstrument

PRODUCTION = """
[cell]
seed = 4
program = "production"
check_every_s = 40.0
check_dwell_s = 3.0
[effects]
torsion = false
backlash = false
"""
DRIFT = """
[effects.drift]
thermal = true
thermal_ppm = 200.0
thermal_time_constant_s = 100.0
creep = true
creep_mm_per_h = 5.0
creep_mdeg_per_h = 50.0
steps = {steps}
start_s = 50.0
span_s = 1000.0
"""


def _plants(steps: str = '["tool_remount", "tracker_bump"]', head: str = PRODUCTION):
    drifting = Plant.from_config(CellConfig.loads(head + DRIFT.format(steps=steps)))
    still = Plant.from_config(CellConfig.loads(head))
    return drifting, still


def _checks(plant: Plant) -> list[dict]:
    return [s for s in plant.trajectory.schedule() if s["label"].startswith("check ")]


def test_the_production_program_checks_every_period_with_the_reflector_in_view_only_then():
    plant, _ = _plants()
    sched = plant.trajectory.schedule()
    checks = _checks(plant)
    assert len(checks) == 12
    # one check per period: each cycle starts check_every_s after the one before
    starts = np.array([s["start_s"] for s in sched if s["label"].startswith("to check")])
    np.testing.assert_allclose(np.diff(starts), 40.0, atol=1e-9)
    assert plant.trajectory.repeat and plant.trajectory.end_s == pytest.approx(12 * 40.0)
    for c in checks:
        assert c["target"] == "tcp" and c["leave_s"] - c["arrive_s"] == pytest.approx(3.0)
        assert c["arrive_s"] == c["start_s"]  # the robot stands before the reflector shows
    assert {s["target"] for s in sched if not s["label"].startswith("check ")} == {"none"}
    # distinct check poses, reachable (the campaign's sampler); the loop is continuous
    q = plant.joint_state(np.array([0.5 * (c["arrive_s"] + c["leave_s"]) for c in checks]))
    assert len({tuple(np.round(v, 6)) for v in q.q_cmd_rad}) == 12
    end = plant.trajectory.end_s
    np.testing.assert_allclose(
        plant.joint_state(np.array([end - 1e-9])).q_cmd_rad,
        plant.joint_state(np.array([0.0])).q_cmd_rad,
        atol=1e-9,
    )


def test_the_tracker_sees_the_reflector_only_at_the_checks():
    plant, _ = _plants()
    plant.clock = SimClock(plant.clock.speed, 0.0)
    inst = TrackerInstrument(plant, plant.config.tracker, plant.config.effects)
    mid = np.array([0.5 * (c["arrive_s"] + c["leave_s"]) for c in _checks(plant)])
    work = np.array([s["arrive_s"] + 1.0 for s in plant.trajectory.schedule()][2::3])
    pts, status = inst.measure(np.concatenate([mid, work]) / plant.clock.speed)
    assert np.all(status[:12] == 0) and np.all(np.isfinite(pts[:12]))
    assert np.all(status[12:] == 1) and np.all(np.isnan(pts[12:]))


def test_the_tcp_moves_by_the_drift_physics_on_the_simulated_clock():
    plant, still = _plants()
    draws = plant.drift_draws
    assert draws is not None and draws.start_s == 50.0
    t_step = draws.step_times_s
    assert set(t_step) == {"tool_remount", "tracker_bump"}
    for t in t_step.values():  # the middle 60 % of [start_s, start_s + span_s]
        assert 250.0 <= t <= 850.0
    sim = np.linspace(0.0, 1400.0, 200)
    wall = sim / plant.clock.speed
    q = plant.joint_state(sim).q_out_rad
    moved = plant.target_mm(q, wall)
    undrifted = still.target_mm(q, wall)
    shift = np.linalg.norm(moved - undrifted, axis=1)
    # nothing before production starts; then growth, creep and steps of tenths of a mm
    assert shift[sim <= 50.0].max() < 1e-9
    assert shift[sim > 900.0].min() > 0.3 and shift.max() < 5.0
    # exactly the drift of sim_devices.drift on the undrifted truth (one implementation)
    from sim_devices.drift import drifted_tcp_mm

    expect = undrifted + (
        drifted_tcp_mm(plant.drift, draws, plant.truth_model, q, sim)
        - plant.cell.tcp_mm(q)  # the drift of the geometric TCP, as pose_campaign adds it
    )
    # the bump turns the whole point: the campaign generator's additive form differs by
    # the turn of the (µm) physical effects, here none (a rigid arm: no effect switched on)
    np.testing.assert_allclose(moved, expect, atol=1e-9)


def test_a_link_target_gets_the_rigid_drift_and_the_campaign_calibrates_an_undrifted_cell():
    head = "[effects]\ntorsion = false\nbacklash = false\n"
    _, still = _plants('["tracker_bump"]', head)
    # default start: the campaign program's end (the campaign sees the cell undrifted)
    drift_text = DRIFT.format(steps='["tracker_bump"]').replace("start_s = 50.0\n", "")
    default = Plant.from_config(CellConfig.loads(head + drift_text))
    assert default.drift_draws is not None
    assert default.drift_draws.start_s == default.trajectory.end_s
    sched = default.trajectory.schedule()
    sweeps = np.array([s["arrive_s"] for s in sched if "sweep" in s["label"]][::25])
    q = default.joint_state(sweeps).q_out_rad
    wall = sweeps / default.clock.speed
    np.testing.assert_allclose(default.target_mm(q, wall), still.target_mm(q, wall), atol=1e-9)
    # a target on link 3 after the start (and the bump): base creep and the bump, no growth
    plant, still = _plants('["tracker_bump"]', head + '[tracker]\ntarget = "link3"\n')
    late = np.linspace(900.0, 1400.0, len(q))
    got = plant.target_mm(q, late / plant.clock.speed)
    base = still.target_mm(q, late / still.clock.speed)
    expect = rigid_drift_mm(plant.drift, plant.drift_draws, plant.truth_model.base_mm, base, late)
    np.testing.assert_allclose(got, expect, atol=1e-9)
    assert np.linalg.norm(got - base, axis=1).min() > 0.1


def test_the_truth_document_records_the_draws():
    plant, _ = _plants()
    doc = plant.truth_document()
    assert doc["drift"]["settings"]["start_s"] == 50.0
    assert doc["drift"]["draws"]["step_times_s"] == plant.drift_draws.step_times_s
    assert len(doc["drift"]["draws"]["thermal_gain"]) == 6
    _, still = _plants()
    assert "drift" not in still.truth_document()


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[cell]\ncheck_every_s = 0.5\n", "check_every_s"),
        ("[cell]\ncheck_dwell_s = 30\ncheck_every_s = 20\n", "check_dwell_s"),
        ("[cell]\ncheck_poses = 0\n", "check_poses"),
        ("[effects.drift]\nspan_s = 0\n", "span_s"),
        ("[effects.drift]\nstart_s = nan\n", "start_s"),
    ],
)
def test_bad_production_and_drift_keys_are_one_line_naming_the_key(text, key):
    with pytest.raises(SimConfigError, match=key) as info:
        CellConfig.loads(text, "cell.toml")
    assert "\n" not in str(info.value) and str(info.value).startswith("cell.toml: [")
