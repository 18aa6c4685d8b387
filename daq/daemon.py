"""``daq run``: the acquisition daemon.

Opens one zenoh session, an optional MCAP recorder, and one
:class:`~daq.pipeline.DeviceStream` per enabled device: in a worker process of its own
(:mod:`daq.worker`) when there is more than one device (``[publish] process_per_device``),
else in a thread. Either way the device's recorder channels are one
:class:`~daq.device_recording.DeviceRecording`, and its health is published once a period
by a :class:`~daq.health.HealthLoop` (the daemon's for a thread, the worker's own for a
worker). It stops on SIGINT/SIGTERM or after ``--duration``: device streams flush what
they hold and close their drivers, the recorder drains and writes the summary, and it
exits 0.

On start it prints one JSON line to stdout: ``{"daq": "running", "cell": ..., "keys":
[...], "listen": [...], "recording": PATH or null}``; on exit one ``{"daq": "stopped",
...}`` line with the final counters.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from daq.bus import Received, Receiver, SchemaServer, open_session, utc_offset_ns
from daq.config import DaqConfig, DeviceConfig, ZenohConfig, resolve, zenoh_overrides
from daq.device_drivers import DriverFactory, keep_freed_heap, make_driver
from daq.device_recording import DeviceRecording, recorder_meta
from daq.errors import ConfigError, DaqError
from daq.foxglove_channels import StreamViewer
from daq.health import HealthLoop
from daq.host_clock import HostClockWatch
from daq.pipeline import DeviceStream, build_schemas
from daq.recording_writer import (
    KIND_HEALTH,
    TWIN_HEALTH_SCHEMA,
    TWIN_HEALTH_SCHEMA_NAME,
    BackgroundRecorder,
    McapRecorder,
)
from daq.router_link import RouterLink
from daq.scheduling import set_realtime_of
from daq.worker import DaemonReport, DeviceWorker, HealthWithReport, worker_zenoh
from edges.stop_signals import on_stop_signals

if TYPE_CHECKING:  # the emulated cell loads only for a daemon that runs one
    from daq.emulated import EmulatedCell

log = logging.getLogger(__name__)

#: a device's counters in the stop summary (from its last health document)
SUMMARY_KEYS = ("samples", "gaps", "samples_missing", "reconnects", "messages_unmatched")

#: zenoh settings that make a peer's first connect behave as a client's: try the
#: endpoints once at open and fail if none answers (a peer would retry in the background)
FAIL_IF_NO_ROUTER: dict[str, Any] = {
    "connect/timeout_ms": 0,
    "connect/exit_on_failure": True,
}


def recording_path(cfg: DaqConfig, path: str | None = None) -> Path:
    start = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    template = path or cfg.recording.path
    return Path(template.format(cell=cfg.cell.name, start=start))


class Daemon:
    """The running daemon; ``run()`` blocks until ``stop`` is set or ``duration_s`` passed."""

    def __init__(
        self,
        cfg: DaqConfig,
        *,
        record_path: str | Path | None = None,
        driver_factory: DriverFactory = make_driver,
    ) -> None:
        self.cfg = cfg
        self.stop = threading.Event()
        # device threads wait for the GIL up to the switch interval (5 ms by default):
        # a shorter one bounds the latency a busy thread adds to another device's samples
        interval = cfg.publish.gil_switch_s
        if interval > 0:
            sys.setswitchinterval(min(sys.getswitchinterval(), interval))
        keep_freed_heap()
        self.utc_offset_ns = utc_offset_ns()
        self._worker_dir: str | None = None
        with contextlib.ExitStack() as undo:  # what is made so far, should the next fail
            zc, worker_zc = self._zenoh_with_workers(driver_factory)
            undo.callback(self._remove_worker_dir)
            self.session = open_session(zc)
            undo.callback(self.session.close)
            self.schemas = SchemaServer(self.session, f"cell/{cfg.cell.name}")
            self.router_link, self.clock_watch = self._watch_router(undo)
            undo.pop_all()
        self.report = DaemonReport()  # added to the health of the devices in threads
        self.recorder: BackgroundRecorder | None = None
        # every enabled device, in a thread or a worker process (the same calls either way)
        self.devices: list[DeviceStream | DeviceWorker] = []
        self.workers: list[DeviceWorker] = []  # those in worker processes
        self.recordings: list[DeviceRecording] = []
        self.health = HealthLoop(self.session, cfg.publish.health_period_s)
        self._twin_rx: Any = None
        self._twin_channels: dict[str, tuple[int, StreamViewer | None]] = {}
        self._closed = False
        try:
            if record_path is not None:
                self.recorder = self._open_recorder(record_path)
            for dev in cfg.devices:
                if dev.enabled:
                    # a worker's driver: made for its schema, not opened
                    self._add_device(dev, driver_factory(dev), worker_zc)
            if self.recorder is not None and cfg.recording.twin:
                # the live twin's keys too, when a twin publishes (its schemas by query)
                self._twin_rx = Receiver(
                    self.session,
                    f"twin/{cfg.cell.name}/**",
                    on_batch=self._record_twin,
                    on_other=self._record_twin_json,
                )
        except BaseException:
            self.close()
            raise

    def _watch_router(
        self, undo: contextlib.ExitStack
    ) -> tuple[RouterLink | None, HostClockWatch | None]:
        """For a client of routers: what it records while none is reachable is counted
        (``RouterLink``) and its clock is measured against the router's
        (:mod:`daq.host_clock`), each closed by ``undo`` should the start fail; a peer:
        neither."""
        if self.cfg.zenoh.mode != "client":
            return None, None
        link = RouterLink(self.session)
        undo.callback(link.close)
        clock = HostClockWatch(self.session, self.host_now_ns, self.cfg.publish.clock_tolerance_s)
        undo.callback(clock.close)
        return link, clock

    def _zenoh_with_workers(
        self, driver_factory: DriverFactory
    ) -> tuple[ZenohConfig, ZenohConfig | None]:
        """The daemon's zenoh settings and, when devices run in worker processes, the
        workers' (None: threads); a daemon that listens gets a unix socket for them in a
        directory of its own (``_worker_dir``, removed at close). Workers need a driver
        made from its configured name: a test's factory of in-process fakes runs in
        threads."""
        cfg = self.cfg
        zc = cfg.zenoh
        per_device = cfg.publish.process_per_device
        if per_device == "auto":
            per_device = sum(1 for d in cfg.devices if d.enabled) > 1
        if not (per_device and driver_factory is make_driver):
            return zc, None
        # workers connect to this session over a unix socket, also when the daemon is a
        # client of routers: it records from its own subscription, which must not pass
        # through a router that may be restarting or out of reach. A client cannot
        # listen, so the daemon's session is then a peer connected to those routers
        # (they route for it as for a client; it reconnects as a client does)
        self._worker_dir = tempfile.mkdtemp(prefix="daq-")
        unix = f"unixsock-stream/{self._worker_dir}/workers.sock"
        if zc.mode == "client":
            zc = replace(zc, mode="peer", extra={**FAIL_IF_NO_ROUTER, **zc.extra})
        zc = replace(zc, listen=(*zc.listen, unix))
        return zc, worker_zenoh(cfg.zenoh, unix)

    def _open_recorder(self, record_path: str | Path) -> BackgroundRecorder:
        """The MCAP recorder of ``record_path``, its metadata the daemon's run."""
        cfg = self.cfg
        meta = {
            "daq": {
                "cell": cfg.cell.name,
                "config": cfg.source,
                "host_utc_minus_monotonic_ns": str(self.utc_offset_ns),
                "started_utc": datetime.now(UTC).isoformat(),
            }
        }
        return BackgroundRecorder(
            McapRecorder(
                record_path,
                compression=cfg.recording.compression,
                chunk_size_bytes=cfg.recording.chunk_size_bytes,
                chunk_interval_s=cfg.recording.chunk_interval_s,
                metadata=meta,
            )
        )

    def _add_device(self, dev: DeviceConfig, driver: Any, worker_zc: ZenohConfig | None) -> None:
        """``dev``'s stream, its recorder channels and its health: in a worker process
        with ``worker_zc``, else in a thread of this process."""
        cfg = self.cfg
        groups = build_schemas(cfg, dev, driver.schema, self.utc_offset_ns)
        recording = None
        if self.recorder is not None:
            recording = DeviceRecording(self.recorder, cfg, dev, [g for g, _ in groups])
            self.recordings.append(recording)
        if worker_zc is not None:
            worker = DeviceWorker(
                cfg,
                dev,
                [g for g, _ in groups],
                self.session,
                worker_zc,
                self.utc_offset_ns,
                recording=recording,
                router_link=self.router_link,
            )
            self.devices.append(worker)
            self.workers.append(worker)
            return
        stream = DeviceStream(
            cfg,
            dev,
            driver,
            self.session,
            self.schemas,
            groups=groups,
            recording=recording,
            utc_offset_ns=self.utc_offset_ns,
            stop=self.stop,
        )
        self.devices.append(stream)
        self.health.add(HealthWithReport(stream, self.report))

    def _record_twin(self, got: Received) -> None:
        """A batch of a twin key (zenoh's callback thread): recorded as it came, and its
        viewer channels at their bounded rate."""
        assert self.recorder is not None
        t = time.time_ns()
        entry = self._twin_channels.get(got.key)
        if entry is None:
            cid = self.recorder.add_columnar(got.schema, recorder_meta(got.schema))
            made = StreamViewer(
                self.recorder, got.schema, rate_hz=self.cfg.recording.viewer_rate_hz
            )
            entry = self._twin_channels[got.key] = (cid, made if made.active else None)
        cid, viewer = entry
        self.recorder.write(cid, got.payload, t, t, got.header.batch_seq)
        if viewer is not None and viewer.due(t):
            viewer.add(got.columns, t)

    def _record_twin_json(self, sample: Any) -> None:
        assert self.recorder is not None
        key = str(sample.key_expr)
        entry = self._twin_channels.get(key)
        if entry is None:
            cid = self.recorder.add_json(
                key, TWIN_HEALTH_SCHEMA_NAME, TWIN_HEALTH_SCHEMA, {"daq.kind": KIND_HEALTH}
            )
            entry = self._twin_channels[key] = (cid, None)
        t = time.time_ns()
        self.recorder.write(entry[0], sample.payload.to_bytes(), t, t)

    @property
    def keys(self) -> list[str]:
        return [k for d in self.devices for k in d.keys]

    def _restart_ended_workers(self) -> None:
        clock = self.clock_watch.doc() if self.clock_watch is not None else None
        self.report.host_clock = clock
        for w in self.workers:
            w.check()
            w.send_report(clock)  # into its next health document

    def host_now_ns(self) -> int:
        """This host's UTC ns as the samples are stamped (monotonic + the start's offset)."""
        return time.monotonic_ns() + self.utc_offset_ns

    def run(self, duration_s: float | None = None) -> list[dict[str, Any]]:
        """Acquire until stopped; returns the last health documents."""
        for d in self.devices:
            d.start()
        self.health.run(self.stop, duration_s, on_round=self._restart_ended_workers)
        self.stop.set()
        for d in self.devices:
            d.stop()
        for d in self.devices:
            d.join(timeout=10.0)
        # a worker published its last document itself and printed it (its handle read it)
        last = [w.last_health for w in self.workers if w.last_health]
        return self.health.publish() + last

    def close(self) -> None:
        """Stop threads, close drivers, flush the recording, close zenoh; safe twice."""
        if self._closed:
            return
        self._closed = True
        self.stop.set()
        for d in self.devices:
            d.stop()
        for d in self.devices:
            d.join(timeout=10.0)
            d.close()
        self.health.close()
        for r in self.recordings:  # the last points into the viewer channels
            r.flush()
        if self._twin_rx is not None:
            self._twin_rx.close()
        if self.recorder is not None:
            self.recorder.close()
        self.schemas.close()
        if self.router_link is not None:
            self.router_link.close()
        if self.clock_watch is not None:
            self.clock_watch.close()
        self.session.close()
        self._remove_worker_dir()

    def _remove_worker_dir(self) -> None:
        if self._worker_dir is not None:
            shutil.rmtree(self._worker_dir, ignore_errors=True)
            self._worker_dir = None

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main_run(args: argparse.Namespace) -> int:
    """``daq run``: the daemon of ``args`` until ``--duration`` or a signal; exit 0."""
    cfg, emulated, record = _run_config(args)
    stopping = threading.Event()
    if emulated is None:  # a configured cell: its devices there before anything opens
        from daq.device_presence import check_devices_present

        check_devices_present(cfg, make_driver)
    try:
        path = recording_path(cfg, args.record or None) if record else None
        # before any session or worker exists: their threads and processes inherit it
        set_realtime_of(cfg)
        daemon = Daemon(cfg, record_path=path)
    except BaseException:
        if emulated is not None:
            emulated.close()
        raise

    def on_signal() -> None:  # in a thread, not the handler: edges/stop_signals.py
        stopping.set()
        daemon.stop.set()

    on_stop_signals(on_signal)
    try:
        print(json.dumps(_running_line(cfg, daemon, path, emulated)), flush=True)
        docs = daemon.run(args.duration)
        unrouted = {w.dev.name: w.unrouted for w in daemon.workers}
        clock = daemon.clock_watch.doc() if daemon.clock_watch is not None else None
    finally:
        daemon.close()
        if emulated is not None:
            emulated.close()
    summary = {
        "daq": "stopped",
        "signal": stopping.is_set(),
        "recording": str(path) if path is not None else None,
        "devices": {
            d["device"]: {
                **{k: d.get(k, 0) for k in SUMMARY_KEYS},
                "messages_unrouted": unrouted.get(d["device"], 0),
            }
            for d in docs
        },
        "host_clock": clock,
    }
    print(json.dumps(summary), flush=True)
    if path is not None:
        print(f"recorded to {path}", file=sys.stderr)
    return 0


