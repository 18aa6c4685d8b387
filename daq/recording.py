"""MCAP recording: a crash-tolerant writer, a streaming reader, ``recover``, ``info``, and
the ``daq record`` zenoh sink.

Writer: chunked and compressed (zstd by default); a chunk is closed when it reaches
``chunk_size_bytes`` *or* ``chunk_interval_s`` after its first message, and written to the
OS at once, so a crash or ``kill -9`` loses at most the chunk in progress. The summary
(indexes, statistics) is written only by :meth:`McapRecorder.close`: a killed recording
has none, and a reader that seeks to the summary fails on it. This module's reader
therefore *streams* (:func:`read_recording`), stops cleanly at the first incomplete record
and says so; ``daq recover`` rewrites such a file whole, with a summary.

Channels (docs/daq.md): one per zenoh data key (topic = the key, message encoding
``daq.columnar.v1``, the key's JSON schema as schema, metadata: device, driver, url…),
one per health key (JSON), and derived viewer channels in Foxglove's JSON schemas
(metadata ``daq.kind = foxglove``; not republished by replay unless asked).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from daq.columnar import ENCODING_NAME, SCHEMA_ENCODING, StreamSchema
from daq.errors import RecordingError
from daq.scheduling import normal_for_this_thread

log = logging.getLogger(__name__)

PROFILE = ""  # no ROS profile
LIBRARY = "grating-twin daq"
COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
KIND_DATA = "data"
KIND_HEALTH = "health"
KIND_FOXGLOVE = "foxglove"
HEALTH_SCHEMA_NAME = "daq.health.v1"
HEALTH_SCHEMA = {
    "title": HEALTH_SCHEMA_NAME,
    "description": "Per-device health, once a second (docs/topics.md)",
    "type": "object",
    "properties": {
        "t_host_ns": {"type": "integer"},
        "device": {"type": "string"},
        "state": {"type": "string"},
        "alive": {"type": "boolean"},
        "rate_hz": {"type": "number"},
        "counters": {"type": "object"},
        "clock": {"type": "object"},
    },
}


class McapRecorder:
    """Writes channels and messages to one MCAP file (not thread-safe; see
    :class:`BackgroundRecorder`). ``close()`` writes the summary; safe to call twice."""

    def __init__(
        self,
        path: str | Path,
        *,
        compression: str = "zstd",
        chunk_size_bytes: int = 1 << 20,
        chunk_interval_s: float = 1.0,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
    ) -> None:
        self.path = Path(path)
        if compression not in COMPRESSION:
            raise RecordingError(f"compression must be one of {', '.join(COMPRESSION)}")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise RecordingError(f"cannot create {self.path}: {exc}") from exc
        self._writer = Writer(
            self._file, chunk_size=chunk_size_bytes, compression=COMPRESSION[compression]
        )
        self._writer.start(profile=PROFILE, library=LIBRARY)
        for name, data in (metadata or {}).items():
            self._writer.add_metadata(name, {k: str(v) for k, v in data.items()})
        self._file.flush()
        self.chunk_interval_ns = int(chunk_interval_s * 1e9)
        self._chunk_open_ns: int | None = None
        self._closed = False
        self.topics: dict[str, int] = {}
        self.messages = 0
        self.bytes = 0

    # -- channels -------------------------------------------------------------------------
    def add_channel(
        self,
        topic: str,
        *,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
        message_encoding: str,
        metadata: Mapping[str, str] | None = None,
    ) -> int:
        if topic in self.topics:
            return self.topics[topic]
        sid = self._writer.register_schema(schema_name, schema_encoding, schema_data)
        cid = self._writer.register_channel(
            topic, message_encoding, sid, {k: str(v) for k, v in (metadata or {}).items()}
        )
        self.topics[topic] = cid
        return cid

    def add_columnar(self, schema: StreamSchema, metadata: Mapping[str, str] | None = None) -> int:
        meta = {"daq.kind": KIND_DATA, "zenoh.key": schema.key, "schema_id": str(schema.schema_id)}
        meta.update(metadata or {})
        return self.add_channel(
            schema.key,
            schema_name=ENCODING_NAME,
            schema_encoding=SCHEMA_ENCODING,
            schema_data=schema.dumps(),
            message_encoding=ENCODING_NAME,
            metadata=meta,
        )

    def add_json(
        self,
        topic: str,
        schema_name: str,
        json_schema: Mapping[str, Any] | bytes,
        metadata: Mapping[str, str] | None = None,
    ) -> int:
        data = json_schema if isinstance(json_schema, bytes) else json.dumps(json_schema).encode()
        return self.add_channel(
            topic,
            schema_name=schema_name,
            schema_encoding="jsonschema",
            schema_data=data,
            message_encoding="json",
            metadata=metadata,
        )

    # -- messages --------------------------------------------------------------------------
    def write(
        self,
        channel_id: int,
        data: bytes,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        sequence: int = 0,
    ) -> None:
        if self._closed:
            raise RecordingError(f"{self.path} is closed")
        self._writer.add_message(
            channel_id,
            log_time=int(log_time_ns),
            data=data,
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            sequence=int(sequence) & 0xFFFFFFFF,
        )
        self.messages += 1
        self.bytes += len(data)
        now = time.monotonic_ns()
        if self._chunk_open_ns is None:
            self._chunk_open_ns = now
        self.tick(now)

    def tick(self, now_ns: int | None = None) -> None:
        """Close the chunk in progress if it is older than ``chunk_interval_s``."""
        if self._chunk_open_ns is None or self._closed:
            return
        now = time.monotonic_ns() if now_ns is None else now_ns
        if now - self._chunk_open_ns >= self.chunk_interval_ns:
            self.flush()

    def flush(self) -> None:
        """Finish the chunk in progress and hand everything to the OS."""
        if self._closed:
            return
        self._writer.flush()  # finalizes the chunk and flushes the file object
        self._chunk_open_ns = None

    def close(self) -> None:
        if self._closed:
            return
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._closed = True
            self._file.close()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: how often the background writer drains its queue (s)
DRAIN_PERIOD_S = 0.02


class BackgroundRecorder:
    """A :class:`McapRecorder` fed through a queue by any thread, written by one thread.

    Channel registration is synchronous (returns the id); messages are queued, so a slow
    disk or a chunk being compressed never stalls an acquisition thread.
    """

    def __init__(self, recorder: McapRecorder) -> None:
        self.recorder = recorder
        self._q: queue.SimpleQueue[tuple[int, bytes, int, int, int] | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._closed = False
        self.max_backlog = 0
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()

    @property
    def path(self) -> Path:
        return self.recorder.path

    def add_columnar(self, schema: StreamSchema, metadata: Mapping[str, str] | None = None) -> int:
        with self._lock:
            return self.recorder.add_columnar(schema, metadata)

    def add_json(self, *args: Any, **kw: Any) -> int:
        with self._lock:
            return self.recorder.add_json(*args, **kw)

    def write(
        self, channel_id: int, data: bytes, log_time_ns: int, publish_time_ns: int, seq: int = 0
    ) -> None:
        if not self._closed:
            self._q.put((channel_id, data, log_time_ns, publish_time_ns, seq))

    def _run(self) -> None:
        # wake once per DRAIN_PERIOD_S and write everything queued, not once per message
        # (3 000 wake-ups a second on the full cell, each taking the interpreter from the
        # acquisition threads; A/B: daemon CPU 0.68-0.79 vs 0.79-0.88 core, latency within
        # the run-to-run noise)
        normal_for_this_thread()  # a chunk's compression must not hold a real-time core
        while True:
            try:
                item = self._q.get(timeout=0.1)
            except queue.Empty:
                with self._lock:
                    self.recorder.tick()
                continue
            items = [item]
            while items[-1] is not None:
                try:
                    items.append(self._q.get_nowait())
                except queue.Empty:
                    break
            self.max_backlog = max(self.max_backlog, len(items) - 1)
            with self._lock:
                for it in items:
                    if it is None:
                        return
                    try:
                        self.recorder.write(*it)
                    except Exception:
                        log.exception("recording to %s failed", self.recorder.path)
            time.sleep(DRAIN_PERIOD_S)

    def close(self) -> None:
        """Drain the queue, write the summary; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._q.put(None)
        self._thread.join()
        with self._lock:
            self.recorder.close()


