"""The live twin's tracking in the view's panel: the state (following, step, alarm), the
drift of each tracked parameter since the view first saw it, and the one-step-ahead error
history as a line of bars (docs/tracking.md, "Live"; the key: docs/topics.md).

:class:`TrackingHistory` keeps the newest rows of ``twin/<cell>/robot/<robot>/tracking``
(bounded); :func:`tracking_text` renders them as markdown. Pure, no GUI.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: the bars of the error history, lowest to highest
BARS = "▁▂▃▄▅▆▇█"
STATES = ("following", "step", "alarm")


@dataclass(frozen=True)
class TrackingRow:
    """One update: mapped time (ns), one-step-ahead error (mm), state code, the steps and
    alarms so far, the tracked parameters and their standard errors ``(k,)``."""

    t_ns: int
    error_mm: float
    state: int
    steps: int
    alarms: int
    parameters: FloatArray
    standard_errors: FloatArray


class TrackingHistory:
    """The newest ``capacity`` updates, the first one seen (the drift's origin) and the
    parameters' names (from the key's schema)."""

    def __init__(self, capacity: int = 200) -> None:
        self.rows: deque[TrackingRow] = deque(maxlen=capacity)
        self.first: TrackingRow | None = None
        self.names: tuple[str, ...] = ()

    def extend(self, columns: dict[str, Any], names: list[str]) -> None:
        """A batch of the tracking key's columns (``names``: its ``meta.parameters``)."""
        self.names = tuple(names)
        for i in range(len(columns["t_mapped_ns"])):
            row = TrackingRow(
                int(columns["t_mapped_ns"][i]),
                float(columns["error_mm"][i]),
                int(columns["state"][i]),
                int(columns["steps"][i]),
                int(columns["alarms"][i]),
                np.asarray(columns["parameters"][i], dtype=float),
                np.asarray(columns["standard_errors"][i], dtype=float),
            )
            if self.first is None:
                self.first = row
            self.rows.append(row)


def sparkline(values: FloatArray) -> str:
    """``values`` ``(m,)`` as bars scaled from 0 to their maximum."""
    if not len(values):
        return ""
    top = float(np.max(values))
    if not top > 0:
        return BARS[0] * len(values)
    idx = np.clip((values / top * (len(BARS) - 1)).round().astype(int), 0, len(BARS) - 1)
    return "".join(BARS[i] for i in idx)


def tracking_text(history: TrackingHistory, bars: int = 40) -> str:
    """Markdown: the state with steps and alarms, the last ``bars`` one-step-ahead errors,
    each parameter's latest value ± its standard error and its drift since the first
    update seen ("" before any update)."""
    if not history.rows or history.first is None:
        return ""
    last, first = history.rows[-1], history.first
    state = STATES[last.state] if 0 <= last.state < len(STATES) else str(last.state)
    errors = np.array([r.error_mm for r in history.rows][-bars:])
    lines = [
        f"tracking: **{state}** · {len(history.rows)} updates · steps {last.steps} · "
        f"alarms {last.alarms}",
        f"one-step-ahead error {last.error_mm:.4f} mm (max {errors.max():.4f}): "
        f"`{sparkline(errors)}`",
    ]
    for name, v, se, v0 in zip(
        history.names, last.parameters, last.standard_errors, first.parameters, strict=False
    ):
        lines.append(f"{name} {v:.6g} ± {se:.2g} (drift {v - v0:+.3g})")
    return "  \n".join(lines)
