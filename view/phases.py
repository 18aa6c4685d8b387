"""The campaign phase at a given instant, from the phases the twin found in the gratings.

The twin's phase detection (:mod:`calibration.twin.phase_detection`) classifies every dwell
(sweep stop, Home return, pose, other). :class:`PhaseTimeline` answers "what is the
robot doing at time t": the dwell it stands in, or the move between two dwells, named by
what it leads to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.twin.phase_detection import Phases


@dataclass(frozen=True)
class PhaseTimeline:
    """Dwell start/end times ``(D,)`` ns and one label per dwell, in time order."""

    t0_ns: NDArray[np.int64]
    t1_ns: NDArray[np.int64]
    labels: tuple[str, ...]
    sweep_joint: NDArray[np.int64]  # (D,) joint swept at the dwell, 0 if not a sweep stop

    @classmethod
    def from_phases(cls, phases: Phases) -> PhaseTimeline:
        d = phases.dwells
        labels = ["dwell"] * len(d)
        joint = np.zeros(len(d), dtype=np.int64)
        passes: dict[tuple[int, str], int] = {}
        for s in phases.sweeps:
            passes[(s.joint, s.pass_name)] = max(passes.get((s.joint, s.pass_name), 0), s.step)
        for s in phases.sweeps:
            last = passes[(s.joint, s.pass_name)] + 1
            labels[s.dwell] = (
                f"sweep of joint {s.joint}, {s.pass_name}, stop {s.step + 1} of {last}"
            )
            joint[s.dwell] = s.joint
        for h in phases.home_returns:
            labels[h.dwell] = f"Home return of joint {h.joint}, trial {h.trial}"
        n_poses = len(phases.poses)
        for i, p in enumerate(phases.poses, start=1):
            labels[p.dwell] = f"pose {i} of {n_poses} ({p.set})"
        for k in phases.other:
            labels[k] = "dwell (other)"
        return cls(
            np.array([x.t0_ns for x in d], dtype=np.int64),
            np.array([x.t1_ns for x in d], dtype=np.int64),
            tuple(labels),
            joint,
        )

    def label_at(self, t_ns: int) -> str:
        """What the robot does at host UTC ``t_ns``: ``"pose 12 of 250 (identify)"``,
        ``"sweep of joint 3, forward, stop 40 of 91"``, ``"moving: sweep of joint 3"``,
        ``"moving to pose 13 of 250 (identify)"``, ``"before the campaign"``…"""
        if len(self.labels) == 0:
            return "no dwell found in the gratings"
        k = int(np.searchsorted(self.t0_ns, t_ns, side="right")) - 1
        if k < 0:
            return "before the first dwell"
        if t_ns <= self.t1_ns[k]:
            return self.labels[k]
        if k + 1 >= len(self.labels):
            return "moving (after the last dwell)"
        j0, j1 = int(self.sweep_joint[k]), int(self.sweep_joint[k + 1])
        if j0 and j0 == j1:
            return f"moving: sweep of joint {j0}"
        nxt = self.labels[k + 1]
        return f"moving to {nxt}" if not nxt.startswith("dwell") else "moving"