#: the emulated cell's tracker/encoder rate without ``--rate`` (Hz)
DEFAULT_EMULATED_RATE_HZ = 1000.0
#: ``daq run`` options that only apply to the emulated cell (no ``--config``), and where
#: a configured cell states the same thing instead
EMULATED_ONLY = {
    "rate": ("--rate", "rate_hz in each [[device]] table"),
    "sim_config": ("--sim-config", "the devices in its [[device]] tables"),
    "no_record": ("--no-record", "[recording] enabled = false"),
}


def check_run_options(args: argparse.Namespace) -> None:
    """Refuse an option that does not apply beside ``--config`` (or ``$DAQ_CONFIG``)
    instead of ignoring it, and ``--record`` with ``--no-record``."""
    if args.record is not None and args.no_record:
        raise ConfigError("--no-record: contradicts --record")
    if args.config is None and not _env_config():
        return
    given = "--config" if args.config is not None else "$DAQ_CONFIG"
    for attr, (option, instead) in EMULATED_ONLY.items():
        if getattr(args, attr, None) not in (None, False):
            raise ConfigError(
                f"{option}: applies to the emulated cell only (no {given}); a configured "
                f"cell states {instead}"
            )


def _run_config(args: Any) -> tuple[DaqConfig, EmulatedCell | None, bool]:
    """The daemon's configuration, the emulated cell it reads (started; None: a
    configured cell, ``--config`` or ``$DAQ_CONFIG``) and whether it records."""
    extra: dict[str, dict[str, Any]] = {}
    if getattr(args, "cell", None):
        extra["cell"] = {"name": args.cell}
    if args.config is None and not _env_config():
        from daq.config import load
        from daq.emulated import EmulatedCell

        rate = DEFAULT_EMULATED_RATE_HZ if args.rate is None else args.rate
        emulated = EmulatedCell(sim_config=args.sim_config, rate_hz=rate)
        base = emulated.start()
        try:
            cfg = load(None, overrides=_with_zenoh(args, extra), base=base)
        except BaseException:
            emulated.close()  # the emulator's processes must not outlive a refused option
            raise
        return cfg, emulated, not args.no_record
    cfg = resolve(args, extra)
    return cfg, None, cfg.recording.enabled or args.record is not None


def _running_line(
    cfg: DaqConfig, daemon: Daemon, path: Path | None, emulated: EmulatedCell | None
) -> dict[str, Any]:
    """The ``{"daq": "running", ...}`` line printed on start."""
    return {
        "daq": "running",
        "cell": cfg.cell.name,
        "keys": daemon.keys,
        "listen": list(cfg.zenoh.listen),
        "connect": list(cfg.zenoh.connect),
        "recording": str(path) if path is not None else None,
        "emulated": emulated.devices if emulated is not None else None,
        "emulator_t0_monotonic_ns": (emulated.t0_monotonic_ns if emulated is not None else None),
    }


def _env_config() -> bool:
    import os

    return bool(os.environ.get("DAQ_CONFIG"))


def _with_zenoh(args: Any, extra: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    out = dict(extra)
    z = zenoh_overrides(args)
    if z:
        out["zenoh"] = z
    return out


__all__ = ["Daemon", "DaqError", "main_run", "make_driver"]
