"""The live twin following the robot: each production dwell with the reflector in view is
one tracking update (issue 28, "Live"; the estimator is :mod:`calibration.twin.tracking`).

The live grating and tracker samples are kept since the last dwell used (at most
``keep_s``). At most every ``detect_every_s`` of grating data the campaign's dwell
detection (:func:`~calibration.twin.phase_detection.find_dwells`) runs over them; a dwell
is *over* when a moving sample (or a gap) follows it, and it is used once the tracker's
samples have caught up with its end (or ``tracker_wait_s`` later). Its measurement is the
campaign's pairing (:func:`~calibration.twin.pairing.pair_dwell`: the mean tracker point
and the mean grating counts at the tracker's instants, the beam and motion checked): the
counts become joint angles through the scale maps, and joints, point and the calibrated
model's effect terms there go to :func:`~calibration.twin.tracking.track_update`. A dwell
without a valid tracker point (the reflector out of view) is skipped, and so is one whose
point is more than ``target_gate_mm`` from the tracked model's TCP: the tracker measured
another target (the campaign's sweeps put the reflector on the swept link), not a step of
this robot (a bumped tracker or a remounted tool moves the point by a millimetre or so).

Cost: nothing per grating batch but appending it; one detection over the kept samples
per ``detect_every_s``; per used dwell one effect evaluation and one update (~1 ms).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel, tcp_positions
from calibration.twin.pairing import PairingOptions, pair_dwell
from calibration.twin.phase_detection import Dwell, PhaseOptions, find_dwells
from calibration.twin.streams import Stream
from calibration.twin.tracking import (
    TrackerState,
    TrackingSetup,
    TrackStep,
    effect_offsets,
    start_tracking,
    track_update,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Joint angles ``(m, n)`` deg (Home + scale map) of grating counts ``(m, n)`` (may be
#: fractional: a dwell's mean).
AngleMap = Callable[[FloatArray], FloatArray]


@dataclass(frozen=True)
class LiveTrackingOptions:
    """When a dwell is a check: at least ``min_dwell_s`` long (0: the campaign's dwell
    detection alone), its point within ``target_gate_mm`` of the model's TCP. Detection
    runs at most every ``detect_every_s`` of grating data; samples are kept at most
    ``keep_s`` (a longer dwell is measured over its last ``keep_s``: the detection's cost
    stays bounded, ~0.2 ms for 5000 samples of six joints); a dwell waits at most
    ``tracker_wait_s`` (of grating data) for the tracker's samples of its end."""

    min_dwell_s: float = 0.0
    target_gate_mm: float = 50.0
    detect_every_s: float = 0.1
    keep_s: float = 5.0
    tracker_wait_s: float = 0.5
    phases: PhaseOptions = field(default_factory=PhaseOptions)
    pairing: PairingOptions = field(default_factory=PairingOptions)


@dataclass(frozen=True)
class LiveCheck:
    """One dwell's measurement: mapped time ``t_ns`` (ns, of its tracker samples), the
    joint angles ``q_deg`` ``(n,)`` and the tracker point ``point_mm`` ``(3,)``."""

    t_ns: int
    q_deg: FloatArray
    point_mm: FloatArray
    pairs: int


@dataclass(frozen=True)
class LiveTrackUpdate:
    """What one check did: its step (a-priori prediction and error, state, λ), the tracked
    parameters after it (absolute, model units) with their standard errors ``(k,)``, and
    the steps and alarms so far (an alarm counts when it is raised)."""

    check: LiveCheck
    step: TrackStep
    parameters: FloatArray
    standard_errors: FloatArray
    steps: int
    alarms: int


