"""MCAP writing: the crash-tolerant writer (:class:`McapRecorder`), a recorder that writes
from a thread of its own (:class:`BackgroundRecorder`), and the check of the place of a
file written as it runs (:func:`check_stream_output`).

Chunked and compressed (zstd by default); a chunk is closed when it reaches
``chunk_size_bytes`` *or* ``chunk_interval_s`` after its first message, and written to the
OS at once, so a crash or ``kill -9`` loses at most the chunk in progress. The summary
(indexes, statistics) is written only by :meth:`McapRecorder.close`: a killed recording
has none, and a reader that seeks to the summary fails on it; this project's reader
streams (:mod:`daq.recording_reader`).

Channels (docs/daq.md): one per zenoh data key (topic = the key, message encoding
``daq.columnar.v1``, the key's JSON schema as schema, metadata: device, driver, url…),
one per health key (JSON), and derived viewer channels in Foxglove's JSON schemas
(metadata ``daq.kind = foxglove``; not republished by replay unless asked).
"""

from __future__ import annotations

import json
import logging
import os
import queue
import stat
import tempfile
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from daq.columnar import ENCODING_NAME, SCHEMA_ENCODING, StreamSchema
from daq.errors import RecordingError
from daq.scheduling import normal_for_this_thread

#: the logger keeps the name of the module this code came from (daq.recording), so a
#: logging configuration that names it still applies
log = logging.getLogger("daq.recording")

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


TWIN_HEALTH_SCHEMA_NAME = "grating_twin.twin_health.v1"
TWIN_HEALTH_SCHEMA = {
    "title": TWIN_HEALTH_SCHEMA_NAME,
    "description": "The live twin's health, once a second (docs/topics.md, Twin keys)",
    "type": "object",
    "properties": {
        "t_host_ns": {"type": "integer"},
        "rate_hz": {"type": "number"},
        "samples": {"type": "integer"},
        "latency_ms": {"type": "object"},
        "upstream_ms": {"type": "object"},
        "twin_ms": {"type": "object"},
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


def check_stream_output(
    path: str | Path,
    option: str,
    inputs: Iterable[str | Path | None] = (),
    *,
    regular: bool = True,
    create_dirs: bool = False,
) -> Path:
    """Check, before anything runs, that a file written *while* a command runs (``daq
    record -o``, ``echo --jsonl``, ``run --record``; not staged: its data must survive a
    crash) can be written: not empty, not a directory, not one of ``inputs``, its
    directory there (or, with ``create_dirs``, creatable) and writable (tried with a
    temporary file), an existing file writable (opened for appending, not changed);
    ``regular``: a device or pipe is refused. :class:`RecordingError` naming ``option``."""
    shown = str(path)
    if not shown.strip():
        raise RecordingError(f"{option}: empty path")
    p = Path(os.path.abspath(path))
    try:
        st: os.stat_result | None = p.stat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise RecordingError(f"{option} {shown}: {exc.strerror or exc}") from None
    if st is not None:
        return _check_existing_output(p, st, f"{option} {shown}", inputs, regular)
    return _check_new_output(p, f"{option} {shown}", create_dirs)


def _check_existing_output(
    p: Path, st: os.stat_result, said: str, inputs: Iterable[str | Path | None], regular: bool
) -> Path:
    """:func:`check_stream_output` of a path that exists (``st``); ``said``: the option
    and the path as given, the start of every refusal."""
    if stat.S_ISDIR(st.st_mode):
        raise RecordingError(f"{said}: is a directory, expected a file path")
    for q in inputs:
        if q is None or not str(q):
            continue
        try:
            qs = Path(q).stat()
        except OSError:
            continue
        if (qs.st_dev, qs.st_ino) == (st.st_dev, st.st_ino):
            raise RecordingError(f"{said}: is an input of this run ({q}); choose another path")
    if not stat.S_ISREG(st.st_mode):
        if regular:
            raise RecordingError(f"{said}: not a regular file (a device or pipe); give a file path")
        return p
    try:
        open(p, "ab").close()  # writable? (appends nothing)
    except OSError as exc:
        raise RecordingError(f"{said}: cannot write: {exc.strerror or exc}") from None
    return p


def _check_new_output(p: Path, said: str, create_dirs: bool) -> Path:
    """:func:`check_stream_output` of a path that does not exist yet: its directory is
    there (or creatable) and takes a file."""
    parent = p.parent
    if not parent.is_dir():
        if parent.exists() or not create_dirs:
            what = "is not a directory" if parent.exists() else "does not exist (create it first)"
            raise RecordingError(f"{said}: directory {parent} {what}")
        parent = next((a for a in p.parents if a.exists()), Path("/"))
        if not parent.is_dir():
            raise RecordingError(f"{said}: {parent} is not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{p.name}.probe-", dir=parent)
    except OSError as exc:
        raise RecordingError(f"{said}: cannot write in {parent}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(probe)
    return p


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
