"""Tracker ↔ grating pairing within a dwell: interpolation, beam breaks, motion."""

from __future__ import annotations

import numpy as np

from calibration.twin.pairing import PairingOptions, pair_dwell
from calibration.twin.phase_detection import PhaseOptions, find_dwells
from calibration.twin.streams import Stream, lost_intervals


def _stream(kind, t_ns, values, status=None, seq=None):
    n = len(t_ns)
    return Stream(
        key=f"cell/c/robot/r/{kind}/samples",
        kind=kind,
        device=kind,
        channels=[f"c{k}" for k in range(values.shape[1])],
        t_ns=np.asarray(t_ns, dtype=np.int64),
        values=values,
        status=status,
        seq=np.arange(n, dtype=np.uint64) if seq is None else np.asarray(seq, dtype=np.uint64),
        epoch=np.zeros(n, dtype=np.int32),
        t_rx_ns=np.asarray(t_ns, dtype=np.int64),
        mapped_ok=np.ones(n, dtype=np.uint8),
        t_device_us=np.asarray(t_ns, dtype=np.int64) // 1000,
    )


def _cell():
    # grating: 1 kHz; still at 1000 counts for 0..99 ms, moves 100..199 ms, still at 5000
    t = np.arange(300) * 1_000_000
    c = np.empty((300, 2), dtype=np.int64)
    c[:100] = 1000
    c[100:200] = np.linspace(1000, 5000, 100).astype(np.int64)[:, None]
    c[200:] = 5000
    g = _stream("grating", t, c)
    # tracker: 1 kHz, offset by 0.5 ms; its point follows the motion
    tt = t + 500_000
    p = np.zeros((300, 3))
    p[:, 0] = np.interp(tt, t, c[:, 0].astype(float)) / 1000.0
    st = np.ones((300, 3), dtype=np.uint16)
    return g, tt, p, st


def test_pairs_only_inside_the_dwell_and_averages_points():
    g, tt, p, st = _cell()
    tr = _stream("tracker", tt, p, st)
    dwells = find_dwells(g.t_ns, g.values, PhaseOptions())
    assert len(dwells) == 2
    m = pair_dwell(dwells[0], g, tr, opts=PairingOptions(margin_s=0.002))
    assert m.ok and m.n_rejected_beam == 0
    assert np.allclose(m.point_mm, [1.0, 0.0, 0.0])
    assert np.allclose(m.counts, [1000.0, 1000.0])
    # the tracker samples during the motion (100..199 ms) are never paired
    assert m.n_pairs <= 98


def test_beam_broken_samples_are_rejected_and_a_fully_broken_dwell_is_lost():
    g, tt, p, st = _cell()
    p = p.copy()
    st = st.copy()
    p[10:60] = np.nan
    st[10:60] = 2  # beam_obstructed, not valid
    tr = _stream("tracker", tt, p, st)
    d0, d1 = find_dwells(g.t_ns, g.values, PhaseOptions())
    m = pair_dwell(d0, g, tr)
    assert m.ok and m.n_rejected_beam == 50
    p[:] = np.nan
    st[:] = 2
    tr = _stream("tracker", tt, p, st)
    lost = pair_dwell(d1, g, tr)
    assert not lost.ok and lost.reason == "beam broken"
    assert np.all(np.isnan(lost.point_mm))


def test_a_point_off_the_dwell_is_rejected_as_moving():
    g, tt, p, st = _cell()
    p = p.copy()
    p[50, 1] = 0.5  # 0.5 mm off: the target was not where the gratings say
    tr = _stream("tracker", tt, p, st)
    d0, _ = find_dwells(g.t_ns, g.values, PhaseOptions())
    m = pair_dwell(d0, g, tr)
    assert m.ok and m.n_rejected_moving >= 1
    assert abs(m.point_mm[1]) < 1e-12


def test_lost_intervals_report_sequence_gaps():
    t = np.arange(1000) * 1_000_000
    keep = (t < 300_000_000) | (t >= 600_000_000)
    s = _stream("tracker", t[keep], np.zeros((int(keep.sum()), 3)), seq=np.flatnonzero(keep))
    (gap,) = lost_intervals(s)
    assert gap["reason"] == "sequence gap"
    assert gap["samples_missing"] == 300
    assert abs(gap["duration_s"] - 0.301) < 1e-9
