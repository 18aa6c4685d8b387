"""``twin run`` live: collect the campaign from the daemon's zenoh keys, then publish the twin.

Collection subscribes to the daemon's data keys (default ``cell/**``; schemas by query),
accumulates the grating, tracker and encoder streams and prints progress (samples, dwells,
sweeps, Home returns, poses found so far). The campaign is over when poses have been found
and the gratings have been still for ``--idle-s``, when no data came for ``--idle-s`` (the
source stopped), or after ``--collect-s``. Streams stamped by host
clocks that disagree (the devices' ``host_clock`` in their health) are refused as a replay
refuses them (:func:`~calibration.twin.streams.check_host_clocks`). The same
pipeline as a replay then runs on the collected streams
(:func:`~calibration.twin.twin_run.run_twin`), and the twin it gives is published as it is in
memory (:meth:`CalibratedTwin.from_twin_run`).

The live twin (docs/topics.md, "Twin keys") is published per grating batch, at the grating
rate, on ``twin/<cell>/robot/<robot>/state`` (columnar ``daq.columnar.v1``, schema by
``<key>/@schema``): per grating sample its mapped time, the joint angles from the scale
calibration, the TCP from the calibrated model with its effects, the flange pose
(position and quaternion), and the encoder-minus-grating joint difference (the encoder
sample nearest in mapped time). ``twin/<cell>/robot/<robot>/health`` (JSON, once a second)
carries the end-to-end latency: publication time minus the grating sample's mapped time
(latch → twin), p50/p99/max over the period, for samples whose clock map had settled
(all samples, with ``clock_settled: false``, while none has).
The batches that arrived together are evaluated in one vectorized call (one TCP, flange
and scale evaluation per drain, not per 1 ms batch), and published as one batch.

When the model carries ``[tracking]`` (and not ``--no-tracking``) the twin follows the
robot: the tracker stream is subscribed too, each production dwell with the reflector on
the TCP updates the tracked model (:mod:`calibration.twin.live_tracking`), the state is
published from the tracked geometry from then on, and each update is a row on
``twin/<cell>/robot/<robot>/tracking`` (docs/tracking.md, "Live").

The twin reads the ``host_clock`` of the grating's and the tracker's devices from their
health (:mod:`calibration.twin.live_clocks`): while those hosts' clocks disagree beyond
the replay's 10 ms it says so, learns no tracking update from the pair, and its health's
``clocks`` says why (docs/deployment.md, "Clocks").
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration.errors import LiveTwinError
from calibration.twin.live_clocks import PairedClocks
from calibration.twin.phase_detection import PhaseOptions, find_dwells, find_phases
from calibration.twin.streams import (
    CellStreams,
    StreamBuilder,
    check_host_clocks,
    host_clock_of,
    pick_streams,
)
from calibration.twin.twin_keys import (
    TRACKING_STATES,
    TWIN_PREFIX,
    frames_schema,
    state_schema,
    tracking_schema,
    twin_keys,
)
from calibration.twin.twin_predictor import AngleReader, TwinPredictor, rotation_quaternions
from edges.stop_signals import on_stop_signals

if TYPE_CHECKING:
    import zenoh

    from calibration.model.description import RobotDescription
    from calibration.scales.scale_files import ScaleCalibration
    from calibration.twin.live_tracking import LiveTracker, LiveTrackUpdate
    from calibration.twin.tracking import TrackingSetup
    from calibration.twin.twin_run import TwinRun
    from daq.bus import Received

FloatArray = NDArray[np.float64]


def _percentiles(parts: list[np.ndarray]) -> dict[str, float]:
    a = np.concatenate(parts) if parts else np.zeros(0)
    if not a.size:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0, "n": 0}
    p50, p99 = np.percentile(a, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(a.max()), "n": int(a.size)}


@dataclass(frozen=True)
class LiveSettings:
    """How the live twin meets the daemon and when it stops (``twin run``'s options).

    ``key``: the key expression of the cell's streams; ``connect``/``listen``: zenoh
    endpoints (``none`` left out); ``mode``: ``client`` (default: the daemon's session then
    routes the twin's keys to everyone connected to it) or ``peer``; ``idle_s``: a silence
    that ends the collection; ``collect_s``/``publish_s``: time limits (0: none);
    ``wait_s``: the longest wait for the first grating batch; ``effects_radius_deg``: the
    effects are linearised within this radius (0: the full predictor per batch);
    ``frames_hz``: the rate of the link frames (0: none); ``tracking``: follow the robot
    through its production dwells when the model has ``[tracking]`` (docs/tracking.md,
    "Live"); ``alarm_mm``: its alarm (None: none)."""

    key: str = "cell/**"
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    listen: tuple[str, ...] = ()
    mode: str = "client"
    idle_s: float = 5.0
    collect_s: float = 0.0
    publish_s: float = 0.0
    wait_s: float = 60.0
    effects_radius_deg: float = 0.25
    frames_hz: float = 30.0
    tracking: bool = True
    alarm_mm: float | None = None

    @classmethod
    def from_options(cls, args: argparse.Namespace) -> LiveSettings:
        """The settings from ``twin run``'s parsed options (the command line's edge)."""
        return cls(
            key=args.key,
            connect=tuple(e for e in (args.connect or ["tcp/127.0.0.1:7447"]) if e != "none"),
            listen=tuple(e for e in (args.listen or ()) if e != "none"),
            mode=getattr(args, "mode", None) or "client",
            idle_s=float(args.idle_s),
            collect_s=float(args.collect_s or 0.0),
            publish_s=float(args.publish_s or 0.0),
            wait_s=float(getattr(args, "wait_s", 60.0)),
            effects_radius_deg=float(getattr(args, "effects_radius_deg", 0.25)),
            frames_hz=float(getattr(args, "frames_hz", 30.0)),
            tracking=not getattr(args, "no_tracking", False),
            alarm_mm=getattr(args, "alarm_mm", None),
        )

    def zenoh_config(self) -> Any:
        from daq.config import ZenohConfig, env_overrides

        # two peers connected to the daemon are not routed to each other: docs/topics.md,
        # "One endpoint reaches everything"
        listen = () if self.mode == "client" else self.listen
        # TLS to a router (docs/deployment.md): DAQ_ZENOH_TLS_CA, _CERTIFICATE, _PRIVATE_KEY
        env = env_overrides().get("zenoh", {})
        return ZenohConfig(
            mode=self.mode,
            listen=listen,
            connect=self.connect,
            tls_ca=str(env.get("tls_ca", "")),
            tls_certificate=str(env.get("tls_certificate", "")),
            tls_private_key=str(env.get("tls_private_key", "")),
        )


@dataclass(frozen=True, eq=False)
class CalibratedTwin:
    """What the live twin computes with: the calibrated description, the gratings' scale
    maps, the motor encoders' relation to the gratings (offsets ``(n,)`` deg, counts per
    turn) and the campaign clock's origin (ns); ``name`` names the model in the schemas."""

    description: RobotDescription
    scale: ScaleCalibration
    encoder_offset_deg: FloatArray
    encoder_counts_per_rev: float
    t0_ns: int
    name: str

    @classmethod
    def from_run(cls, run: Mapping[str, Any]) -> CalibratedTwin:
        """The twin an earlier ``twin run`` wrote (run.json's ``calibrated`` and
        ``files.scale``/``files.phases``, resolved paths): read at the command line's edge."""
        from calibration.model.description import load_robot
        from calibration.scales.scale_files import read_scale_toml

        desc = load_robot(run["calibrated"])
        phases = json.loads(Path(run["files"]["phases"]).read_text(encoding="utf-8"))
        return cls.of(desc, read_scale_toml(run["files"]["scale"]), phases, str(run["calibrated"]))

    @classmethod
    def from_twin_run(cls, run: TwinRun, name: str) -> CalibratedTwin:
        """The twin of a ``twin run`` in memory, as :meth:`from_run` reads it back from the
        files written of it (``name``: where its calibrated.toml is, as run.json says)."""
        export = run.export
        return cls.of(run.calibrated, export.scale_calibration(), export.phases, name)

    @classmethod
    def of(
        cls,
        description: RobotDescription,
        scale: ScaleCalibration,
        phases: Mapping[str, Any],
        name: str,
    ) -> CalibratedTwin:
        """From a run's values in memory (``phases``: the summary phases.json holds)."""
        from calibration.twin.campaign_measurement import ENCODER_COUNTS_PER_REV

        n = description.n_joints
        offset = np.asarray(phases.get("encoder_offset_deg") or [0.0] * n, dtype=float)
        cpr = float(phases.get("encoder_counts_per_rev", ENCODER_COUNTS_PER_REV))
        t0_ns = int(phases.get("campaign", {}).get("t0_ns", 0))
        return cls(description, scale, offset, cpr, t0_ns, name)


