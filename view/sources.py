"""Where the view's samples come from: a recording played back, or the live cell and twin.

Both answer one question, :meth:`latest`: the :class:`Snapshot` to draw now. The viewer
asks at its own frame rate, so a 1 kHz stream never queues up behind the drawing: the
latest sample wins and the ones between two frames are only counted.

* :class:`ReplaySource` reads the recording once with the project's reader
  (:func:`calibration.twin.streams.read_recording_streams`, built on
  :mod:`daq.recording_reader` and :mod:`daq.columnar`) and answers for any time of a
  :class:`ReplayClock` (play, pause, speed, seek): a pure function of the time.
* :class:`LiveSource` subscribes to the daemon's data keys (``cell/**``) and the live
  twin's (``twin/**``, docs/topics.md), or one cell's (``cell/<cell>/**``,
  ``twin/<cell>/**``), with :class:`daq.bus.Receiver`, keeping the latest twin sample,
  the recent tracker and grating samples and the twin's health.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration.twin.phase_detection import PhaseOptions, find_phases
from calibration.twin.streams import CellStreams, stream_kind
from edges.channel_names import GRATING, joint_columns
from view.model import TwinModel
from view.phases import PhaseTimeline
from view.tracking_panel import TrackingHistory, tracking_text

if TYPE_CHECKING:
    import zenoh

    from calibration.twin.campaign_measurement import CampaignMeasurements

FloatArray = NDArray[np.float64]
TRACKER_VALID = 1  # status bit of a tracker channel: the measurement is valid


@dataclass(frozen=True)
class Snapshot:
    """What the view draws at one instant.

    Times: ``t_ns`` host UTC of the newest grating sample shown; ``t_s`` seconds since the
    source's first one; ``duration_s`` the recording's length (None live). ``q_deg``
    ``(n,)`` and ``tcp_mm`` ``(3,)`` (tracker frame, mm) are the twin's, None when unknown.
    ``tracker_mm`` ``(3,)`` is the latest tracker point (None: none, or beam broken).
    ``pose_points_mm`` and ``pose_twin_mm`` ``(k, 3)``: the tracker's point of every pose
    measured so far and the twin's TCP there (NaN where unknown). ``rate_hz`` and
    ``latency_ms`` (p50, p99) describe the stream (replay: the recorded grating stream and
    its receive − mapped delay; live: the twin's health).
    """

    t_ns: int
    t_s: float
    duration_s: float | None
    q_deg: FloatArray | None
    tcp_mm: FloatArray | None
    tracker_mm: FloatArray | None
    pose_points_mm: FloatArray
    pose_twin_mm: FloatArray
    phase: str
    rate_hz: float | None = None
    latency_ms: tuple[float, float] | None = None
    playing: bool = True
    speed: float = 1.0
    note: str = ""
    #: live: host UTC ns at which the twin published the drawn sample (its
    #: ``t_publish_ns``), None in replay or without a live twin
    published_ns: int | None = None
    #: live: the twin's tracking as markdown (view.tracking_panel; "" without updates)
    tracking: str = ""


class ReplayClock:
    """Replay time in seconds from the recording's start: play, pause, speed, seek.

    Thread-safe (the GUI calls it from viser's threads). At the end it stops there,
    paused."""

    def __init__(self, duration_s: float, *, speed: float = 1.0, playing: bool = True) -> None:
        self.duration_s = float(duration_s)
        self._lock = threading.Lock()
        self._pos_s = 0.0
        self._since = time.monotonic()
        self._speed = float(speed)
        self._playing = playing

    def _now_locked(self) -> float:
        t = self._pos_s
        if self._playing:
            t += (time.monotonic() - self._since) * self._speed
        if t >= self.duration_s:
            t = self.duration_s
            self._pos_s, self._playing = t, False
        return t

    def now_s(self) -> float:
        with self._lock:
            return self._now_locked()

    @property
    def playing(self) -> bool:
        with self._lock:
            self._now_locked()
            return self._playing

    @property
    def speed(self) -> float:
        return self._speed

    def play(self) -> None:
        with self._lock:
            t = self._now_locked()
            self._pos_s = 0.0 if t >= self.duration_s else t  # play at the end: from the start
            self._since = time.monotonic()
            self._playing = True

    def pause(self) -> None:
        with self._lock:
            self._pos_s = self._now_locked()
            self._playing = False

    def seek(self, t_s: float) -> None:
        with self._lock:
            self._pos_s = min(max(float(t_s), 0.0), self.duration_s)
            self._since = time.monotonic()

    def set_speed(self, speed: float) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        with self._lock:
            self._pos_s = self._now_locked()
            self._since = time.monotonic()
            self._speed = float(speed)


@dataclass(frozen=True)
class PosePoints:
    """The campaign's measured poses: when each became known (its dwell's end, host UTC
    ns, ``(m,)``, sorted), the tracker's point ``(m, 3)`` mm and the twin's TCP there
    ``(m, 3)`` mm (NaN without scale maps)."""

    t_ns: NDArray[np.int64]
    points_mm: FloatArray
    twin_mm: FloatArray

    @classmethod
    def empty(cls) -> PosePoints:
        return cls(np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty((0, 3)))


def pose_points(meas: CampaignMeasurements, twin: TwinModel) -> PosePoints:
    """The poses of :class:`~calibration.twin.campaign_measurement.CampaignMeasurements`
    with the twin's TCP at each (one vectorized evaluation)."""
    if not meas.poses:
        return PosePoints.empty()
    dwells = meas.phases.dwells
    t_end = np.array([dwells[p.dwell].t1_ns for p in meas.poses], dtype=np.int64)
    t_mid = np.array([meas.stops[p.dwell].t_ns for p in meas.poses], dtype=np.int64)
    q = twin.joint_deg(meas.pose_counts)
    twin_mm = np.full((len(t_end), 3), np.nan)
    if q is not None:
        twin_mm = twin.tcp_mm(q, t_mid)
    order = np.argsort(t_end, kind="stable")
    return PosePoints(t_end[order], meas.pose_points_mm[order], twin_mm[order])


class ReplaySource:
    """A recording's streams answered at the time of a :class:`ReplayClock`."""

    def __init__(
        self,
        streams: CellStreams,
        twin: TwinModel,
        *,
        timeline: PhaseTimeline | None = None,
        poses: PosePoints | None = None,
        speed: float = 1.0,
        note: str = "",
    ) -> None:
        g = streams.grating
        order = np.argsort(g.t_ns, kind="stable")
        self.g_t = g.t_ns[order]
        self.g_counts = g.values[order]
        self.g_rx = g.t_rx_ns[order]
        tr = streams.tracker
        order = np.argsort(tr.t_ns, kind="stable")
        self.tr_t = tr.t_ns[order]
        valid = np.isfinite(tr.values[order]).all(axis=1)
        if tr.status is not None:
            valid &= (tr.status[order] & TRACKER_VALID).all(axis=1).astype(bool)
        self.tr_xyz = np.where(valid[:, None], tr.values[order], np.nan)
        self.twin = twin
        self.timeline = timeline
        self.poses = poses or PosePoints.empty()
        self.t_start_ns = int(self.g_t[0])
        self.duration_s = float(self.g_t[-1] - self.g_t[0]) * 1e-9
        # paused until the page is served (``clock.play()``): the replay starts when
        # someone can watch it, not while the viewer is setting up
        self.clock = ReplayClock(self.duration_s, speed=speed, playing=False)
        self.note = note

    def latest(self) -> Snapshot:
        return self.snapshot_at(self.clock.now_s())

    def snapshot_at(self, t_s: float) -> Snapshot:
        """The state of the recording ``t_s`` seconds after its first grating sample."""
        t_ns = self.t_start_ns + round(t_s * 1e9)
        i = max(int(np.searchsorted(self.g_t, t_ns, side="right")) - 1, 0)
        q = self.twin.joint_deg(self.g_counts[i])
        q_deg = tcp = None
        if q is not None:
            q_deg = q[0]
            tcp = self.twin.tcp_mm(q, [self.g_t[i]])[0]
        k = int(np.searchsorted(self.tr_t, t_ns, side="right")) - 1
        tracker = self.tr_xyz[k] if k >= 0 and np.isfinite(self.tr_xyz[k]).all() else None
        m = int(np.searchsorted(self.poses.t_ns, t_ns, side="right"))
        # the recorded stream over the last second: its rate and the daemon's delay
        lo = int(np.searchsorted(self.g_t, t_ns - 1_000_000_000, side="right"))
        rate = latency = None
        if i - lo >= 1:
            span_s = (self.g_t[i] - self.g_t[lo]) * 1e-9
            rate = (i - lo) / span_s if span_s > 0 else None
            delay_ms = (self.g_rx[lo : i + 1] - self.g_t[lo : i + 1]) * 1e-6
            p50, p99 = np.percentile(delay_ms, [50, 99])
            latency = (float(p50), float(p99))
        phase = self.timeline.label_at(t_ns) if self.timeline else "phases not known"
        return Snapshot(
            t_ns=int(self.g_t[i]),
            t_s=float(t_s),
            duration_s=self.duration_s,
            q_deg=q_deg,
            tcp_mm=tcp,
            tracker_mm=tracker,
            pose_points_mm=self.poses.points_mm[:m],
            pose_twin_mm=self.poses.twin_mm[:m],
            phase=phase,
            rate_hz=rate,
            latency_ms=latency,
            playing=self.clock.playing,
            speed=self.clock.speed,
            note=self.note,
        )

    def close(self) -> None:
        pass


@dataclass
class _Ring:
    """The last ``capacity`` rows of a stream: times ``(c,)`` ns and values ``(c, k)``."""

    capacity: int
    width: int
    t: NDArray[np.int64] = field(init=False)
    v: FloatArray = field(init=False)
    size: int = 0
    head: int = 0

    def __post_init__(self) -> None:
        self.t = np.zeros(self.capacity, dtype=np.int64)
        self.v = np.zeros((self.capacity, self.width))

    def extend(self, t: NDArray[Any], v: NDArray[Any]) -> None:
        m = min(len(t), self.capacity)
        t, v = t[-m:], v[-m:]
        idx = (self.head + np.arange(m)) % self.capacity
        self.t[idx] = t
        self.v[idx] = v
        self.head = (self.head + m) % self.capacity
        self.size = min(self.size + m, self.capacity)

    def ordered(self) -> tuple[NDArray[np.int64], FloatArray]:
        idx = (self.head - self.size + np.arange(self.size)) % self.capacity
        return self.t[idx], self.v[idx]


class LiveSource:
    """The daemon's and the live twin's zenoh keys, the latest sample of each kept.

    Batches are handled on zenoh's callback thread (docs/topics.md: no hand-over per
    message): each one only replaces the latest values and appends to bounded rings
    (``window_s`` of grating, tracker and twin samples at ``rate_hz``). Every
    ``phase_period_s`` a thread of its own finds the phases in the grating window (the
    twin's own rules) and, for each pose dwell that ended, stores the tracker's mean point
    and the twin's mean TCP over it.
    """

    def __init__(
        self,
        session: zenoh.Session,
        twin: TwinModel,
        *,
        cell: str | None = None,
        window_s: float = 60.0,
        rate_hz: float = 1000.0,
        phase_period_s: float = 2.0,
        say: Callable[[str], None] = lambda _t: None,
    ) -> None:
        from daq.bus import Receiver
        from daq.cells import cell_data_key, cell_twin_key

        self.session = session  # the caller's: it closes it after this source
        #: the cell followed (``cell/<cell>/**``, ``twin/<cell>/**``); None: every cell
        self.cell = cell
        data_key = cell_data_key(cell) if cell is not None else "cell/**"
        twin_key = cell_twin_key(cell) if cell is not None else "twin/**"
        self.twin = twin
        self.say = say
        n = twin.n_joints
        cap = int(window_s * rate_hz)
        self._lock = threading.Lock()
        self._grating = _Ring(cap, n)
        self._tracker = _Ring(cap, 3)
        self._twin = _Ring(cap, 3)
        self._kinds: dict[str, tuple[str, list[str]]] = {}
        self._latest_counts: NDArray[Any] | None = None
        self._latest_t_ns = 0
        self._twin_q: FloatArray | None = None
        self._twin_tcp: FloatArray | None = None
        self._twin_t_ns = 0
        self._twin_published_ns: int | None = None
        self._tracker_xyz: FloatArray | None = None
        self._health: dict[str, Any] = {}
        self._tracking = TrackingHistory()
        self._first_t_ns: int | None = None
        self._phase = "waiting for gratings"
        self._poses_t: list[int] = []
        self._pose_points: list[FloatArray] = []
        self._pose_twin: list[FloatArray] = []
        self._seen_pose_t0: set[int] = set()
        self.batches = 0
        self._stop = threading.Event()
        self._phase_period_s = phase_period_s
        self._receivers = [
            Receiver(session, data_key, on_batch=self._on_batch),
            Receiver(session, twin_key, on_batch=self._on_batch, on_other=self._on_other),
        ]
        self._phase_thread = threading.Thread(target=self._phases_loop, name="view-phases")
        self._phase_thread.daemon = True
        self._phase_thread.start()

    # -- zenoh's callback thread: quick -------------------------------------------------------
    def _kind(self, got: Any) -> tuple[str, list[str]]:
        known = self._kinds.get(got.key)
        if known is None:
            names = list(got.schema.names)
            kind = stream_kind(names)
            cols: list[str] = []
            if got.key.startswith("twin/") and {"q_deg", "tcp_mm"} <= set(names):
                kind = "twin"
            elif got.key.startswith("twin/") and {"error_mm", "parameters"} <= set(names):
                kind = "tracking"  # cols: the tracked parameters' names
                cols = [str(p) for p in got.schema.meta.get("parameters", [])]
            if kind == "grating":
                cols = joint_columns(names, GRATING)
            known = self._kinds[got.key] = (kind, cols)
        return known

    def _on_batch(self, got: Any) -> None:
        kind, cols = self._kind(got)
        c = got.columns
        if len(c.get("t_mapped_ns", ())) == 0:
            return
        t = np.asarray(c["t_mapped_ns"], dtype=np.int64)
        with self._lock:
            self.batches += 1
            if kind == "twin":
                self._twin_q = np.asarray(c["q_deg"][-1], dtype=float)
                self._twin_tcp = np.asarray(c["tcp_mm"][-1], dtype=float)
                self._twin_t_ns = int(t[-1])
                if "t_publish_ns" in c:
                    self._twin_published_ns = int(c["t_publish_ns"][-1])
                self._twin.extend(t, np.asarray(c["tcp_mm"], dtype=float))
            elif kind == "tracking":
                self._tracking.extend(c, cols)
            elif kind == "grating" and len(cols) == self.twin.n_joints:
                counts = np.column_stack([c[k] for k in cols])
                self._grating.extend(t, counts)
                self._latest_counts = counts[-1]
                self._latest_t_ns = int(t[-1])
                if self._first_t_ns is None:
                    self._first_t_ns = int(t[0])
            elif kind == "tracker":
                xyz = np.column_stack([c["x_mm"], c["y_mm"], c["z_mm"]]).astype(float)
                if "status" in c:
                    ok = (np.asarray(c["status"]) & TRACKER_VALID).all(axis=1)
                    xyz[~ok] = np.nan
                self._tracker.extend(t, xyz)
                self._tracker_xyz = xyz[-1]

    def _on_other(self, sample: Any) -> None:
        if not str(sample.key_expr).endswith("/health"):
            return
        try:
            doc = json.loads(sample.payload.to_bytes())
        except (ValueError, UnicodeDecodeError):
            return
        if isinstance(doc, dict):
            with self._lock:
                self._health = doc

    # -- the phase thread ------------------------------------------------------------------
    def _phases_loop(self) -> None:
        opts = PhaseOptions()
        while not self._stop.wait(self._phase_period_s):
            with self._lock:
                t, counts = self._grating.ordered()
                tr_t, tr_v = self._tracker.ordered()
                tw_t, tw_v = self._twin.ordered()
            if len(t) < 100:
                continue
            ph = find_phases(t, counts.astype(np.int64), opts)
            label = PhaseTimeline.from_phases(ph).label_at(int(t[-1]))
            found = self._new_poses(ph, tr_t, tr_v, tw_t, tw_v, int(t[-1]))
            with self._lock:
                # live, the window's counts ("of N") mean nothing: poses are counted from
                # the ones stored since the view started
                label = re.sub(r" of \d+", "", label)
                if "pose " in label:
                    head = label.split("pose ", 1)[0]
                    label = f"{head}pose {len(self._poses_t) + 1} since the view started"
                self._phase = label
                for row in found:
                    self._poses_t.append(row[0])
                    self._pose_points.append(row[1])
                    self._pose_twin.append(row[2])

    def _new_poses(
        self,
        ph: Any,
        tr_t: NDArray[np.int64],
        tr_v: FloatArray,
        tw_t: NDArray[np.int64],
        tw_v: FloatArray,
        now_ns: int,
    ) -> list[tuple[int, FloatArray, FloatArray]]:
        out = []
        for p in ph.poses:
            d = ph.dwells[p.dwell]
            if d.t1_ns >= now_ns or d.t0_ns in self._seen_pose_t0:
                continue  # still standing there, or stored already
            self._seen_pose_t0.add(d.t0_ns)
            sel = (tr_t >= d.t0_ns) & (tr_t <= d.t1_ns)
            pts = tr_v[sel]
            pts = pts[np.isfinite(pts).all(axis=1)]
            if len(pts) == 0:
                continue
            twin = np.full(3, np.nan)
            sel = (tw_t >= d.t0_ns) & (tw_t <= d.t1_ns)
            if sel.any():
                twin = tw_v[sel].mean(axis=0)
            out.append((d.t1_ns, pts.mean(axis=0), twin))
        return out

    # -- the viewer's thread -------------------------------------------------------------
    def latest(self) -> Snapshot:
        with self._lock:
            q, tcp = self._twin_q, self._twin_tcp
            published = self._twin_published_ns
            t_ns = self._twin_t_ns or self._latest_t_ns
            counts = self._latest_counts
            tracker = self._tracker_xyz
            health = dict(self._health)
            phase = self._phase
            pts = np.array(self._pose_points).reshape(-1, 3)
            twin_pts = np.array(self._pose_twin).reshape(-1, 3)
            first = self._first_t_ns
            tracking = tracking_text(self._tracking)
        note = ""
        read = self.twin.joint_deg(counts) if q is None and counts is not None else None
        if read is not None:
            # no live twin on the bus: the view's own model reads the gratings
            q = read[0]
            tcp = self.twin.tcp_mm(q, [t_ns])[0]
            note = "no live twin on twin/**: the view's model reads the gratings"
        elif q is None:
            note = "waiting for the live twin (twin/**) or gratings with --model"
        lat = health.get("latency_ms") or {}
        latency = (float(lat["p50"]), float(lat["p99"])) if {"p50", "p99"} <= set(lat) else None
        rate = health.get("rate_hz")
        return Snapshot(
            t_ns=t_ns,
            t_s=(t_ns - first) * 1e-9 if first and t_ns else 0.0,
            duration_s=None,
            q_deg=q,
            tcp_mm=tcp,
            tracker_mm=tracker if tracker is not None and np.isfinite(tracker).all() else None,
            pose_points_mm=pts,
            pose_twin_mm=twin_pts,
            phase=phase,
            rate_hz=float(rate) if rate is not None else None,
            latency_ms=latency,
            note=note,
            published_ns=published,
            tracking=tracking,
        )

    def close(self) -> None:
        self._stop.set()
        for r in self._receivers:
            r.close()
        self._phase_thread.join(timeout=5.0)
