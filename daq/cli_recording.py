"""The recording commands of ``daq`` (:mod:`daq.cli` parses their options):
``daq record`` (zenoh keys -> MCAP), ``daq recover`` and ``daq info`` (where and why a
file is damaged).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Mapping
from typing import Any

from daq.columnar import ENCODING_NAME, StreamSchema, decode, read_header
from daq.errors import DaqError
from daq.recording_holes import (
    HOLES_SCHEMA,
    HOLES_SCHEMA_NAME,
    HOLES_TOPIC,
    KIND_HOLES,
    Hole,
    HoleFinder,
)
from daq.recording_reader import read_recording, scan
from daq.recording_recover import recover
from daq.recording_writer import (
    HEALTH_SCHEMA,
    HEALTH_SCHEMA_NAME,
    KIND_HEALTH,
    BackgroundRecorder,
    McapRecorder,
    check_stream_output,
)
from edges.stop_signals import on_stop_signals

#: the logger keeps the name of the module this code came from (daq.recording), so a
#: logging configuration that names it still applies
log = logging.getLogger("daq.recording")

#: what ``daq record`` logs when its session (a client of routers) loses its router
RECORDER_LOST = "no router: nothing arrives; the messages missed are recorded as holes"
RECORDER_BACK = "router reached again: recording resumes"


def main_recover(args: Any) -> int:
    result = recover(args.file, args.output, in_place=getattr(args, "in_place", False))
    print(json.dumps(result.as_dict(args.file)), flush=True)
    return 0


def main_info(args: Any) -> int:
    rec, counts = scan(args.file)
    doc = {
        "file": str(args.file),
        "bytes": rec.size,
        "complete": rec.complete,
        "truncated": rec.truncated,
        "error": rec.error,
        "messages": rec.messages,
        "chunks": rec.chunks,
        "chunks_damaged": rec.chunks_damaged,
        "orphans": rec.orphans,
        "damaged": [d.as_dict() for d in rec.damaged],
        "metadata": rec.metadata,
        "channels": [
            {
                "topic": ch.topic,
                "message_encoding": ch.message_encoding,
                "schema": rec.schemas[ch.schema_id].name if ch.schema_id in rec.schemas else "",
                "messages": counts.get(ch.topic, 0),
                "metadata": dict(ch.metadata),
            }
            for ch in rec.channels.values()
        ],
    }
    if counts.get(HOLES_TOPIC):  # a subscriber's recording: what it lacks, and why
        doc["holes"] = [
            json.loads(m.data) for m in read_recording(args.file).messages_iter({HOLES_TOPIC})
        ]
    print(json.dumps(doc, indent=1), flush=True)
    return 0 if rec.complete else 1


def main_record(args: Any, zc: Any) -> int:
    """``daq record``: subscribe to a key expression and write every sample to MCAP."""

    import zenoh

    from daq.bus import fetch_schemas, open_session, require_peer

    # the file is written as samples come (a crash keeps what was closed): checked up
    # front, not staged
    config_path = getattr(args, "config", None) or os.environ.get("DAQ_CONFIG")
    check_stream_output(args.output, "-o/--output", [config_path])
    stop = threading.Event()
    on_stop_signals(stop.set)  # not stop.set() in the handler: edges/stop_signals.py
    session = open_session(zc)
    try:
        require_peer(session, zc)  # nobody there: said within seconds, no file written
        rec = BackgroundRecorder(McapRecorder(args.output))
    except BaseException:
        session.close()
        raise
    # schemas first, then the subscriber (a schema get on a young subscription coincided
    # with lost messages: daq.bus.Receiver)
    known = fetch_schemas(session, args.key)
    rate = float(getattr(args, "viewer_rate_hz", 30.0))
    link, holes = _hole_finder(session, zc)
    channels = _SubscribedChannels(rec, session, known, rate, holes)
    sub = session.declare_subscriber(args.key, zenoh.handlers.FifoChannel(65536))
    print(json.dumps({"recording": str(rec.path), "key": args.key}), flush=True)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    try:
        while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
            sample = sub.try_recv()
            if sample is None:
                channels.write_holes(holes.due(time.time_ns()))
                time.sleep(0.0005)
                continue
            channels.write(sample)
    finally:
        sub.undeclare()
        channels.flush()
        channels.write_holes(holes.drain())
        rec.close()
        if link is not None:
            link.close()
        session.close()
    said = {"recorded": str(rec.path), "holes": holes.holes}
    print(json.dumps({**said, "messages_missing": holes.messages_missing}), flush=True)
    return 0


def _hole_finder(session: Any, zc: Any) -> tuple[Any, HoleFinder]:
    """The hole finder of ``daq record`` and, for a client of routers, the watch of its
    router (a hole's reason may be this session's lost router; None: a peer)."""
    if zc.mode != "client":
        return None, HoleFinder()
    from daq.router_link import RouterLink

    link = RouterLink(session, said=(RECORDER_LOST, RECORDER_BACK))
    return link, HoleFinder(lambda: link.changes)


class _SubscribedChannels:
    """The channels ``daq record`` writes: one per key, made at the key's first sample
    (a columnar key with its schema, fetched if it was not ``known``, and its viewer
    channels at ``rate_hz``; a JSON key as health), or none (a key it cannot record)."""

    def __init__(
        self,
        rec: BackgroundRecorder,
        session: Any,
        known: Mapping[str, StreamSchema],
        rate_hz: float,
        holes: HoleFinder,
    ) -> None:
        self.rec = rec
        self.holes = holes
        self._holes_channel: int | None = None
        self.columnar: set[str] = set()  # the data keys recorded (their batch_seq watched)
        self.session = session
        self.known = known
        self.rate_hz = rate_hz
        self.ids: dict[str, int] = {}  # -1: not recorded
        # viewer channels (daq.foxglove_channels) of the columnar keys, at their bounded rate
        self.viewers: dict[str, tuple[Any, StreamSchema]] = {}

    def write(self, sample: Any) -> None:
        """Record one zenoh sample, at the time it is written (host UTC ns)."""
        key = str(sample.key_expr)
        now = time.time_ns()
        cid = self.ids.get(key)
        if cid is None:
            cid = self.ids[key] = self._open(key, str(sample.encoding))
        if cid < 0:
            return
        payload = sample.payload.to_bytes()
        self.rec.write(cid, payload, now, now)
        self._watch(key, payload, now)
        view = self.viewers.get(key)
        if view is not None and view[0].due(now):
            try:
                view[0].add(decode(view[1], payload)[1], now)
            except DaqError as exc:  # a payload of another schema: the data is kept
                log.warning("%s: no viewer message: %s", key, exc)

    def _watch(self, key: str, payload: bytes, now: int) -> None:
        """Hand a message to the hole finder: a data batch's ``batch_seq``, a health
        document's counters."""
        if key in self.columnar:
            with contextlib.suppress(DaqError):  # not a batch: recorded, not watched
                self.holes.on_batch(key, read_header(payload).batch_seq, now)
            self.write_holes(self.holes.due(now))
        elif key.endswith("/health"):
            with contextlib.suppress(ValueError):
                self.holes.on_health(key, json.loads(payload), now)

    def write_holes(self, holes: list[Hole]) -> None:
        """Each hole as a record of the holes channel (made at the first), and a line."""
        for h in holes:
            if self._holes_channel is None:
                self._holes_channel = self.rec.add_json(
                    HOLES_TOPIC, HOLES_SCHEMA_NAME, HOLES_SCHEMA, {"daq.kind": KIND_HOLES}
                )
            self.rec.write(self._holes_channel, h.to_json(), h.t_after_ns, h.t_after_ns)
            log.warning(
                "%s: hole of %d messages (batch_seq %d..%d, %.3f s): %s",
                h.key, h.count, h.first_missing, h.last_missing, h.duration_s, h.reason,
            )  # fmt: skip

    def _open(self, key: str, encoding: str) -> int:
        """The channel id of ``key`` (-1: not recorded)."""
        from daq.bus import fetch_schema
        from daq.foxglove_channels import StreamViewer

        if encoding.endswith(ENCODING_NAME):
            try:
                schema = self.known.get(key) or fetch_schema(self.session, key)
                cid = self.rec.add_columnar(schema)
                viewer = StreamViewer(self.rec, schema, rate_hz=self.rate_hz)
                if viewer.active:
                    self.viewers[key] = (viewer, schema)
            except Exception as exc:
                log.warning("no schema for %s, not recorded: %s", key, exc)
                return -1
            self.columnar.add(key)
            return cid
        if encoding.startswith("application/json"):
            return self.rec.add_json(
                key, HEALTH_SCHEMA_NAME, HEALTH_SCHEMA, {"daq.kind": KIND_HEALTH}
            )
        return -1

    def flush(self) -> None:
        """The last points into the viewer channels."""
        for viewer, _ in self.viewers.values():
            viewer.flush(time.time_ns())
