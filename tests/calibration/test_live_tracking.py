"""The live twin following the robot (issue 28, "Live"): the emulated cell's production run
with thermal drift, base creep and a tool remount, played to the live tracker as the
daemon's streams would bring it (in process: grating counts dwelling at each check pose,
then moving on; tracker samples at 1 kHz during the dwell).

The streams are built from the emulator's drifting checks (sim_devices.pose_campaign,
sim_devices.drift): the twin gets the calibrated model (from the campaign), counts and
points, never the drift or the step time. The gratings' scale maps are a plain linear
map here (1e5 counts per degree): the scale calibration is not what is tested.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.effects.calibrate import calibrate
from calibration.model.description import load_robot
from calibration.twin.live_tracking import LiveTracker
from calibration.twin.tracking import effect_offsets, static_errors_mm, track_checks, tracking_setup
from calibration.twin.twin_predictor import TwinPredictor
from sim_devices.drift import CellDrift
from sim_devices.pose_campaign import (
    CampaignSettings,
    CheckProgram,
    emulated_campaign,
    emulated_checks,
)

DRIFT = CellDrift(thermal=True, creep=True, steps=("tool_remount",))
COUNTS_PER_DEG = 1e5
T0_NS = 1_800_000_000 * 10**9  # the campaign clock's origin (host UTC)
DWELL = 300  # grating samples at 1 kHz per check
MOVE = 20  # then moving away


def _angles(counts: np.ndarray) -> np.ndarray:
    return counts / COUNTS_PER_DEG


def _feed(tracker: LiveTracker, q_deg: np.ndarray, points: np.ndarray, t_s: np.ndarray):
    """Each check as the live streams bring it: a dwell, then a move; batches of 50 ms."""
    updates = []
    rng = np.random.default_rng(0)
    for q, p, t in zip(q_deg, points, t_s, strict=True):
        start = T0_NS + int(t * 1e9) - DWELL * 10**6 // 2
        tt = start + np.arange(DWELL + MOVE, dtype=np.int64) * 10**6
        c = np.rint(q * COUNTS_PER_DEG).astype(np.int64)
        counts = np.repeat(c[None, :], DWELL + MOVE, axis=0)
        counts[DWELL:] += (np.arange(1, MOVE + 1) * 500)[:, None]  # moving on
        for a in range(0, DWELL + MOVE, 50):
            tracker.add_gratings(tt[a : a + 50], counts[a : a + 50])
            in_dwell = tt[a : min(a + 50, DWELL)]
            # the tracker's points come a little later than the gratings (its own link)
            jitter = rng.integers(0, 3)
            tracker.add_tracker(in_dwell, np.repeat(p[None, :], len(in_dwell), 0), None)
            if jitter:
                updates += tracker.updates()
    # the robot goes on moving after the last check
    tt = tt[-1] + np.arange(1, 201, dtype=np.int64) * 10**6
    tracker.add_gratings(tt, counts[-1] + (np.arange(1, 201) * 500)[:, None])
    updates += tracker.updates()
    return updates


def _scenario(seed: int, drift: CellDrift, hours: float):
    nominal = load_robot("kr500")
    data = emulated_campaign(nominal, seed)
    checks = emulated_checks(data, seed, CheckProgram(hours=hours, drift=drift), CampaignSettings())
    desc = calibrate(nominal, data.campaign, effects=False).description
    return checks, desc


@pytest.mark.parametrize("seed", [3, 7, 11, 12])
def test_the_live_tracker_follows_drift_and_a_step_and_its_tcp_the_truth(seed):
    checks, desc = _scenario(seed, DRIFT, 6.0)
    c = checks.checks
    setup = tracking_setup(desc)
    live = LiveTracker(setup, desc, _angles, T0_NS)
    ups = _feed(live, c.q_deg, c.xyz_mm, c.t_s)
    # every check's dwell found, paired and learned from, in time order
    assert len(ups) == len(c.t_s)
    got_t = np.array([u.check.t_ns for u in ups])
    assert np.all(np.diff(got_t) > 0)
    err = np.array([u.step.error_mm for u in ups])
    # the same estimator as twin track on the same checks (q through 1e-5° counts)
    q = np.radians(c.q_deg)
    off = effect_offsets(desc, q, c.t_s)
    offline = track_checks(setup, q, c.xyz_mm, off)
    static = static_errors_mm(setup, q, c.xyz_mm, off)
    assert np.max(np.abs(err - offline.error_mm)) < 1e-3
    assert err.mean() <= 0.5 * static.mean()
    # the step: reported once, within 5 checks of the emulator's (hidden) time
    step_row = int(np.searchsorted(c.t_s, checks.draws.step_times_s["tool_remount"]))
    detected = [i for i, u in enumerate(ups) if u.step.step_detected]
    assert len(detected) == 1 and 0 <= detected[0] - step_row < 5, detected
    assert ups[-1].steps == 1 and ups[detected[0]].step.state == "step"
    assert np.all(ups[-1].standard_errors > 0) and len(ups[-1].parameters) == len(setup.names)
    # the published TCP: the tracked geometry's, nearer the truth than the calibrated one
    calibrated = TwinPredictor(desc)
    tracked = TwinPredictor(desc)
    tracked.set_geometry(live.geometry)
    last = slice(-20, None)
    t_last = c.t_s[last]
    cal_tcp, _ = calibrated.tcp_and_flange(q[last], t_last)
    tr_tcp, _ = tracked.tcp_and_flange(q[last], t_last)
    cal_err = np.linalg.norm(cal_tcp - checks.true_mm[last], axis=1).mean()
    tr_err = np.linalg.norm(tr_tcp - checks.true_mm[last], axis=1).mean()
    assert tr_err < 0.2 * cal_err, (tr_err, cal_err)


def test_without_dwells_nothing_moves_and_the_tcp_is_the_calibrated_one():
    checks, desc = _scenario(5, DRIFT, 0.5)
    c = checks.checks
    setup = tracking_setup(desc)
    live = LiveTracker(setup, desc, _angles, T0_NS)
    # the robot always moving: no dwell, so no check and the calibrated geometry
    t = T0_NS + np.arange(2000, dtype=np.int64) * 10**6
    counts = np.rint(c.q_deg[0] * COUNTS_PER_DEG).astype(np.int64) + (np.arange(2000) * 50)[:, None]
    for a in range(0, 2000, 100):
        live.add_gratings(t[a : a + 100], counts[a : a + 100])
        live.add_tracker(t[a : a + 100], np.repeat(c.xyz_mm[:1], 100, 0), None)
        assert live.updates() == []
    q = np.radians(c.q_deg)
    plain, _ = TwinPredictor(desc).tcp_and_flange(q, c.t_s)
    same = TwinPredictor(desc)
    same.set_geometry(live.geometry)
    again, _ = same.tcp_and_flange(q, c.t_s)
    assert np.array_equal(plain, again)
    # a dwell whose reflector is out of view (no tracker samples) is no check
    hidden = LiveTracker(setup, desc, _angles, T0_NS)
    ups = _feed(hidden, c.q_deg[:5], np.full((5, 3), np.nan), c.t_s[:5])
    assert ups == [] and hidden.state.rows == 0
    # nor one whose point is another target's (200 mm off the TCP: not this robot's step)
    other = LiveTracker(setup, desc, _angles, T0_NS)
    ups = _feed(other, c.q_deg[:5], c.xyz_mm[:5] + np.array([200.0, 0.0, 0.0]), c.t_s[:5])
    assert ups == [] and other.other_targets == 5