def _stream(
    kind: str, t_ns: IntArray, values: NDArray[np.generic], status: NDArray[np.uint16] | None
) -> Stream:
    """A :class:`Stream` of kept samples (what pairing reads: times, values, status)."""
    m = len(t_ns)
    zeros = np.zeros(m, dtype=np.int64)
    return Stream(
        kind,
        kind,
        kind,
        [],
        t_ns,
        values,
        status,
        np.zeros(m, dtype=np.uint64),
        np.zeros(m, dtype=np.int32),
        zeros,
        np.ones(m, dtype=np.uint8),
        zeros,
    )


class LiveTracker:
    """The tracked model of a calibrated description, fed with the live streams.

    ``setup``: :func:`~calibration.twin.tracking.tracking_setup` of ``description``;
    ``angles_deg``: the scale maps (:data:`AngleMap`); ``t0_ns``: the campaign clock's
    origin (the effects' time terms run on it)."""

    def __init__(
        self,
        setup: TrackingSetup,
        description: RobotDescription,
        angles_deg: AngleMap,
        t0_ns: int,
        options: LiveTrackingOptions = LiveTrackingOptions(),
    ) -> None:
        self.setup = setup
        self.description = description
        self.angles_deg = angles_deg
        self.t0_ns = int(t0_ns)
        self.options = options
        self.state: TrackerState = start_tracking(setup)
        self.steps = self.alarms = self.other_targets = 0
        n = description.n_joints
        self._g_t: list[IntArray] = [np.empty(0, dtype=np.int64)]
        self._g_c: list[IntArray] = [np.empty((0, n), dtype=np.int64)]
        self._p_t: list[IntArray] = [np.empty(0, dtype=np.int64)]
        self._p_v: list[FloatArray] = [np.empty((0, 3))]
        self._p_s: list[NDArray[np.uint16]] = [np.empty((0, 3), dtype=np.uint16)]
        self._newest_g = self._newest_p = self._detected_at = -(1 << 62)

    @property
    def geometry(self) -> KinematicModel:
        """The tracked geometry as it stands (the calibrated one before any check)."""
        return self.setup.model(self.state.theta)

    def add_gratings(self, t_ns: IntArray, counts: IntArray) -> None:
        """Grating samples: mapped times ``(m,)`` ns, counts ``(m, n)``."""
        if len(t_ns):
            self._g_t.append(np.asarray(t_ns, dtype=np.int64))
            self._g_c.append(np.asarray(counts, dtype=np.int64))
            self._newest_g = max(self._newest_g, int(t_ns[-1]))

    def add_tracker(
        self, t_ns: IntArray, points_mm: FloatArray, status: NDArray[np.uint16] | None
    ) -> None:
        """Tracker samples: mapped times ``(m,)`` ns, points ``(m, 3)`` mm, status
        ``(m, 3)`` (None: every point valid when finite)."""
        if not len(t_ns):
            return
        self._p_t.append(np.asarray(t_ns, dtype=np.int64))
        self._p_v.append(np.asarray(points_mm, dtype=float))
        st = np.ones((len(t_ns), 3), dtype=np.uint16) if status is None else status
        self._p_s.append(np.asarray(st, dtype=np.uint16))
        self._newest_p = max(self._newest_p, int(t_ns[-1]))

    def updates(self) -> list[LiveTrackUpdate]:
        """The dwells that ended since the last call, each one a tracking update (in time
        order; none between detections)."""
        opts = self.options
        if self._newest_g - self._detected_at < opts.detect_every_s * 1e9:
            return []
        self._detected_at = self._newest_g
        g_t, g_c = self._joined_gratings()
        dwells = find_dwells(g_t, g_c, opts.phases)
        grating = _stream("grating", g_t, g_c, None)
        p_t, p_v, p_s = self._joined_points()
        tracker = _stream("tracker", p_t, p_v, p_s)
        out: list[LiveTrackUpdate] = []
        used = -1  # the last grating sample of the last dwell dealt with
        waiting = None  # the first sample of a dwell over but waiting for the tracker
        for d in dwells:
            if d.i1 >= len(g_t) - 1:
                break  # still dwelling (or the newest samples): not over yet
            waited = self._newest_g - d.t1_ns >= opts.tracker_wait_s * 1e9
            if self._newest_p < d.t1_ns and not waited:
                waiting = d.i0
                break  # the tracker's samples of its end have not arrived yet
            used = d.i1
            if d.duration_s >= opts.min_dwell_s:
                up = self._update(d, grating, tracker)
                if up is not None:
                    out.append(up)
        self._trim(g_t, g_c, used, waiting)
        return out

    def _update(self, dwell: Dwell, grating: Stream, tracker: Stream) -> LiveTrackUpdate | None:
        stop = pair_dwell(dwell, grating, tracker, None, self.options.pairing)
        if not stop.ok:
            return None  # the reflector out of view, the beam broken: no check
        q_deg = self.angles_deg(stop.counts[None, :].astype(float))[0]
        q = np.radians(q_deg)
        t_s = (stop.t_ns - self.t0_ns) * 1e-9
        offset = effect_offsets(self.description, q[None, :], np.array([t_s]))[0]
        tcp = tcp_positions(self.geometry, q[None, :])[0] + offset
        if float(np.linalg.norm(stop.point_mm - tcp)) > self.options.target_gate_mm:
            self.other_targets += 1
            return None
        was_alarm = self.state.alarm
        self.state, step = track_update(self.setup, self.state, q, stop.point_mm, offset)
        self.steps += int(step.step_detected)
        self.alarms += int(self.state.alarm and not was_alarm)
        se = np.sqrt(np.diag(self.state.covariance(self.setup)))
        check = LiveCheck(stop.t_ns, q_deg, stop.point_mm, stop.n_pairs)
        return LiveTrackUpdate(
            check, step, self.setup.absolute(self.state.theta), se, self.steps, self.alarms
        )

    def _joined_gratings(self) -> tuple[IntArray, IntArray]:
        t, c = np.concatenate(self._g_t), np.concatenate(self._g_c)
        self._g_t, self._g_c = [t], [c]
        return t, c

    def _joined_points(self) -> tuple[IntArray, FloatArray, NDArray[np.uint16]]:
        t, v, s = np.concatenate(self._p_t), np.concatenate(self._p_v), np.concatenate(self._p_s)
        self._p_t, self._p_v, self._p_s = [t], [v], [s]
        return t, v, s

    def _trim(self, g_t: IntArray, g_c: IntArray, used: int, waiting: int | None) -> None:
        """Drop the samples up to the last dwell dealt with, those that can never be part
        of a dwell (before the trailing still run; all of it but its last sample when it
        spans more than a dwell may: the robot creeping), and any older than ``keep_s``;
        never a dwell waiting for the tracker (from ``waiting`` on)."""
        keep_from = used + 1
        if waiting is None and len(g_c) - keep_from > 1:
            ph = self.options.phases
            rest = g_c[keep_from:]
            moved = np.flatnonzero(np.abs(np.diff(rest, axis=0)).max(axis=1) > ph.still_counts)
            run0 = int(moved[-1]) + 1 if moved.size else 0
            run = rest[run0:]
            if int((run.max(axis=0) - run.min(axis=0)).max()) > ph.span_counts:
                run0 = len(rest) - 1
            keep_from += run0
        if len(g_t):
            oldest = int(g_t[-1]) - int(self.options.keep_s * 1e9)
            keep_from = max(keep_from, int(np.searchsorted(g_t, oldest)))
        if keep_from <= 0:
            return
        self._g_t, self._g_c = [g_t[keep_from:]], [g_c[keep_from:]]
        cut = int(g_t[keep_from - 1])  # tracker samples up to it belong to what is gone
        t = self._p_t[0]
        j = int(np.searchsorted(t, cut, side="right"))
        self._p_t, self._p_v, self._p_s = [t[j:]], [self._p_v[0][j:]], [self._p_s[0][j:]]
