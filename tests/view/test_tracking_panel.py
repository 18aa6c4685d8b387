"""The view's tracking panel: the state, the one-step-ahead error history and the drift of
each tracked parameter, from the rows of the twin's tracking key."""

from __future__ import annotations

import numpy as np

from view.tracking_panel import BARS, TrackingHistory, sparkline, tracking_text


def _columns(k0: int, m: int, state: int) -> dict[str, np.ndarray]:
    k = np.arange(k0, k0 + m)
    return {
        "t_mapped_ns": 10**18 + k * 10**9,
        "error_mm": 0.01 * (1 + k % 4),
        "state": np.full(m, state, np.uint8),
        "steps": np.full(m, int(state == 1), np.uint32),
        "alarms": np.zeros(m, np.uint32),
        "parameters": np.column_stack([1000.0 + 0.001 * k, 1.0 + 1e-6 * k]),
        "standard_errors": np.full((m, 2), 1e-3),
    }


def test_the_panel_shows_the_state_the_error_history_and_the_drift():
    h = TrackingHistory(capacity=50)
    assert tracking_text(h) == ""
    names = ["base.x_mm", "joint2.length_scale"]
    h.extend(_columns(0, 30, 0), names)
    assert "**following**" in tracking_text(h)
    h.extend(_columns(30, 40, 1), names)  # the oldest rows fall out, the origin stays
    text = tracking_text(h, bars=8)
    assert len(h.rows) == 50 and h.first is not None and h.first.t_ns == 10**18
    assert "**step**" in text and "steps 1" in text
    # base.x_mm moved 0.069 mm since the first update seen
    assert "base.x_mm 1000.07 ± 0.001 (drift +0.069)" in text, text
    assert "joint2.length_scale" in text
    bars = text.split("`")[1]
    assert len(bars) == 8 and set(bars) <= set(BARS) and BARS[-1] in bars


def test_sparkline_scales_to_its_maximum():
    assert sparkline(np.array([0.0, 0.5, 1.0])) == BARS[0] + BARS[4] + BARS[-1]
    assert sparkline(np.zeros(3)) == BARS[0] * 3 and sparkline(np.zeros(0)) == ""