# -- streaming reader ----------------------------------------------------------------------


@dataclass
class RecordedMessage:
    topic: str
    channel: Channel
    schema: Schema | None
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


@dataclass
class Recording:
    """What a streaming pass found: channels, schemas, metadata, and how it ended."""

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False  # the footer was reached
    truncated: bool = False  # stopped at an incomplete or unreadable record
    error: str = ""
    messages: int = 0

    def messages_iter(self, topics: set[str] | None = None) -> Iterator[RecordedMessage]:
        """Stream the file's messages in file order (never seeks to the summary)."""
        try:
            fh = open(self.path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise RecordingError(f"cannot open {self.path}: {exc}") from exc
        with fh:
            reader = StreamReader(fh, validate_crcs=True, record_size_limit=1 << 31)
            records = reader.records
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    self.complete = True
                    return
                except Exception as exc:  # EndOfFile, short chunk, bad CRC, zstd error
                    self.truncated = True
                    self.error = f"{type(exc).__name__}: {exc}"
                    return
                if isinstance(rec, Schema):
                    self.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    self.channels[rec.id] = rec
                elif isinstance(rec, Metadata):
                    self.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Message):
                    ch = self.channels.get(rec.channel_id)
                    if ch is None:
                        continue
                    if topics is not None and ch.topic not in topics:
                        continue
                    self.messages += 1
                    yield RecordedMessage(
                        ch.topic,
                        ch,
                        self.schemas.get(ch.schema_id),
                        rec.log_time,
                        rec.publish_time,
                        rec.sequence,
                        rec.data,
                    )