class LiveTwin:
    """One zenoh session: collect the campaign, then publish the twin."""

    def __init__(self, settings: LiveSettings, say: Callable[[str], None]) -> None:
        from daq.bus import Receiver, open_session

        self.args = settings
        self.say = say
        self.session = open_session(settings.zenoh_config())
        self.receiver = Receiver(self.session, settings.key, on_other=self._other)
        self.builders: dict[str, StreamBuilder] = {}
        self.collected_clocks: dict[str, dict[str, float]] = {}  # by health key
        self.clocks = PairedClocks({})
        self._health_subs: list[Any] = []
        self.closed = False

    # -- collection ------------------------------------------------------------------
    def _other(self, sample: zenoh.Sample) -> None:
        """A JSON sample on the collected keys (zenoh's thread): a device's health, whose
        ``host_clock`` is kept by key for the check after the collection."""
        key = str(sample.key_expr)
        clock = host_clock_of(sample.payload.to_bytes()) if key.endswith("/health") else None
        if clock is not None:  # one assignment: the collecting thread reads it
            self.collected_clocks = {**self.collected_clocks, key: clock}

    def _builder(self, got: Received) -> StreamBuilder:
        """The stream of ``got``'s key (made from its schema on its first batch)."""
        b = self.builders.get(got.key)
        if b is None:
            b = self.builders[got.key] = StreamBuilder(got.key, got.schema.to_json())
        return b

    def _add(self, got: Received) -> None:
        b = self._builder(got)
        if b.kind in ("grating", "tracker", "encoders"):
            b.add(got.header.batch_seq, got.columns)

    def collect(self) -> CellStreams:
        args, say = self.args, self.say
        started = time.monotonic()
        last_report = started
        opts = PhaseOptions()
        say(f"collecting {args.key} (connect {list(args.connect)})")
        last_data = None
        while True:
            got = self.receiver.receive(0.2)
            now = time.monotonic()
            if got is not None:
                self._add(got)
                last_data = now
            elif last_data is not None and now - last_data >= args.idle_s:
                say(f"no data for {args.idle_s:g} s: the source stopped, campaign over")
                break
            if args.collect_s and now - started >= args.collect_s:
                say("collection time is up")
                break
            if now - last_report < 5.0:
                continue
            last_report = now
            g = next((b for b in self.builders.values() if b.kind == "grating"), None)
            if g is None or not g._parts["t"]:
                say("waiting for grating samples")
                continue
            gs = g.build()
            ph = find_phases(gs.t_ns, gs.values, opts)
            s = ph.summary()
            n_sweep = sum(sum(v.values()) for v in s["sweep_stops"].values())
            say(
                f"{now - started:.0f} s: {len(gs)} grating samples, {s['dwells']} dwells, "
                f"{n_sweep} sweep stops, {sum(s['home_returns'].values())} Home returns, "
                f"{s['poses']['identify'] + s['poses']['validate']} poses"
            )
            if ph.poses:
                tail = find_dwells(gs.t_ns[-20000:], gs.values[-20000:], opts)
                if tail and tail[-1].i1 >= min(len(gs), 20000) - 2:
                    still_s = tail[-1].duration_s
                    if still_s >= args.idle_s:
                        say(f"the robot has been still for {still_s:.1f} s: campaign over")
                        break
        streams = pick_streams(self.builders, "live zenoh")
        check_host_clocks(streams, self.collected_clocks)  # as a replay: refused, saying why
        return streams

    # -- publication -----------------------------------------------------------------
    def _wait_for_grating(self) -> StreamBuilder:
        """The grating stream: collected already, or named by its first batch (--from),
        waited for at most ``--wait-s``."""
        args = self.args
        grating = next((b for b in self.builders.values() if b.kind == "grating"), None)
        wait_s = args.wait_s
        deadline = time.monotonic() + wait_s
        while grating is None:  # no collection (--from): the first grating batch names it
            if time.monotonic() >= deadline:
                raise LiveTwinError(
                    f"no grating samples on {args.key} within {wait_s:g} s "
                    f"(--connect {' '.join(args.connect)}, --wait-s)"
                )
            got = self.receiver.receive(min(1.0, max(0.0, deadline - time.monotonic())))
            if got is not None:
                self._add(got)
                grating = next((b for b in self.builders.values() if b.kind == "grating"), None)
        return grating

    def _narrow_to(self, grating: StreamBuilder, tracking: bool) -> None:
        """Subscribe to the grating key and the encoders' keys only (and the tracker's when
        ``tracking``; not whatever else ``--key`` matches): the twin's thread is woken for
        what it uses."""
        from calibration.twin.streams import stream_kind
        from daq.bus import Receiver, fetch_schemas

        kinds = ("encoders", "tracker") if tracking else ("encoders",)
        keys = [grating.key]
        trackers = []
        for key, schema in sorted(fetch_schemas(self.session, self.args.key).items()):
            kind = stream_kind(c.name for c in schema.columns)
            if key != grating.key and kind in kinds:
                keys.append(key)
                trackers += [key] if kind == "tracker" else []
        for key, b in sorted(self.builders.items()):
            if b.kind in kinds and key not in keys:
                keys.append(key)
                trackers += [key] if b.kind == "tracker" else []
        narrow = Receiver(self.session, keys)
        old, self.receiver = self.receiver, narrow
        old.close()
        self._watch_clocks(grating.key, trackers[0] if trackers else None)

    def _watch_clocks(self, grating: str, tracker: str | None) -> None:
        """Follow the ``host_clock`` in the health of the grating's device and of the
        tracker's (data keys; None: not tracking)."""
        import zenoh

        paired = {"grating": grating} | ({"tracker": tracker} if tracker else {})
        self.clocks = clocks = PairedClocks(
            {kind: key.rsplit("/", 1)[0] + "/health" for kind, key in paired.items()}
        )

        def take(sample: zenoh.Sample) -> None:  # zenoh's callback thread
            clocks.take(str(sample.key_expr), sample.payload.to_bytes())

        self._health_subs = [
            self.session.declare_subscriber(key, zenoh.handlers.Callback(take))
            for key in clocks.keys.values()
        ]

    def publish(self, twin: CalibratedTwin) -> int:
        """Publish ``twin`` as the gratings drive it until ``publish_s`` (or forever)."""
        import sys

        args, say = self.args, self.say
        grating = self._wait_for_grating()
        setup = self._tracking_setup(twin)
        self._narrow_to(grating, setup is not None)
        cell = str(grating.meta.get("cell", "cell"))
        robot = str(grating.meta.get("robot", "robot"))
        out = TwinPublication(self.session, twin, args, cell, robot, setup, self.clocks)
        say(f"publishing the live twin on {out.keys['state']} (health: {out.keys['health']})")
        if setup is not None:
            say(
                f"tracking {', '.join(setup.names)} from the production dwells "
                f"(on {out.keys['tracking']})"
            )
        stop = threading.Event()
        # SIGTERM (systemd) as SIGINT: the summary, a clean close; installed before the
        # line a supervisor waits for, so a signal right after it is not a kill
        on_stop_signals(stop.set)
        print(json.dumps({"twin": "live", "keys": out.keys}), flush=True)
        # the receiving thread waits for the interpreter at most this long while this
        # one computes (Python's default is 5 ms; the daemon uses the same)
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        started = time.monotonic()
        while not stop.is_set() and not (
            args.publish_s and time.monotonic() - started >= args.publish_s
        ):
            batch = self._drain()
            now_m = time.monotonic()
            clocks_said = self.clocks.check()
            if clocks_said is not None:
                say(clocks_said)
            gratings = self._gratings_of(batch, out)
            if gratings is not None:
                out.state(*gratings)
            doc = out.health(now_m)
            if doc is not None:
                end_to_end, own_share = doc["latency_ms"], doc["twin_ms"]
                say(
                    f"live twin: {doc['rate_hz']:.0f} samples/s, latency p50 "
                    f"{end_to_end['p50']:.1f} ms, p99 {end_to_end['p99']:.1f} ms "
                    f"(the twin's own p50 {own_share['p50']:.2f} ms)"
                    + ("" if doc["clock_settled"] else " (clock map not settled yet)")
                )
        out.close()
        say(f"published {out.seq} twin samples")
        return 0

    def _tracking_setup(self, twin: CalibratedTwin) -> TrackingSetup | None:
        """The tracking setup of the twin's model, or None (one line says why): off by
        ``--no-tracking``, or the model without ``[tracking]`` or anything to track."""
        from calibration.errors import TrackingError
        from calibration.twin.tracking import TrackingSettings, tracking_setup

        if not self.args.tracking:
            self.say("tracking off (--no-tracking): the calibrated model is published")
            return None
        if twin.description.tracking is None:
            self.say(
                "tracking off: the model has no [tracking] table (calibrate it again with "
                "this version's twin run or twin identify)"
            )
            return None
        try:
            return tracking_setup(
                twin.description, settings=TrackingSettings(alarm_mm=self.args.alarm_mm)
            )
        except TrackingError as exc:
            self.say(f"tracking off: the model {exc}")
            return None

    def _drain(self) -> list[Received]:
        """The batches that have arrived (at most ~500; the first waited for at most
        0.1 s): the daemon sends ~1 ms batches, one model evaluation per batch would fall
        behind, so they are evaluated together."""
        batch: list[Received] = []
        got = self.receiver.receive(0.1)
        while got is not None and len(batch) < 500:
            batch.append(got)
            got = self.receiver.receive(0.0)
        if got is not None:
            batch.append(got)
        return batch

    def _gratings_of(
        self, batch: list[Received], out: TwinPublication
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The batch's grating samples joined: counts ``(m, n)``, mapped times ``(m,)`` ns,
        whether each one's clock map had settled ``(m,)``, when the twin received it
        ``(m,)`` ns (None: no grating sample); the encoders' samples go to ``out``."""
        counts, t_map, ok, recv = [], [], [], []
        for got in batch:
            b = self._builder(got)
            cols = got.columns
            if b.kind == "grating":
                counts.append(np.column_stack([cols[c] for c in b.channels]))
                t_map.append(np.asarray(cols["t_mapped_ns"], dtype=np.int64))
                ok.append(np.asarray(cols["t_mapped_ok"], dtype=np.uint8))
                recv.append(np.full(len(t_map[-1]), got.t_recv_ns, dtype=np.int64))
            elif b.kind == "encoders":
                out.encoders(cols["t_mapped_ns"], np.column_stack([cols[c] for c in b.channels]))
            elif b.kind == "tracker" and out.tracker is not None:
                if not self.clocks.admits(len(cols["t_mapped_ns"])):  # clocks apart/unknown
                    continue
                xyz = np.column_stack([cols[c] for c in b.channels]).astype(float)
                out.tracker.add_tracker(cols["t_mapped_ns"], xyz, b.status_of(cols))
        if not counts:
            return None
        return _joined(counts), _joined(t_map), _joined(ok) == 1, _joined(recv)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for sub in self._health_subs:
            sub.undeclare()
        self.receiver.close()
        self.session.close()


def _joined(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts) if len(parts) > 1 else parts[0]


class TwinPublication:
    """One publication of a :class:`CalibratedTwin` on a cell's twin keys: the publishers,
    the model's evaluators (:class:`AngleReader`, :class:`TwinPredictor`) and what runs on
    between batches (sample numbers, the encoders' recent samples, this period's
    latencies). :meth:`LiveTwin.publish` feeds it."""

    def __init__(
        self,
        session: Any,
        twin: CalibratedTwin,
        settings: LiveSettings,
        cell: str,
        robot: str,
        tracking: TrackingSetup | None = None,
        clocks: PairedClocks | None = None,
    ) -> None:
        from daq.bus import JSON_ENCODING, ChannelPublisher, SchemaServer

        desc = twin.description
        n = desc.n_joints
        self.twin = twin
        self.cell, self.robot = cell, robot
        self.clocks = clocks if clocks is not None else PairedClocks({})
        self.keys = twin_keys(cell, robot)
        self.gear = np.array(desc.gear_ratios, dtype=float)
        radius = settings.effects_radius_deg
        self.predictor = TwinPredictor(desc, radius_deg=radius)
        self.reader = AngleReader(twin.scale, n, desc.home, radius_deg=radius)
        self.schemas = SchemaServer(session, TWIN_PREFIX)
        state = state_schema(self.keys["state"], n, cell, robot, twin.name)
        self.state_pub = ChannelPublisher(session, state, schemas=self.schemas)
        names = self.predictor.frame_names
        frames = frames_schema(self.keys["frames"], names, cell, robot, twin.name)
        self.frames_pub = ChannelPublisher(session, frames, schemas=self.schemas)
        self.health_pub = session.declare_publisher(self.keys["health"], encoding=JSON_ENCODING)
        self.tracker: LiveTracker | None = None
        self.tracking_pub: Any = None
        self.tracking_seq = 0
        self.last_tracking: dict[str, Any] = {}
        if tracking is not None:
            from calibration.twin.live_tracking import LiveTracker

            self.tracker = LiveTracker(tracking, desc, self.reader.exact, twin.t0_ns)
            sch = tracking_schema(self.keys["tracking"], tracking.names, cell, robot, twin.name)
            self.tracking_pub = ChannelPublisher(session, sch, schemas=self.schemas)
        hz = settings.frames_hz
        self.frames_every_ns = int(1e9 / hz) if hz > 0 else None
        self.next_frames_ns = 0
        self.enc_t = np.empty(0, dtype=np.int64)
        self.enc_v = np.empty((0, n))
        self.seq = self.frames_seq = 0
        self.lat: list[np.ndarray] = []  # end to end, settled clock maps (ms)
        self.lat_all: list[np.ndarray] = []
        self.upstream: list[np.ndarray] = []  # latch -> zenoh handed the batch to the twin
        self.own: list[np.ndarray] = []  # zenoh handed it over -> the twin published
        self.period_start = time.monotonic()
        self.samples_period = 0

    def encoders(self, t_mapped_ns: np.ndarray, counts: np.ndarray) -> None:
        """Motor encoder samples (counts ``(m, n)``) as joint angles, the newest 2000 kept."""
        twin = self.twin
        deg = counts.astype(float) / twin.encoder_counts_per_rev * 360.0 / self.gear
        deg += twin.encoder_offset_deg
        self.enc_t = np.concatenate((self.enc_t, t_mapped_ns))[-2000:]
        self.enc_v = np.concatenate((self.enc_v, deg))[-2000:]

    def state(
        self, counts: np.ndarray, t_map: np.ndarray, settled: np.ndarray, recv: np.ndarray
    ) -> None:
        """Publish the twin's state of grating samples (counts ``(m, n)``, mapped times
        ``(m,)`` ns, clock maps settled ``(m,)``, received ``(m,)`` ns), note their
        latencies, and the link frames of the newest one when they are due."""
        m, n = counts.shape
        q = self.reader.angles(counts)
        t_s = (t_map - self.twin.t0_ns) * 1e-9
        tcp, fl = self.predictor.tcp_and_flange(np.radians(q), t_s)
        diff = np.full((m, n), np.nan)
        if self.enc_t.size:
            idx = np.clip(np.searchsorted(self.enc_t, t_map), 0, self.enc_t.size - 1)
            diff = self.enc_v[idx] - q
        t_pub = time.time_ns()
        self.state_pub.publish(
            {
                "seq": np.arange(self.seq, self.seq + m, dtype=np.uint64),
                "t_mapped_ns": t_map,
                "t_publish_ns": np.full(m, t_pub, dtype=np.int64),
                "q_deg": q,
                "tcp_mm": tcp,
                "flange_mm": fl[:, :3, 3],
                "flange_quat": rotation_quaternions(fl[:, :3, :3]),
                "encoder_minus_grating_deg": diff,
            }
        )
        self.seq += m
        self.samples_period += m
        # latency on settled clock maps only (provisional mapped times can be off)
        self.lat.append((t_pub - t_map[settled]) * 1e-6)
        self.lat_all.append((t_pub - t_map) * 1e-6)
        self.upstream.append((recv[settled] - t_map[settled]) * 1e-6)
        self.own.append((t_pub - recv) * 1e-6)
        # the link frames of the newest sample, at a bounded rate (for viewers and
        # recorders: Foxglove's frame transforms), after the state went out
        if self.frames_every_ns is not None and t_pub >= self.next_frames_ns:
            self.next_frames_ns = t_pub + self.frames_every_ns
            pos, quat = self.predictor.frames(np.radians(q[-1:]))
            self.frames_pub.publish(
                {
                    "seq": np.array([self.frames_seq], dtype=np.uint64),
                    "t_mapped_ns": t_map[-1:],
                    "frame_mm": pos,
                    "frame_quat": quat,
                }
            )
            self.frames_seq += 1
        if self.tracker is not None:  # after the state went out: off the latency path
            self.tracker.add_gratings(t_map, counts)
            ups = self.tracker.updates()
            if ups:
                self._tracked(ups)

    def _tracked(self, ups: list[LiveTrackUpdate]) -> None:
        """Dwells updated the tracked model: publish from its geometry from now on (one
        rebuild of the chain per update, none per batch) and put the updates out."""
        assert self.tracker is not None and self.tracking_pub is not None
        self.predictor.set_geometry(self.tracker.geometry)
        m = len(ups)
        codes = {s: i for i, s in enumerate(TRACKING_STATES)}
        self.tracking_pub.publish(
            {
                "seq": np.arange(self.tracking_seq, self.tracking_seq + m, dtype=np.uint64),
                "t_mapped_ns": np.array([u.check.t_ns for u in ups], dtype=np.int64),
                "t_publish_ns": np.full(m, time.time_ns(), dtype=np.int64),
                "point_mm": np.array([u.check.point_mm for u in ups]),
                "predicted_mm": np.array([u.step.predicted_mm for u in ups]),
                "error_mm": np.array([u.step.error_mm for u in ups]),
                "parameters": np.array([u.parameters for u in ups]),
                "standard_errors": np.array([u.standard_errors for u in ups]),
                "lambda": np.array([u.step.forgetting for u in ups]),
                "state": np.array([codes[u.step.state] for u in ups], dtype=np.uint8),
                "displacement_mm": np.array([u.step.displacement_mm for u in ups]),
                "steps": np.array([u.steps for u in ups], dtype=np.uint32),
                "alarms": np.array([u.alarms for u in ups], dtype=np.uint32),
            }
        )
        self.tracking_seq += m
        last = ups[-1]
        self.last_tracking = {
            "updates": self.tracking_seq,
            "state": last.step.state,
            "error_mm": last.step.error_mm,
            "steps": last.steps,
            "alarms": last.alarms,
        }

    def health(self, now_m: float) -> dict[str, Any] | None:
        """Once a second (``now_m``: monotonic s): the health document of the period, put
        on the health key, and a new period begun; None within a period."""
        elapsed = now_m - self.period_start
        if elapsed < 1.0:
            return None
        settled = any(x.size for x in self.lat)
        reader = self.reader
        doc = {
            "t_host_ns": time.time_ns(),
            "cell": self.cell,
            "robot": self.robot,
            "state": "publishing",
            "rate_hz": self.samples_period / elapsed,
            "samples": self.seq,
            "latency_ms": _percentiles(self.lat if settled else self.lat_all),
            "latency": "publication time minus the grating sample's mapped time",
            "upstream_ms": _percentiles(self.upstream),
            "upstream": "the twin's receipt of the batch minus the mapped time "
            "(device, daemon, zenoh)",
            "twin_ms": _percentiles(self.own),
            "twin": "publication time minus the twin's receipt (the twin's own share)",
            "clock_settled": settled,
            "model": self.twin.name,
            "tracking": self._tracking_health(),
            "clocks": self.clocks.doc(),
            "effects": self.predictor.describe(),
            "scale_maps": {
                "linearised_radius_deg": reader.radius_deg,
                "linearisations": reader.refreshes,
                "full_map_calls": reader.full_calls,
            },
        }
        self.health_pub.put(json.dumps(doc))
        self.period_start, self.samples_period = now_m, 0
        self.lat, self.lat_all, self.upstream, self.own = [], [], [], []
        return doc

    def _tracking_health(self) -> dict[str, Any]:
        """The health document's ``tracking``: on or off, the dwells skipped as another
        target's, and the latest update's state (docs/topics.md)."""
        if self.tracker is None:
            return {"on": False}
        return {"on": True, "other_targets": self.tracker.other_targets, **self.last_tracking}

    def close(self) -> None:
        self.state_pub.close()
        self.frames_pub.close()
        if self.tracking_pub is not None:
            self.tracking_pub.close()
        self.health_pub.undeclare()
        self.schemas.close()
