"""Robot programs: joint moves with synchronized trapezoidal velocity profiles and dwells.

A :class:`Trajectory` is built once from a start vector and a list of :class:`Move` and is
then evaluated for whole arrays of times at once (the devices sample it at 1 kHz).
All joints of one move start and stop together; the slowest joint sets the duration.
Units: rad, rad/s, rad/s², seconds of simulated time.

Each move also names the tracker target that is mounted while it runs (motion and dwell):
``"tcp"`` (the tool's target) or ``"link:J"`` (the target fixed on link J, 1-based, for
joint J's scale calibration), or ``"none"`` (:data:`HIDDEN`: the reflector out of the
tracker's view, e.g. the production program's work between its checks: the tracker reports
a broken beam). The target changes at a move's start; the campaign program makes every
change a zero-motion move whose dwell is the operator moving the reflector.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Move:
    """Go to ``target_rad`` at ``speed`` (fraction of the joints' maximum), then dwell."""

    target_rad: tuple[float, ...]
    speed: float = 1.0
    dwell_s: float = 0.0
    label: str = ""
    target: str = "tcp"  # tracker target during this move: "tcp", "link:J" or HIDDEN


#: The move's tracker target: none in view (the tracker's beam is broken meanwhile).
HIDDEN = "none"


def parse_target(target: str) -> int | None:
    """``"tcp"`` -> None, ``"link:J"`` -> J - 1 (0-based joint index); else ValueError."""
    if target == "tcp":
        return None
    if target.startswith("link:") and target[5:].isdigit() and int(target[5:]) >= 1:
        return int(target[5:]) - 1
    raise ValueError(f"tracker target must be 'tcp' or 'link:J', got {target!r}")


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A piecewise trapezoidal joint trajectory; segment arrays have a leading ``(S,)``."""

    start_s: FloatArray  # (S,) move start times
    move_s: FloatArray  # (S,) move durations
    accel_s: FloatArray  # (S,) acceleration phase durations
    q0_rad: FloatArray  # (S, n) start vectors
    dq_rad: FloatArray  # (S, n) displacement of each move
    direction: FloatArray  # (S, n) last motion direction (+1/-1) once the move starts
    labels: tuple[str, ...]
    end_s: float
    repeat: bool = False
    targets: tuple[str, ...] = ()  # per segment (empty: all "tcp")

    @classmethod
    def build(
        cls,
        start_rad: ArrayLike,
        moves: list[Move],
        vmax_rad_s: ArrayLike,
        amax_rad_s2: ArrayLike,
        *,
        repeat: bool = False,
    ) -> Trajectory:
        q = np.asarray(start_rad, dtype=float).copy()
        n = q.shape[0]
        vmax = np.broadcast_to(np.asarray(vmax_rad_s, dtype=float), (n,))
        amax = np.broadcast_to(np.asarray(amax_rad_s2, dtype=float), (n,))
        if not moves:
            moves = [Move(tuple(q), dwell_s=1.0, label="hold")]
        s = len(moves)
        start = np.empty(s)
        dur = np.empty(s)
        acc = np.empty(s)
        q0 = np.empty((s, n))
        dq = np.empty((s, n))
        direction = np.empty((s, n))
        last_dir = np.ones(n)
        t = 0.0
        for k, mv in enumerate(moves):
            target = np.asarray(mv.target_rad, dtype=float)
            if target.shape != (n,):
                raise ValueError(f"move {k}: target must have {n} joints")
            if not 0.0 < mv.speed <= 1.0:
                raise ValueError(f"move {k}: speed must be in (0, 1], got {mv.speed}")
            if mv.target != HIDDEN:
                parse_target(mv.target)
            d = target - q
            dist = np.abs(d)
            v = vmax * mv.speed
            a = amax * max(mv.speed, 0.05)
            tri = dist <= v * v / a
            t_joint = np.where(tri, 2.0 * np.sqrt(dist / a), dist / v + v / a)
            j = int(np.argmax(t_joint))
            total = float(t_joint[j])
            ta = total / 2.0 if tri[j] else float(v[j] / a[j])
            start[k], dur[k], acc[k] = t, total, ta
            q0[k], dq[k] = q, d
            moving = dist > 0
            last_dir = np.where(moving, np.sign(d), last_dir)
            direction[k] = last_dir
            t += total + max(0.0, mv.dwell_s)
            q = target
        labels = tuple(m.label for m in moves)
        targets = tuple(m.target for m in moves)
        return cls(start, dur, acc, q0, dq, direction, labels, t, repeat, targets)

    @property
    def n_joints(self) -> int:
        return int(self.q0_rad.shape[1])

    def _locate(self, t_s: ArrayLike) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
        t = np.asarray(t_s, dtype=float)
        if self.repeat and self.end_s > 0:
            t = np.mod(t, self.end_s)
        t = np.maximum(t, 0.0)
        idx = np.clip(np.searchsorted(self.start_s, t, side="right") - 1, 0, None)
        tau = t - self.start_s[idx]
        total = self.move_s[idx]
        ta = self.accel_s[idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            vp = np.where(total > 0, 1.0 / (total - ta), 0.0)
            s = np.where(
                tau < ta,
                0.5 * vp / np.where(ta > 0, ta, 1.0) * tau**2,
                np.where(
                    tau < total - ta,
                    vp * (tau - 0.5 * ta),
                    1.0 - 0.5 * vp / np.where(ta > 0, ta, 1.0) * (total - tau) ** 2,
                ),
            )
            ds = np.where(
                tau < ta,
                vp * tau / np.where(ta > 0, ta, 1.0),
                np.where(tau < total - ta, vp, vp * (total - tau) / np.where(ta > 0, ta, 1.0)),
            )
        done = (tau >= total) | (total <= 0)
        s = np.where(done, 1.0, np.clip(s, 0.0, 1.0))
        ds = np.where(done, 0.0, np.maximum(ds, 0.0))
        return idx, s, ds

    def evaluate(self, t_s: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Joint positions ``(N, n)`` rad, velocities ``(N, n)`` rad/s, and the direction
        ``(N, n)`` (±1) of the last motion of each joint, at simulated times ``(N,)`` s."""
        idx, s, ds = self._locate(np.atleast_1d(t_s))
        dq = self.dq_rad[idx]
        q = self.q0_rad[idx] + s[:, None] * dq
        qd = ds[:, None] * dq
        return q, qd, self.direction[idx]

    def segment_at(self, t_s: float) -> int:
        return int(self._locate(np.array([t_s]))[0][0])

    def segments_at(self, t_s: ArrayLike) -> NDArray[np.intp]:
        """Segment index ``(N,)`` at simulated times ``(N,)`` (before 0: the first)."""
        return self._locate(np.atleast_1d(t_s))[0]

    def target_of(self, segment: int) -> str:
        """The tracker target mounted during ``segment``."""
        return self.targets[segment] if self.targets else "tcp"

    def schedule(self) -> list[dict[str, float | str]]:
        """Start, end of motion, end of dwell, label and mounted tracker target of every move
        (for the truth file)."""
        ends = np.append(self.start_s[1:], self.end_s)
        return [
            {
                "start_s": float(a),
                "arrive_s": float(a + d),
                "leave_s": float(e),
                "label": lab,
                "target": self.target_of(k),
            }
            for k, (a, d, e, lab) in enumerate(
                zip(self.start_s, self.move_s, ends, self.labels, strict=True)
            )
        ]
