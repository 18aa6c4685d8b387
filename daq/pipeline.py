"""One device's path: driver batches → clock map → columnar batches on zenoh (+ MCAP).

:class:`DeviceStream` runs in its own thread. It reads the driver (which owns timeouts,
host receive stamps and reconnects), maps device time to host time with
:class:`daq.clock_sync.DeviceClockMap`, counts gaps and sequence breaks, coalesces reads
into batches of at most ``max_batch_samples`` or ``max_batch_age_s``, and publishes one
message per channel group (and writes it to the device's
:class:`~daq.device_recording.DeviceRecording`, when recording). It keeps a liveliness
token while the device is connected and gives its health document on request
(:meth:`DeviceStream.health`, once a period by a :class:`~daq.health.HealthLoop`).

Published clocks: ``host_utc`` is CLOCK_REALTIME ns since the Unix epoch, obtained from
the driver's ``time.monotonic_ns`` stamps plus one offset taken when the daemon started
(so an NTP step during a run does not break the stream's monotonicity); ``device`` is the
device's own µs clock, unwrapped by the driver, valid within one ``epoch``.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh
from numpy.typing import NDArray

from daq.bus import (
    ChannelPublisher,
    PublishError,
    SchemaServer,
    channel_key,
    device_key,
    health_key,
)
from daq.clock_sync import DeviceClockMap
from daq.columnar import Column, StreamSchema
from daq.config import ChannelGroup, DaqConfig, DeviceConfig
from daq.device_recording import DeviceRecording
from daq.errors import ConfigError, TransportError
from daq.scheduling import describe as describe_scheduling
from drivers.base import BatchSchema, ChannelSchema, Driver, SampleBatch

log = logging.getLogger(__name__)

HOST_CLOCK = "host_utc"
DEFAULT_CHANNEL = "samples"
#: status bit the daemon sets on a sample that follows a sequence gap (driver bits below)
TIME_COLUMNS = ("seq", "epoch", "t_device_us", "t_host_rx_ns", "t_mapped_ns", "t_mapped_ok")
#: the clock fit is trusted once it has this many bucket minima (0.25 s each) ...
SETTLED_POINTS = 8
#: ... a plausible drift, and a tight lower envelope
SETTLED_MAX_DRIFT_PPM = 500.0
SETTLED_MAX_RMS_NS = 1_000_000.0
#: rx delays kept per batch for the health percentiles (a strided subsample)
RX_DELAY_SAMPLES = 64
#: the clock fit is fed at most this often (the least-delayed sample since the last feed)
CLOCK_FEED_NS = 20_000_000


#: a device's channel groups: each one's schema and the driver columns it carries
ChannelGroups = list[tuple[StreamSchema, NDArray[np.intp]]]


def build_schemas(
    cfg: DaqConfig, dev: DeviceConfig, driver_schema: BatchSchema, utc_offset_ns: int
) -> ChannelGroups:
    """The columnar schema of every channel group of ``dev`` and its driver columns."""
    names = [c.name for c in driver_schema.channels]
    groups = dev.channels or (ChannelGroup(DEFAULT_CHANNEL, ()),)
    out = []
    for g in groups:
        members = list(g.channels) or names
        missing = [m for m in members if m not in names]
        if missing:
            raise ConfigError(
                f"{cfg.source}: [[device]] {dev.name!r}: [channels] {g.name!r}: driver "
                f"{dev.driver!r} has no channel {missing[0]!r} (it has: {', '.join(names)})"
            )
        idx = np.array([names.index(m) for m in members], dtype=np.intp)
        cols = _time_columns(dev.name)
        chans = [driver_schema.channels[i] for i in idx]
        for c in chans:
            cols.append(Column(c.name, c.dtype, unit=c.unit, description=c.description))
        cols.append(
            Column(
                "status",
                "uint16",
                (len(chans),),
                description="per-channel status bits, in the order of status_channels",
            )
        )
        joints = None
        if dev.joints is not None:
            joints = [dev.joints[i] if i < len(dev.joints) else None for i in idx.tolist()]
        meta = _group_meta(cfg, dev, g.name, driver_schema, chans, joints, utc_offset_ns)
        key = channel_key(cfg.cell.name, dev.robot, dev.name, g.name)
        out.append((StreamSchema(key, tuple(cols), meta), idx))
    return out


def _time_columns(device: str) -> list[Column]:
    """The columns every group of ``device`` starts with (:data:`TIME_COLUMNS`)."""
    return [
        Column("seq", "uint64", description="sample sequence number (device's, unwrapped)"),
        Column("epoch", "int32", description="device restarts seen before this sample"),
        Column(
            "t_device_us",
            "int64",
            unit="us",
            clock=f"device:{device}",
            description="device clock at the latch, unwrapped, valid within one epoch",
        ),
        Column(
            "t_host_rx_ns",
            "int64",
            unit="ns",
            clock=HOST_CLOCK,
            description="host time when the frame carrying the sample was received",
        ),
        Column(
            "t_mapped_ns",
            "int64",
            unit="ns",
            clock=HOST_CLOCK,
            description="device time mapped to the host clock (online offset+drift fit)",
        ),
        Column(
            "t_mapped_ok",
            "uint8",
            description="1: the clock fit had settled when this sample was mapped; 0: "
            "provisional (first seconds after a start or restart, backlog catch-up)",
        ),
    ]


def _group_meta(
    cfg: DaqConfig,
    dev: DeviceConfig,
    group: str,
    driver_schema: BatchSchema,
    chans: list[ChannelSchema],
    joints: list[int | None] | None,
    utc_offset_ns: int,
) -> dict[str, Any]:
    """The schema metadata of channel group ``group`` of ``dev``: where its samples come
    from, its clocks, its status channels (``chans``) and the joint of each."""
    return {
        "cell": cfg.cell.name,
        "robot": dev.robot,
        "device": dev.name,
        "channel": group,
        "driver": dev.driver,
        "driver_kind": driver_schema.kind,
        "url": dev.url,
        "source": driver_schema.source,
        "device_clock": driver_schema.device_clock,
        "host_clock": "host_utc: CLOCK_REALTIME ns since 1970 (monotonic + offset at start)",
        "host_utc_minus_monotonic_ns": utc_offset_ns,
        "status_channels": [c.name for c in chans],
        "status_bits": {str(k): v for k, v in driver_schema.status_bits.items()},
        "joints": joints,
        "rate_hz": dev.rate_hz,
    }


@dataclass
class Counters:
    samples: int = 0
    batches: int = 0
    bytes: int = 0
    gaps: int = 0  # sequence jumps within an epoch
    samples_missing: int = 0  # samples those jumps skipped
    seq_breaks: int = 0  # sequence went back or repeated within an epoch
    epochs: int = 0  # device restarts seen (epoch changes)
    time_gaps: int = 0  # device-clock steps > 1.5 periods within an epoch (needs rate_hz)
    time_missing_s: float = 0.0  # device time those steps skipped beyond one period
    publish_errors: int = 0
    messages_unsent: int = 0  # encoded and recorded, but their put failed (lost on the wire)
    messages_unmatched: int = 0  # put while no subscriber matched (none, or router out of reach)
    away_s: float = 0.0  # time not connected (after the first connection)
    window_samples: int = 0
    window_rx_delay_ns: list[NDArray[np.int64]] = field(default_factory=list)


def _first_of_power2(n: int) -> bool:
    """Log the 1st, 2nd, 4th, 8th... occurrence."""
    return n & (n - 1) == 0


class DeviceStream:
    """Reads one driver and publishes its samples; see the module docstring."""

    def __init__(
        self,
        cfg: DaqConfig,
        dev: DeviceConfig,
        driver: Driver,
        session: zenoh.Session,
        schemas: SchemaServer,
        *,
        groups: ChannelGroups,
        recording: DeviceRecording | None = None,
        utc_offset_ns: int,
        stop: threading.Event,
    ) -> None:
        self.cfg = cfg
        self.dev = dev
        self.driver = driver
        self.session = session
        self.recording = recording
        self.utc_offset_ns = utc_offset_ns
        self._stop = stop
        self.counters = Counters()
        self.groups = groups  # build_schemas of the driver's schema (the caller's: once)
        # groups carrying every driver channel in order pass the status array as it is
        n_ch = driver.schema.n_channels
        self._all_channels = [np.array_equal(idx, np.arange(n_ch)) for _, idx in self.groups]
        cc = cfg.zenoh.congestion_control
        self.publishers = [
            ChannelPublisher(session, s, congestion=cc, schemas=schemas) for s, _ in self.groups
        ]
        self.clock = self._new_clock()
        self._epoch: int | None = None
        self._last_seq: int | None = None
        self._last_t_dev: tuple[int, int] | None = None
        self._clock_best: tuple[int, int] | None = None  # (device µs, host ns) to feed
        self._clock_fed = 0  # host ns of the last feed
        self._settled = False
        n_ok = max(1, 2 * cfg.publish.max_batch_samples)
        self._ok_ones = np.ones(n_ok, np.uint8)  # t_mapped_ok columns, sliced (read-only)
        self._ok_zeros = np.zeros(n_ok, np.uint8)
        self._ok_ones.flags.writeable = False
        self._ok_zeros.flags.writeable = False
        self._token: Any = None
        self._lock = threading.Lock()
        self._connected_once = False
        self._state = "opening"
        self._away_since: float | None = None
        self._thread = threading.Thread(target=self._run, name=f"dev-{dev.name}", daemon=True)
        self.error: BaseException | None = None
        self.scheduling = "normal"  # the acquisition thread's, once it runs

    def _new_clock(self) -> DeviceClockMap:
        # restarts are the driver's to detect (epoch); a backlog read after a reconnect is
        # late, not a restart, so the map must not start a new segment on disagreement
        return DeviceClockMap(
            tick_s=1e-6,
            window_s=self.dev.clock_window_s,
            restart_tolerance_s=1e9,
            latency_ns=int(self.dev.clock_latency_us * 1000),
        )

    # -- lifecycle --------------------------------------------------------------------------
    @property
    def keys(self) -> list[str]:
        return [p.key for p in self.publishers]

    @property
    def health_key(self) -> str:
        return health_key(self.cfg.cell.name, self.dev.robot, self.dev.name)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Ask the thread to stop (it publishes what it holds and closes the driver);
        sets the stop event it was given (the daemon's streams share one)."""
        self._stop.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread.ident is not None:  # started
            self._thread.join(timeout)

    @property
    def state(self) -> str:
        return self._state

    def _set_alive(self, alive: bool) -> None:
        if alive and self._token is None:
            self._token = self.session.liveliness().declare_token(
                device_key(self.cfg.cell.name, self.dev.robot, self.dev.name)
            )
        elif not alive and self._token is not None:
            token, self._token = self._token, None
            try:
                token.undeclare()
            except Exception:  # session already closed
                log.debug("liveliness undeclare failed", exc_info=True)

    def _track_state(self) -> None:
        state = self.driver.health().state
        now = time.monotonic()
        connected = state == "connected"
        if connected:
            self._connected_once = True
            if self._away_since is not None:
                self.counters.away_s += now - self._away_since
                self._away_since = None
        elif self._connected_once and self._away_since is None:
            self._away_since = now
        self._state = state
        self._set_alive(connected)

    def _open(self) -> bool:
        from drivers.errors import DriverError

        while not self._stop.is_set():
            try:
                self.driver.open(timeout_s=min(self.dev.open_timeout_s, 1.0))
                return True
            except DriverError as exc:
                self._state = "reconnecting"
                log.warning("%s: %s (retrying)", self.dev.name, exc)
                self._stop.wait(0.2)
        return False

    def _run(self) -> None:
        pub = self.cfg.publish
        pending: list[Any] = []
        n_pending = 0
        first_ns = 0
        self.scheduling = describe_scheduling()
        try:
            if not self._open():
                return
            last_state_check = 0.0
            while True:
                stopping = self._stop.is_set()
                now = time.monotonic()
                if now - last_state_check > 0.02:
                    self._track_state()
                    last_state_check = now
                # stopping: one last read without waiting (if connected: no reconnect
                # attempt), so rows the driver holds are published, not dropped
                timeout = 0.0
                if not stopping:
                    timeout = pub.read_timeout_s
                    if pending:
                        age_left = pub.max_batch_age_s - (time.monotonic_ns() - first_ns) / 1e9
                        timeout = max(0.0, min(timeout, age_left))
                if not stopping or self._state == "connected":
                    batch = self.driver.read(timeout_s=timeout)
                    if len(batch):
                        if not pending:
                            first_ns = int(batch.t_host_ns[0])
                        pending.append(batch)
                        n_pending += len(batch)
                aged = pending and time.monotonic_ns() - first_ns >= pub.max_batch_age_s * 1e9
                if pending and (stopping or aged):
                    self._process(pending)
                    pending, n_pending = [], 0
                elif n_pending >= pub.max_batch_samples:
                    # a source ahead of us: full messages only, the rest waits for the next
                    # read or its age (a short tail message would cost as much as a full one)
                    whole = SampleBatch.concat(self.driver.schema, pending)
                    cut = n_pending - n_pending % pub.max_batch_samples
                    self._process([whole[:cut]])
                    pending, n_pending = [], 0
                    if cut < len(whole):
                        pending, n_pending = [whole[cut:]], len(whole) - cut
                        first_ns = int(whole.t_host_ns[cut])
                if stopping:
                    break
        except BaseException as exc:  # keep the daemon up; report in health
            self.error = exc
            log.exception("%s: acquisition thread failed", self.dev.name)
        finally:
            try:
                self.driver.close()
            finally:
                self._set_alive(False)
                self._state = "closed"

    # -- one batch ------------------------------------------------------------------------
    def _process(self, batches: list[Any]) -> None:
        """Map, count, publish and record one read's batches (concatenated when several).
        Long because it is the per-batch hot path: its arrays and counters are locals the
        steps share, and a split would add calls per batch and per channel group."""
        if len(batches) == 1:
            b0 = batches[0]
            seq, t_dev, epoch = b0.seq, b0.t_device_us, b0.epoch
            t_host, values, status = b0.t_host_ns, b0.values, b0.status
        else:
            seq = np.concatenate([b.seq for b in batches])
            t_dev = np.concatenate([b.t_device_us for b in batches])
            epoch = np.concatenate([b.epoch for b in batches])
            t_host = np.concatenate([b.t_host_ns for b in batches])
            values = np.concatenate([b.values for b in batches])
            status = np.concatenate([b.status for b in batches])
        # epochs only ever rise: first == last means one epoch (the common case, whose
        # bookkeeping below avoids numpy calls: a 1 kHz device sends 1-4 samples a message)
        one = int(epoch[0]) if int(epoch[0]) == int(epoch[-1]) else None
        mapped, mapped_ok = self._map(t_dev, epoch, t_host, one)
        self._count_gaps(seq, epoch, one)
        self._count_time_gaps(t_dev, epoch, one)
        c = self.counters
        n = len(seq)
        c.samples += n
        c.window_samples += n
        # the health percentiles need a sample of the delays, not millions a second
        stride = max(1, n // RX_DELAY_SAMPLES)
        c.window_rx_delay_ns.append(t_host[::stride] - mapped[::stride])
        off = self.utc_offset_ns
        base = {
            "seq": seq,
            "epoch": epoch,
            "t_device_us": t_dev,
            "t_host_rx_ns": t_host + off,
            "t_mapped_ns": mapped + off,
            "t_mapped_ok": mapped_ok,
        }
        step = self.cfg.publish.max_batch_samples
        for gi, ((schema, idx), publisher) in enumerate(
            zip(self.groups, self.publishers, strict=True)
        ):
            cols = dict(base)
            for j, col in zip(idx.tolist(), schema.columns[len(TIME_COLUMNS) :], strict=False):
                cols[col.name] = values[:, j]
            # the usual group takes no fancy-index copy (whose result can come out
            # column-major and cost the encoder another copy)
            whole = self._all_channels[gi]
            cols["status"] = status if whole else np.ascontiguousarray(status[:, idx])
            seq0 = publisher.batch_seq
            sent0, bytes0 = publisher.messages, publisher.bytes
            errors0 = publisher.put_errors
            unmatched0 = publisher.unmatched
            try:
                payloads = publisher.publish_slices(cols, step)
            except PublishError as exc:
                # not on the wire (subscribers see the batch_seq hole as lost batches),
                # but counted here and still recorded: the recording stays complete
                payloads = exc.payloads
                c.publish_errors += publisher.put_errors - errors0
                c.messages_unsent += publisher.put_errors - errors0
                if not isinstance(exc.cause, TransportError) and _first_of_power2(c.publish_errors):
                    log.error("%s: publish failed: %r", schema.key, exc.cause)
            except Exception:  # encoding failed: nothing to send or record
                c.publish_errors += 1
                if _first_of_power2(c.publish_errors):
                    log.exception("%s: publish failed", schema.key)
                continue
            t_pub = time.time_ns()
            c.messages_unmatched += publisher.unmatched - unmatched0
            c.batches += publisher.messages - sent0  # published: unsent ones are counted
            c.bytes += publisher.bytes - bytes0  # in messages_unsent
            if self.recording is not None:
                self.recording.write(gi, payloads, t_pub, seq0, cols)

    def _map(
        self,
        t_dev: NDArray[np.int64],
        epoch: NDArray[np.int32],
        t_host: NDArray[np.int64],
        one_epoch: int | None = None,
    ) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
        """Mapped monotonic ns and settled flags; a new clock map per device epoch."""
        n = len(t_host)
        if one_epoch is not None and (self._epoch is None or one_epoch == self._epoch):
            self._epoch = one_epoch
            self._feed_clock(t_dev, t_host)
            ok = self._ok_ones if self._settled else self._ok_zeros
            return self.clock.map(t_dev), ok[:n] if n <= len(ok) else np.full(
                n, self._settled, np.uint8
            )
        out = np.empty_like(t_host)
        ok = np.zeros(n, np.uint8)
        starts = np.flatnonzero(np.diff(epoch)) + 1
        bounds = [0, *starts.tolist(), len(epoch)]
        for a, b in itertools.pairwise(bounds):
            ep = int(epoch[a])
            if self._epoch is not None and ep != self._epoch:
                self.counters.epochs += 1
                self.clock = self._new_clock()
                self._last_seq = None
                self._clock_best = None
                self._clock_fed = 0
                self._settled = False
            self._epoch = ep
            td, th = t_dev[a:b], t_host[a:b]
            self._feed_clock(td, th)
            out[a:b] = self.clock.map(td)
            ok[a:b] = self._settled
        return out, ok

    def _feed_clock(self, td: NDArray[np.int64], th: NDArray[np.int64]) -> None:
        # only the lowest apparent delay matters to the lower-envelope fit (its buckets
        # keep one minimum per 0.25 s): keep the best point and feed it every
        # CLOCK_FEED_NS; the caller maps the whole run with the current fit
        k = int(np.argmin(th - td * 1000)) if len(td) > 1 else 0
        d, h = int(td[k]), int(th[k])
        best = self._clock_best
        if best is None or h - d * 1000 < best[1] - best[0] * 1000:
            self._clock_best = best = (d, h)
        now = int(th[-1])
        if not self._clock_fed or now - self._clock_fed >= CLOCK_FEED_NS:
            self.clock.update(np.array([best[0]]), np.array([best[1]]))
            self._clock_best = None
            self._clock_fed = now
            q = self.clock.quality()
            self._settled = (
                q.points >= SETTLED_POINTS
                and abs(q.drift_ppm) < SETTLED_MAX_DRIFT_PPM
                and q.envelope_rms_ns < SETTLED_MAX_RMS_NS
            )

    def _count_gaps(
        self, seq: NDArray[Any], epoch: NDArray[np.int32], one_epoch: int | None = None
    ) -> None:
        n = len(seq)
        if not n:
            return
        c = self.counters
        last = self._last_seq
        if last is not None and one_epoch is not None:
            s0, s1 = int(seq[0]), int(seq[-1])
            if s0 == last + 1 and s1 - s0 == n - 1 and (n <= 2 or bool(np.all(np.diff(seq) == 1))):
                self._last_seq = s1
                return  # contiguous: the common case
        seq = seq.astype(np.int64)
        prev = np.concatenate([[seq[0] - 1 if last is None else last], seq])
        same = np.concatenate([[True], np.diff(epoch) == 0])
        d = np.diff(prev)
        jumps = same & (d > 1)
        c.gaps += int(np.count_nonzero(jumps))
        c.samples_missing += int(np.sum(d[jumps] - 1))
        c.seq_breaks += int(np.count_nonzero(same & (d < 1)))
        self._last_seq = int(seq[-1])

    def _count_time_gaps(
        self, t_dev: NDArray[np.int64], epoch: NDArray[np.int32], one_epoch: int | None = None
    ) -> None:
        """Gaps in device time: a driver may renumber its sequence across a reconnect."""
        n = len(t_dev)
        if self.dev.rate_hz is None or not n:
            return
        period_us = 1e6 / self.dev.rate_hz
        last = self._last_t_dev
        if last is not None and one_epoch is not None and last[1] == one_epoch:
            limit = 1.5 * period_us
            t0 = int(t_dev[0])
            if t0 - last[0] <= limit and (n == 1 or int(np.diff(t_dev).max()) <= limit):
                self._last_t_dev = (int(t_dev[-1]), one_epoch)
                return  # no gap: the common case
        prev = t_dev[0] if last is None or last[1] != int(epoch[0]) else last[0]
        dt = np.diff(np.concatenate([[prev], t_dev]))
        same = np.concatenate([[True], np.diff(epoch) == 0])
        big = same & (dt > 1.5 * period_us)
        if big.any():
            self.counters.time_gaps += int(np.count_nonzero(big))
            self.counters.time_missing_s += float(np.sum(dt[big] - period_us)) / 1e6
        self._last_t_dev = (int(t_dev[-1]), int(epoch[-1]))

    # -- health ---------------------------------------------------------------------------
    def health(self, period_s: float) -> dict[str, Any]:
        """The health document (docs/topics.md); resets the per-period window."""
        c = self.counters
        h = self.driver.health()
        dc = h.counters
        q = self.clock.quality()
        delays = c.window_rx_delay_ns
        c.window_rx_delay_ns = []
        lat: dict[str, float] | None = None
        if delays:
            d = np.concatenate(delays) / 1e6
            lat = {"p50": float(np.percentile(d, 50)), "p99": float(np.percentile(d, 99))}
        away = c.away_s + (
            time.monotonic() - self._away_since if self._away_since is not None else 0.0
        )
        doc = {
            "t_host_ns": time.time_ns(),
            "cell": self.cfg.cell.name,
            "robot": self.dev.robot,
            "device": self.dev.name,
            "driver": self.dev.driver,
            "url": self.dev.url,
            "state": self._state,
            "alive": self._token is not None,
            "rate_hz": c.window_samples / period_s if period_s > 0 else 0.0,
            "expected_rate_hz": self.dev.rate_hz,
            "samples": c.samples,
            "batches": c.batches,
            "bytes": c.bytes,
            "gaps": c.gaps,
            "samples_missing": c.samples_missing,
            "seq_breaks": c.seq_breaks,
            "time_gaps": c.time_gaps,
            "time_missing_s": c.time_missing_s,
            "lost_samples": dc.get("lost_samples", 0),
            "crc_errors": dc.get("crc_errors", 0),
            "timeouts": dc.get("timeouts", 0),
            "disconnects": dc.get("disconnects", 0),
            "reconnects": dc.get("reconnects", 0),
            "device_restarts": c.epochs,
            "away_s": away,
            "publish_errors": c.publish_errors,
            "messages_unsent": c.messages_unsent,
            "messages_unmatched": c.messages_unmatched,
            "rx_delay_ms": lat,
            "clock": {
                "offset_ns": q.offset_ns + self.utc_offset_ns,
                "drift_ppm": q.drift_ppm,
                "envelope_rms_ns": q.envelope_rms_ns,
                "points": q.points,
                "outliers": q.outliers,
                "restarts": c.epochs,
                "wraps": dc.get("clock_wraps", 0),
            },
            "driver_counters": dc,
            "error": repr(self.error) if self.error is not None else None,
            "scheduling": self.scheduling,
        }
        c.window_samples = 0
        return doc

    def close(self) -> None:
        for p in self.publishers:
            p.close()
        self._set_alive(False)