def read_recording(path: str | Path) -> Recording:
    """A :class:`Recording` to stream with ``messages_iter()`` (fields fill as it goes)."""
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file")
    return Recording(p)


def scan(path: str | Path) -> tuple[Recording, dict[str, int]]:
    """One streaming pass: the recording's description and message count per topic."""
    rec = read_recording(path)
    counts: dict[str, int] = {}
    for m in rec.messages_iter():
        counts[m.topic] = counts.get(m.topic, 0) + 1
    return rec, counts


def recover(src: str | Path, dst: str | Path | None = None) -> Recording:
    """Rewrite ``src`` whole (every complete chunk, plus a summary) to ``dst`` (default:
    ``src`` in place, through a ``.tmp`` file). Returns what was read."""
    src = Path(src)
    out = Path(dst) if dst is not None else src
    tmp = out.with_name(out.name + ".tmp")
    rec = read_recording(src)
    writer_file = open(tmp, "wb")  # noqa: SIM115 - closed below
    try:
        w = Writer(writer_file, compression=CompressionType.ZSTD)
        w.start(profile=PROFILE, library=LIBRARY)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        meta_done: set[str] = set()
        for m in rec.messages_iter():
            for name, data in rec.metadata.items():
                if name not in meta_done:
                    w.add_metadata(name, data)
                    meta_done.add(name)
            ch = m.channel
            if ch.id not in channel_ids:
                sid = 0
                if m.schema is not None:
                    if m.schema.id not in schema_ids:
                        schema_ids[m.schema.id] = w.register_schema(
                            m.schema.name, m.schema.encoding, m.schema.data
                        )
                    sid = schema_ids[m.schema.id]
                channel_ids[ch.id] = w.register_channel(
                    ch.topic, ch.message_encoding, sid, dict(ch.metadata)
                )
            w.add_message(
                channel_ids[ch.id],
                log_time=m.log_time,
                data=m.data,
                publish_time=m.publish_time,
                sequence=m.sequence,
            )
        for name, data in rec.metadata.items():
            if name not in meta_done:
                w.add_metadata(name, data)
        w.finish()
        writer_file.flush()
        os.fsync(writer_file.fileno())
    except BaseException:
        writer_file.close()
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    writer_file.close()
    os.replace(tmp, out)
    return rec


# -- commands --------------------------------------------------------------------------------


def main_recover(args: Any) -> int:
    rec = recover(args.file, args.output)
    state = "complete" if rec.complete else ("truncated: " + rec.error if rec.truncated else "")
    print(
        json.dumps(
            {
                "input": str(args.file),
                "output": str(args.output or args.file),
                "messages": rec.messages,
                "channels": len(rec.channels),
                "input_state": state,
            }
        )
    )
    return 0


def main_info(args: Any) -> int:
    rec, counts = scan(args.file)
    doc = {
        "file": str(args.file),
        "complete": rec.complete,
        "truncated": rec.truncated,
        "error": rec.error,
        "messages": rec.messages,
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
    print(json.dumps(doc, indent=1))
    return 0 if not rec.truncated else 1


def main_record(args: Any, zc: Any) -> int:
    """``daq record``: subscribe to a key expression and write every sample to MCAP."""
    import signal

    import zenoh

    from daq.bus import fetch_schema, fetch_schemas, open_session

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = open_session(zc)
    rec = BackgroundRecorder(McapRecorder(args.output))
    # schemas first, then the subscriber (a schema get on a young subscription coincided
    # with lost messages: daq.bus.Receiver)
    known = fetch_schemas(session, args.key)
    channels: dict[str, int] = {}
    sub = session.declare_subscriber(args.key, zenoh.handlers.FifoChannel(65536))
    print(json.dumps({"recording": str(rec.path), "key": args.key}), flush=True)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    try:
        while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
            sample = sub.try_recv()
            if sample is None:
                time.sleep(0.0005)
                continue
            key = str(sample.key_expr)
            now = time.time_ns()
            cid = channels.get(key)
            if cid is None:
                enc = str(sample.encoding)
                if enc.endswith(ENCODING_NAME):
                    try:
                        schema = known.get(key) or fetch_schema(session, key)
                        cid = rec.add_columnar(schema)
                    except Exception as exc:
                        log.warning("no schema for %s, not recorded: %s", key, exc)
                        channels[key] = -1
                        continue
                elif enc.startswith("application/json"):
                    cid = rec.add_json(
                        key, HEALTH_SCHEMA_NAME, HEALTH_SCHEMA, {"daq.kind": KIND_HEALTH}
                    )
                else:
                    channels[key] = -1
                    continue
                channels[key] = cid
            if cid < 0:
                continue
            rec.write(cid, sample.payload.to_bytes(), now, now)
    finally:
        sub.undeclare()
        rec.close()
        session.close()
    return 0
