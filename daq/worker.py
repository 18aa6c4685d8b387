"""Device workers: each device's acquisition in a Python process of its own.

Why: a 1 kHz device costs its acquisition thread ~0.25 core here (driver read, clock map,
encode, put; mostly per-sample overhead of a cold Python path), so three devices in one
process hold its GIL ~75 % of the time and each waits for the others: in a 10-minute soak
on a quiet host the device → subscriber p99 was 5.7 ms, 2.5 ms of it between a sample's
latch and its driver stamp, against 1.7 ms for raw zenoh in the same minutes. One process
per device gives each its own GIL.

The daemon (:class:`DeviceWorker`) starts ``python -m daq.worker`` and writes one JSON line
on its stdin: the cell, the publish settings, the device, the daemon's UTC offset, and the
zenoh settings of a *client* session connected to the daemon's own session over a unix
socket the daemon listens on (a client-mode daemon's workers connect to its routers
instead). zenoh routes the worker's data, schema replies and liveliness token through the
daemon's session in Rust, so subscribers see the same keys as from a single process. The
worker runs a :class:`~daq.pipeline.DeviceStream` and a :class:`~daq.health.HealthLoop`
over it, as the daemon does for a device in a thread; a daemon that is a client of
routers then writes a JSON line each health period with what the worker cannot know
(:class:`DaemonReport`: ``messages_unrouted``, ``host_clock``), added to the worker's
health documents. It stops on SIGINT/SIGTERM or when its stdin closes (the daemon is
gone): it flushes, closes the driver, publishes its last health document and prints it
as one JSON line on stdout. The daemon writes a worker's
messages and health documents to the device's :class:`~daq.device_recording.DeviceRecording`
from its own subscription.

Only JSON crosses the pipe; the driver is made from the device's configured name.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import zenoh

from daq.bus import SchemaServer, health_key, open_session
from daq.columnar import StreamSchema, decode, read_header
from daq.config import (
    CellConfig,
    ChannelGroup,
    DaqConfig,
    DeviceConfig,
    PublishConfig,
    ZenohConfig,
)
from daq.device_recording import DeviceRecording
from daq.errors import DaqError
from daq.router_link import RouterLink
from edges.stop_signals import on_stop_signals

if TYPE_CHECKING:
    from daq.health import HealthSource

log = logging.getLogger(__name__)

#: how long the daemon waits for a stopping worker's last messages to reach its recorder
DRAIN_S = 2.0


def worker_zenoh(cfg: ZenohConfig, unix_endpoint: str | None) -> ZenohConfig:
    """The zenoh settings of a worker: a client of the daemon's session (over
    ``unix_endpoint``; the daemon always gives one, a client of routers too, so that it
    records from its own session: docs/deployment.md), else of the daemon's ``connect``."""
    connect = (unix_endpoint,) if unix_endpoint is not None else cfg.connect
    return dataclasses.replace(cfg, mode="client", listen=(), connect=tuple(connect))


def worker_spec(
    cfg: DaqConfig, dev: DeviceConfig, zc: ZenohConfig, utc_offset_ns: int
) -> dict[str, Any]:
    """What a worker needs, as JSON-able data."""
    return {
        "source": cfg.source,
        "cell": dataclasses.asdict(cfg.cell),
        "publish": dataclasses.asdict(cfg.publish),
        "zenoh": dataclasses.asdict(zc),
        "device": dataclasses.asdict(dev),
        "utc_offset_ns": utc_offset_ns,
    }


def config_from_spec(spec: Mapping[str, Any]) -> tuple[DaqConfig, DeviceConfig, int]:
    """The inverse of :func:`worker_spec` (tuples where the dataclasses have them)."""
    d = dict(spec["device"])
    d["channels"] = tuple(
        ChannelGroup(g["name"], tuple(g.get("channels", ()))) for g in d.get("channels", ())
    )
    if d.get("joints") is not None:
        d["joints"] = tuple(d["joints"])
    dev = DeviceConfig(**d)
    z = dict(spec["zenoh"])
    z["listen"], z["connect"] = tuple(z["listen"]), tuple(z["connect"])
    cfg = DaqConfig(
        cell=CellConfig(**spec["cell"]),
        zenoh=ZenohConfig(**z),
        publish=PublishConfig(**spec["publish"]),
        devices=(dev,),
        source=spec["source"],
    )
    return cfg, dev, int(spec["utc_offset_ns"])


# -- the worker process ---------------------------------------------------------------------


