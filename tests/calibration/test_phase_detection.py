"""Phase finding on a grating stream sampled from the emulator's campaign program."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.model.description import load_robot
from calibration.twin.phase_detection import PhaseOptions, find_dwells, find_phases
from sim_devices.motion import Trajectory
from sim_devices.plant import DEFAULT_AMAX_DEG_S2, DEFAULT_VMAX_DEG_S, campaign_moves

COUNTS_PER_RAD = np.array([1.2e6, 0.9e6, 0.7e6, 0.44e6, 0.32e6, 0.22e6])


def _stream(joints=(0, 1, 5), n_id=10, n_val=15, dt_sim=0.1, seed=4, noise=0.5, sweeps=None):
    desc = load_robot("kr500")
    rng = np.random.default_rng(seed)
    moves = campaign_moves(
        desc, rng, joints=joints, n_identification=n_id, n_validation=n_val, sweeps=sweeps
    )
    traj = Trajectory.build(
        np.radians(desc.home),
        moves,
        np.radians(DEFAULT_VMAX_DEG_S),
        np.radians(DEFAULT_AMAX_DEG_S2),
    )
    t_sim = np.arange(0.0, traj.end_s, dt_sim)
    q, _, _ = traj.evaluate(t_sim)
    counts = np.rint(q * COUNTS_PER_RAD + 1_000_000_000 + rng.normal(0, noise, q.shape)).astype(
        np.int64
    )
    t_ns = (np.arange(t_sim.size) * 1_000_000).astype(np.int64)  # 1 kHz wall
    return desc, moves, t_ns, counts


def test_finds_the_programs_sweeps_home_returns_and_poses():
    desc, _moves, t_ns, counts = _stream()
    ph = find_phases(t_ns, counts)
    s = ph.summary()
    lo = [j.lower_deg + 1 for j in desc.joints]
    hi = [j.upper_deg - 1 for j in desc.joints]
    for j in (0, 1, 5):
        stops = math.floor((hi[j] - lo[j]) / 2.0) + 1
        assert s["sweep_stops"][str(j + 1)] == {"forward": stops, "backward": stops}
        assert s["home_returns"][str(j + 1)] == 10
        assert s["step_counts"][str(j + 1)] == pytest.approx(
            math.radians(2.0) * COUNTS_PER_RAD[j], rel=1e-3
        )
    assert s["poses"] == {"identify": 10, "validate": 15}
    # Home vector from the other joints' sweeps
    assert np.allclose(ph.home_counts, 1_000_000_000, atol=3)
    # forward pass first, steps counted from the positive limit
    first = next(st for st in ph.sweeps if st.joint == 1 and st.pass_name == "forward")
    d = ph.dwells[first.dwell]
    assert d.counts[0] == pytest.approx(1e9 + math.radians(hi[0]) * COUNTS_PER_RAD[0], abs=3)


#: where a planned sweep holds the other joints (deg): away from Home (0, -90, 90, 0, 0, 0)
HELD_DEG = np.array([25.0, -70.0, 60.0, 30.0, 45.0, -40.0])


def _planned(joint: int) -> np.ndarray:
    """A planned sweep of ``joint`` (1-based): 2° stops 2° inside its limits, the other
    joints at :data:`HELD_DEG`, ``(K, 6)`` rad."""
    j = load_robot("kr500").joints[joint - 1]
    stops = np.arange(j.upper_deg - 2.0, j.lower_deg + 2.0, -2.0)
    q = np.tile(HELD_DEG, (len(stops), 1))
    q[:, joint - 1] = stops
    return np.radians(q)


def test_sweeps_holding_the_other_joints_away_from_home_find_the_same_phases():
    _, _, t_ns, counts = _stream()
    default = find_phases(t_ns, counts)
    sweeps = {2: _planned(2), 6: _planned(6)}
    _, _, t_ns, counts = _stream(sweeps=sweeps)
    ph = find_phases(t_ns, counts)
    s, s0 = ph.summary(), default.summary()
    assert s["sweep_stops"]["1"] == s0["sweep_stops"]["1"]
    for j, q in sweeps.items():
        assert s["sweep_stops"][str(j)] == {"forward": len(q), "backward": len(q)}
    assert s["home_returns"] == s0["home_returns"] == {"1": 10, "2": 10, "6": 10}
    assert s["poses"] == s0["poses"] == {"identify": 10, "validate": 15}
    np.testing.assert_allclose(ph.home_counts, 1_000_000_000, atol=3)
    # the same poses (the planned sweeps draw nothing: the same random poses)
    np.testing.assert_allclose(
        [ph.dwells[p.dwell].counts for p in ph.poses],
        [default.dwells[p.dwell].counts for p in default.poses],
        atol=2,
    )
    # the sweeps alone would have put Home elsewhere: most of the other joints' stops
    # are the planned ones, away from Home
    held = [ph.dwells[st.dwell].counts for st in ph.sweeps if st.joint != 1]
    assert np.all(np.abs(np.median(held, axis=0)[[0, 2, 3, 4]] - 1e9) > 1e4)


def test_pose_split_is_in_time_order():
    _, _moves, t_ns, counts = _stream(joints=(0, 5), n_id=4, n_val=6)
    ph = find_phases(t_ns, counts)
    assert [p.set for p in ph.poses] == ["identify"] * 4 + ["validate"] * 6
    starts = [ph.dwells[p.dwell].t0_ns for p in ph.poses]
    assert starts == sorted(starts)


def test_a_gap_in_the_stream_ends_a_dwell_and_creep_is_not_a_dwell():
    t = np.arange(100, dtype=np.int64) * 1_000_000
    c = np.zeros((100, 2), dtype=np.int64)
    t[50:] += 2_000_000_000  # 2 s with no samples
    dw = find_dwells(t, c, PhaseOptions())
    assert [(d.i0, d.i1) for d in dw] == [(0, 49), (50, 99)]
    creep = np.zeros((100, 2), dtype=np.int64)
    creep[:, 0] = np.arange(100)  # one count per sample: calm per sample, but 99 in all
    assert find_dwells(np.arange(100) * 1_000_000, creep, PhaseOptions()) == []