class DaemonReport:
    """What the daemon adds to a device's health documents (docs/topics.md): the
    device's messages it recorded while it had no router (``messages_unrouted``; a worker
    cannot see the router: the daemon counts; None: the daemon is not a client of
    routers) and its host's clock against the router's (``host_clock``,
    :mod:`daq.host_clock`; None: not measured). A worker learns them on stdin, after
    its spec, one JSON line at a time; the daemon's own streams take them directly."""

    def __init__(self) -> None:
        self.messages_unrouted: int | None = None
        self.host_clock: dict[str, Any] | None = None

    def read(self, line: str) -> None:
        """One line from the daemon: ``{"messages_unrouted": N, "host_clock": {...}}``
        (either key may be absent)."""
        try:
            doc = json.loads(line)
            if "messages_unrouted" in doc:
                self.messages_unrouted = int(doc["messages_unrouted"])
            if isinstance(doc.get("host_clock"), dict):
                self.host_clock = doc["host_clock"]
        except (ValueError, TypeError, AttributeError):
            log.warning("worker: ignored a line from the daemon: %.80s", line)

    def add_to(self, doc: dict[str, Any]) -> dict[str, Any]:
        if self.messages_unrouted is not None:
            doc["messages_unrouted"] = self.messages_unrouted
        if self.host_clock is not None:
            doc["host_clock"] = self.host_clock
        return doc


class HealthWithReport:
    """A stream's health source with the daemon's report added (:class:`DaemonReport`)."""

    def __init__(self, stream: HealthSource, report: DaemonReport) -> None:
        self._stream = stream
        self.report = report
        self.health_key: str = stream.health_key
        self.recording: DeviceRecording | None = stream.recording

    def health(self, period_s: float) -> dict[str, Any]:
        return self.report.add_to(self._stream.health(period_s))


def _read_parent(stop: threading.Event, report: DaemonReport) -> None:
    try:
        for line in sys.stdin:
            if line.strip():
                report.read(line)
    finally:
        stop.set()


def main() -> int:
    from daq.device_drivers import keep_freed_heap, make_driver
    from daq.health import HealthLoop
    from daq.pipeline import DeviceStream, build_schemas

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    spec = json.loads(sys.stdin.readline())
    cfg, dev, utc_offset = config_from_spec(spec)
    stop = threading.Event()
    on_stop_signals(stop.set)  # not stop.set() in the handler: edges/stop_signals.py
    report = DaemonReport()
    threading.Thread(target=_read_parent, args=(stop, report), name="stdin", daemon=True).start()
    if cfg.publish.gil_switch_s > 0:
        sys.setswitchinterval(min(sys.getswitchinterval(), cfg.publish.gil_switch_s))
    keep_freed_heap()
    session = open_session(cfg.zenoh)
    schemas = SchemaServer(session, f"cell/{cfg.cell.name}")
    driver = make_driver(dev)
    groups = build_schemas(cfg, dev, driver.schema, utc_offset)
    stream = DeviceStream(
        cfg, dev, driver, session, schemas, groups=groups, utc_offset_ns=utc_offset, stop=stop
    )
    health = HealthLoop(session, cfg.publish.health_period_s)
    try:
        health.add(HealthWithReport(stream, report))
        stream.start()
        health.run(stop)
        stream.join(timeout=10.0)
        health.publish()
    finally:
        stream.close()
        health.close()
        schemas.close()
        session.close()
        print(json.dumps({"health": health.last[0] if health.last else {}}), flush=True)
    return 0


# -- the daemon's handle ----------------------------------------------------------------------


class DeviceWorker:
    """One device's worker process, seen from the daemon; records what it publishes.

    ``schemas`` are the device's channel groups (built by the daemon from the driver's
    schema, the same the worker builds); ``recording``: where its messages and health go.
    """

    def __init__(
        self,
        cfg: DaqConfig,
        dev: DeviceConfig,
        schemas: list[StreamSchema],
        session: zenoh.Session,
        zc: ZenohConfig,
        utc_offset_ns: int,
        *,
        recording: DeviceRecording | None = None,
        router_link: RouterLink | None = None,
    ) -> None:
        self.dev = dev
        #: data messages recorded while the daemon had no router (``RouterLink``)
        self.unrouted = 0
        self._router_link = router_link
        self._host_clock: dict[str, Any] | None = None  # the latest sent
        self.schemas = schemas
        self.recording = recording
        self.recorded = 0  # data messages written to the recorder
        self.restarts = 0  # times the worker ended by itself and was started again
        self.last_health: dict[str, Any] | None = None
        self._subs: list[Any] = []
        self._spec = json.dumps(worker_spec(cfg, dev, zc, utc_offset_ns))
        self.proc: subprocess.Popen[str] | None = None
        self._lock = threading.Lock()
        hk = health_key(cfg.cell.name, dev.robot, dev.name)
        self._subs.append(session.declare_subscriber(hk, self._on_health))
        if recording is not None:
            for gi, s in enumerate(schemas):
                self._subs.append(
                    session.declare_subscriber(
                        s.key, zenoh.handlers.Callback(self._recorder_of(recording, gi, s))
                    )
                )

    @property
    def keys(self) -> list[str]:
        return [s.key for s in self.schemas]

    def _recorder_of(
        self, recording: DeviceRecording, group: int, s: StreamSchema
    ) -> Callable[[zenoh.Sample], None]:
        def on_data(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            t = time.time_ns()
            try:
                seq = read_header(payload).batch_seq
                recording.write(group, (payload,), t, seq, lambda: decode(s, payload)[1])
            except DaqError as exc:
                log.warning("%s: not recorded: %s", s.key, exc)
            link = self._router_link
            with self._lock:
                self.recorded += 1
                if link is not None and not link.up:
                    self.unrouted += 1

        return on_data

    def _on_health(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        try:
            doc = json.loads(data)
        except ValueError:
            return
        self.last_health = doc
        if self.recording is not None:
            self.recording.write_health(data)

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "daq.worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        assert self.proc.stdin is not None
        self.proc.stdin.write(self._spec + "\n")
        self.proc.stdin.flush()

    def check(self) -> bool:
        """Start the worker again if it ended by itself (logged); True if it had."""
        if self.proc is None or self.proc.poll() is None:
            return False
        code = self.proc.returncode
        self.stop()
        self.proc.communicate()
        self.restarts += 1
        log.error("%s: worker exited with code %s; starting it again", self.dev.name, code)
        self.start()
        return True

    def send_report(self, host_clock: dict[str, Any] | None = None) -> None:
        """Tell the worker the daemon's report of its device (:class:`DaemonReport`), for
        its next health document; nothing when the daemon has no router to report on."""
        stdin = self.proc.stdin if self.proc is not None else None
        if self._router_link is None or stdin is None:  # (stop() may clear it meanwhile)
            return
        if host_clock is not None:
            self._host_clock = host_clock
        with self._lock:
            doc: dict[str, Any] = {"messages_unrouted": self.unrouted}
        if self._host_clock is not None:
            doc["host_clock"] = self._host_clock
        line = json.dumps(doc)
        with contextlib.suppress(OSError, ValueError):  # a worker that ended: check() sees it
            stdin.write(line + "\n")
            stdin.flush()

    def stop(self) -> None:
        """Ask the worker to stop (its stdin closes, after the daemon's last counts)."""
        if self.proc is not None and self.proc.stdin is not None:
            self.send_report()
            stdin, self.proc.stdin = self.proc.stdin, None  # communicate() must not touch it
            with contextlib.suppress(OSError):
                stdin.close()

    def join(self, timeout: float = 10.0) -> dict[str, Any] | None:
        """Wait for the worker; its last health document (None if it left none)."""
        if self.proc is None:
            return self.last_health
        self.stop()
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            log.error("%s: worker did not stop within %.0f s; killed", self.dev.name, timeout)
            self.proc.kill()
            out, _ = self.proc.communicate()
        if self.proc.returncode != 0:
            log.error("%s: worker exited with code %s", self.dev.name, self.proc.returncode)
        self.proc = None
        for line in reversed((out or "").strip().splitlines()):
            try:
                doc = json.loads(line).get("health")
            except (ValueError, AttributeError):
                continue
            if doc:
                self.last_health = doc
                self._drain(int(doc.get("batches", 0)))
            break
        return self.last_health

    def _drain(self, published: int) -> None:
        # the worker's last messages may still be on their way to the recorder
        if self.recording is None:
            return
        t_end = time.monotonic() + DRAIN_S
        while self.recorded < published and time.monotonic() < t_end:
            time.sleep(0.01)

    def close(self) -> None:
        self.join()
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:  # session already closed
                log.debug("worker subscriber undeclare failed", exc_info=True)
        self._subs = []


if __name__ == "__main__":
    sys.exit(main())
