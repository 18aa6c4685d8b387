"""MCAP recording: a crash-tolerant writer, a streaming reader, ``recover``, ``info``, and
the ``daq record`` zenoh sink.

Writer: chunked and compressed (zstd by default); a chunk is closed when it reaches
``chunk_size_bytes`` *or* ``chunk_interval_s`` after its first message, and written to the
OS at once, so a crash or ``kill -9`` loses at most the chunk in progress. The summary
(indexes, statistics) is written only by :meth:`McapRecorder.close`: a killed recording
has none, and a reader that seeks to the summary fails on it. This module's reader
therefore *streams* (:func:`read_recording`): it checks every chunk (lengths,
decompression to the stated size, CRC) and uses it whole or not at all, skips a damaged
region by resynchronising on the next chunk that checks out, and lists every region it
skipped (:class:`Damage`: byte offsets, record kind, reason). ``daq recover`` writes the
readable messages of such a file as a whole file with a summary, beside the original
(``F.recovered.mcap``, ``-o``) or, with ``--in-place``, in its place keeping
``F.mcap.bak``; a complete file is left alone. ``daq info`` says where and why a file is
damaged. A file that is not MCAP (no magic), empty, a directory or a device is a
:class:`~daq.errors.RecordingError` naming it.

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
import shutil
import stat
import tempfile
import threading
import time
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from mcap.records import Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from daq.columnar import ENCODING_NAME, SCHEMA_ENCODING, StreamSchema, decode
from daq.errors import DaqError, RecordingError
from daq.scheduling import normal_for_this_thread
from edges.outputs import OutputSet

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


# -- streaming reader ----------------------------------------------------------------------
#
# The reader parses MCAP itself, record by record (the mcap library's StreamReader stops
# at the first bad byte and cannot resume): every read is bounded by the file's size and
# MAX_RECORD_BYTES, a chunk is used whole or not at all (its length fields, its
# decompression to exactly its stated size and its CRC must all check out), and after a
# damaged region the reader resynchronises on the next chunk that checks out, so one bad
# chunk in the middle costs that chunk only.

MAGIC = b"\x89MCAP0\r\n"
#: the largest record the reader loads, in bytes (the writer's chunks are
#: ``chunk_size_bytes``, 1 MiB by default and at most 64 MiB, plus one message)
MAX_RECORD_BYTES = 256 << 20
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_METADATA = 0x0C
RECORD_KINDS: dict[int, str] = {
    0x01: "header",
    0x02: "footer",
    0x03: "schema",
    0x04: "channel",
    0x05: "message",
    0x06: "chunk",
    0x07: "message index",
    0x08: "chunk index",
    0x09: "attachment",
    0x0A: "attachment index",
    0x0B: "statistics",
    0x0C: "metadata",
    0x0D: "metadata index",
    0x0E: "summary offset",
    0x0F: "data end",
}
CHUNK_COMPRESSIONS = ("", "zstd", "lz4")
_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4 + 8  # times, size, crc, compression length, records length
_FOOTER_LEN = 20
_RESYNC_WINDOW = 1 << 20


class _Bad(Exception):
    """A record that does not check out; the text says why (one phrase)."""


class _Fields:
    """Little-endian fields of one record's bytes, every read bounds-checked."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise _Bad(
                f"bad length: a field of {n} bytes at +{self.pos} runs past the record's "
                f"end ({len(self.data)} bytes)"
            )
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def u16(self) -> int:
        return int.from_bytes(self.take(2), "little")

    def u32(self) -> int:
        return int.from_bytes(self.take(4), "little")

    def u64(self) -> int:
        return int.from_bytes(self.take(8), "little")

    def string(self) -> str:
        raw = self.take(self.u32())
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise _Bad(f"a string at +{self.pos - len(raw)} is not UTF-8") from None

    def str_map(self) -> dict[str, str]:
        n = self.u32()
        end = self.pos + n
        if end > len(self.data):
            raise _Bad("bad length: a key-value map runs past the record's end")
        out: dict[str, str] = {}
        while self.pos < end:
            key = self.string()
            out[key] = self.string()
        if self.pos != end:
            raise _Bad("bad length: a key-value map's entries overrun its stated length")
        return out

    def rest(self) -> bytes:
        return self.take(len(self.data) - self.pos)


def _schema(f: _Fields) -> Schema:
    sid, name, encoding = f.u16(), f.string(), f.string()
    return Schema(id=sid, name=name, encoding=encoding, data=f.take(f.u32()))


def _channel(f: _Fields) -> Channel:
    cid, sid = f.u16(), f.u16()
    topic, encoding = f.string(), f.string()
    return Channel(
        id=cid, schema_id=sid, topic=topic, message_encoding=encoding, metadata=f.str_map()
    )


def _message(f: _Fields) -> Message:
    cid, seq, log_time, publish_time = f.u16(), f.u32(), f.u64(), f.u64()
    return Message(
        channel_id=cid, sequence=seq, log_time=log_time, publish_time=publish_time, data=f.rest()
    )


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    """``data`` decompressed, at most ``size + 1`` bytes (a wrong size is caught, never
    allocated)."""
    if compression == "":
        return data
    try:
        if compression == "zstd":
            import zstandard

            with zstandard.ZstdDecompressor().stream_reader(data) as reader:
                return bytes(reader.read(size + 1))
        import lz4.frame

        return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1))
    except ImportError as exc:
        raise _Bad(f"cannot decompress {compression}: {exc}") from None
    except Exception as exc:  # zstd/lz4 errors: the compressed bytes are damaged
        why = f"{type(exc).__name__}: {exc}"
        raise _Bad(f"{compression} data does not decompress ({why})") from None


def _chunk_records(body: bytes) -> list[Schema | Channel | Message]:
    """The schema, channel and message records of one chunk record's content, or _Bad."""
    f = _Fields(body)
    f.u64(), f.u64()  # message start and end time
    size, crc = f.u64(), f.u32()
    compression = f.string()
    if compression not in CHUNK_COMPRESSIONS:
        raise _Bad(f"unknown compression {compression[:20]!r}")
    n = f.u64()
    if n != len(body) - f.pos:
        raise _Bad(
            f"bad length: its records field says {n} bytes, the record holds {len(body) - f.pos}"
        )
    if size > MAX_RECORD_BYTES:
        raise _Bad(f"bad length: uncompressed size {size} bytes is over the reader's limit")
    data = _decompress(compression, f.rest(), size)
    if len(data) < size:
        raise _Bad(f"decompresses to {len(data)} bytes, stated {size}")
    if len(data) > size:
        raise _Bad(f"decompresses to more than its stated {size} bytes")
    if crc != 0 and zlib.crc32(data) != crc:
        raise _Bad(f"bad CRC (stored {crc:#010x}, computed {zlib.crc32(data):#010x})")
    out: list[Schema | Channel | Message] = []
    g = _Fields(data)
    while g.pos < len(data):
        at = g.pos
        op = g.take(1)[0]
        inner = _Fields(g.take(g.u64()))
        try:
            if op == OP_SCHEMA:
                out.append(_schema(inner))
            elif op == OP_CHANNEL:
                out.append(_channel(inner))
            elif op == OP_MESSAGE:
                out.append(_message(inner))
        except _Bad as exc:
            raise _Bad(f"{RECORD_KINDS[op]} record at +{at} inside: {exc}") from None
    return out


def _plausible_chunk(buf: bytes, i: int, remaining: int) -> bool:
    """Cheap test of a chunk header at ``buf[i]`` (``remaining``: file bytes from there):
    the record length fits the file and agrees with its compression and records fields."""
    if i + 9 + _CHUNK_FIXED > len(buf):
        return True  # cannot tell from the window: the full check decides
    length = int.from_bytes(buf[i + 1 : i + 9], "little")
    if length < _CHUNK_FIXED or length > min(remaining - 9, MAX_RECORD_BYTES):
        return False
    clen = int.from_bytes(buf[i + 9 + 28 : i + 9 + 32], "little")
    if clen > 4:
        return False
    j = i + 9 + 32 + clen
    if j + 8 > len(buf):
        return True
    return int.from_bytes(buf[j : j + 8], "little") == length - _CHUNK_FIXED - clen


@dataclass(frozen=True)
class Damage:
    """A damaged region of a recording: bytes ``offset``..``end`` (the offset where
    reading resumed, or the file's size) skipped; ``record``: the kind of the record that
    did not check out at ``offset``; ``reason``: why."""

    offset: int
    end: int
    record: str
    reason: str

    def as_dict(self) -> dict[str, Any]:
        return {
            "offset": self.offset,
            "end": self.end,
            "bytes": self.end - self.offset,
            "record": self.record,
            "reason": self.reason,
        }

    def __str__(self) -> str:
        skipped = f", bytes {self.offset}-{self.end} skipped" if self.end > self.offset else ""
        return f"byte {self.offset}: {self.record}: {self.reason}{skipped}"


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
    """What a streaming pass found: channels, schemas, metadata, and how it ended.

    ``complete``: the footer and the end magic were reached and nothing was damaged;
    ``damaged``: every region skipped (a missing footer is one, at the file's end);
    ``truncated``: there is at least one (the file is not whole); ``error``: them in
    words; ``messages``: messages yielded; ``orphans``: messages read whose channel
    record was lost (in a damaged chunk) and not in the summary either; ``chunks``:
    chunks read whole.
    """

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False
    truncated: bool = False
    error: str = ""
    messages: int = 0
    damaged: list[Damage] = field(default_factory=list)
    orphans: int = 0
    chunks: int = 0
    size: int = 0

    def _reset(self) -> None:
        self.schemas, self.channels, self.metadata = {}, {}, {}
        self.complete = self.truncated = False
        self.error = ""
        self.messages = self.orphans = self.chunks = 0
        self.damaged = []

    def _damage(self, offset: int, end: int, record: str, reason: str) -> None:
        self.damaged.append(Damage(offset, end, record, reason))
        self.truncated = True
        first = str(self.damaged[0])
        more = len(self.damaged) - 1
        regions = f"region{'s' * (more > 1)}"
        self.error = first + (f" (and {more} more damaged {regions})" if more else "")

    @property
    def chunks_damaged(self) -> int:
        return sum(1 for d in self.damaged if d.record == "chunk")

    def messages_iter(self, topics: set[str] | None = None) -> Iterator[RecordedMessage]:
        """Stream the file's messages in file order, past damaged regions (module
        comment); never loads more than one record."""
        self._reset()
        fh = _open_recording(self.path)
        with fh:
            self.size = size = os.fstat(fh.fileno()).st_size
            fallback = _summary_channels(fh, size)
            yield from self._walk(fh, size, fallback, topics)

    def _message(
        self,
        m: Message,
        fallback: tuple[dict[int, Schema], dict[int, Channel]],
        topics: set[str] | None,
    ) -> RecordedMessage | None:
        ch = self.channels.get(m.channel_id)
        if ch is None:
            ch = fallback[1].get(m.channel_id)
            if ch is None:
                self.orphans += 1
                return None
            self.channels[ch.id] = ch
            if ch.schema_id not in self.schemas and ch.schema_id in fallback[0]:
                self.schemas[ch.schema_id] = fallback[0][ch.schema_id]
        if topics is not None and ch.topic not in topics:
            return None
        self.messages += 1
        return RecordedMessage(
            ch.topic,
            ch,
            self.schemas.get(ch.schema_id),
            m.log_time,
            m.publish_time,
            m.sequence,
            m.data,
        )

    def _walk(
        self,
        fh: Any,
        size: int,
        fallback: tuple[dict[int, Schema], dict[int, Channel]],
        topics: set[str] | None,
    ) -> Iterator[RecordedMessage]:
        """The messages of ``fh`` (``size`` bytes), top-level record after record; an
        unreadable one is noted in ``damaged`` and skipped to the next good chunk."""
        pos = len(MAGIC)
        while True:
            if pos >= size:
                self._damage(
                    size,
                    size,
                    "footer",
                    "missing: the file ends after its last whole record (a recording "
                    "that was not closed: killed, crashed or out of disk)",
                )
                return
            top = _read_top(fh, pos, size)
            if top.problem:
                resume = self._skip(fh, pos, size, top)
                if resume is None:
                    return
                pos = resume
                continue
            for r in top.records:
                if isinstance(r, Schema):
                    self.schemas[r.id] = r
                elif isinstance(r, Channel):
                    self.channels[r.id] = r
                elif isinstance(r, Metadata):
                    self.metadata[r.name] = dict(r.metadata)
                elif isinstance(r, Message):
                    got = self._message(r, fallback, topics)
                    if got is not None:
                        yield got
            if top.op == OP_CHUNK:
                self.chunks += 1
            pos += 9 + top.length
            if top.op == OP_FOOTER:
                self._after_footer(fh, pos, size)
                return

    def _skip(self, fh: Any, pos: int, size: int, top: _TopRecord) -> int | None:
        """Note the damage of the unreadable record ``top`` at ``pos``; where reading
        resumes: the next chunk that checks out (None: there is none, the walk ends)."""
        resume = top.resume
        if resume is None:
            resume = _resync(fh, pos + 1, size)
        problem, length = top.problem, top.length
        if problem == "length":
            problem = (
                f"bad length: {length} bytes would run past the end of the file"
                if resume is not None
                else f"truncated: the file ends {size - pos - 9} bytes into a record "
                f"of {length} bytes"
            )
        self._damage(pos, size if resume is None else resume, top.kind, problem)
        return resume

    def _after_footer(self, fh: Any, pos: int, size: int) -> None:
        """The end magic after the footer (which ends at ``pos``), and nothing after it:
        the file is ``complete`` when it holds and nothing was damaged."""
        tail = _pread(fh, pos, len(MAGIC) + 1)
        if tail[: len(MAGIC)] != MAGIC:
            self._damage(pos, size, "end magic", "missing or wrong after the footer")
        elif len(tail) > len(MAGIC):
            self._damage(
                pos + len(MAGIC),
                size,
                "end",
                f"{size - pos - len(MAGIC)} bytes after the end magic",
            )
        else:
            self.complete = not self.damaged


class _TopRecord(NamedTuple):
    """A top-level record as read: ``op`` (-1: its header is cut short), ``kind`` (in
    words), ``length`` (bytes after the 9-byte header), the ``records`` it stands for;
    ``problem``: why it cannot be used ("": it can; "length": past the end of the file,
    worded once the reader knows whether a chunk follows), ``resume``: a chunk found
    inside a record whose length is too large."""

    op: int
    kind: str
    length: int
    records: list[Any]
    problem: str = ""
    resume: int | None = None


def _read_top(fh: Any, pos: int, size: int) -> _TopRecord:
    """The top-level record at ``pos`` of ``fh`` (``size`` bytes), checked."""
    head = _pread(fh, pos, 9)
    if len(head) < 9:
        problem = f"truncated: the file ends {len(head)} bytes into a record header"
        return _TopRecord(-1, "record", 0, [], problem)
    op, length = head[0], int.from_bytes(head[1:], "little")
    kind = RECORD_KINDS.get(op, "unknown record" if op < 0x80 else f"private record {op:#04x}")
    if op not in RECORD_KINDS and op < 0x80:
        return _TopRecord(op, kind, length, [], f"bad opcode {op:#04x}")
    if pos == len(MAGIC) and op != OP_HEADER:
        return _TopRecord(op, "header", length, [], f"missing: the first record is a {kind}")
    if length > size - pos - 9:
        return _TopRecord(op, kind, length, [], "length")  # worded by Recording._skip
    if length > MAX_RECORD_BYTES:
        problem = (
            f"bad length: {length} bytes is over the reader's limit of {MAX_RECORD_BYTES} bytes"
        )
        return _TopRecord(op, kind, length, [], problem)
    body = _pread(fh, pos + 9, length)
    try:
        records, fields_end = _top_record(op, body)
    except _Bad as exc:
        return _TopRecord(op, kind, length, [], str(exc))
    if fields_end < length:  # a length too large swallows what follows: a chunk, say
        body_at = pos + 9
        resume = _resync(fh, body_at + fields_end, size, body_at + length)
        if resume is not None:
            problem = f"bad length: {length} bytes, but a chunk starts inside it at byte {resume}"
            return _TopRecord(op, kind, length, records, problem, resume)
    return _TopRecord(op, kind, length, records)


def _pread(fh: Any, at: int, n: int) -> bytes:
    fh.seek(at)
    return bytes(fh.read(n))


def _top_record(op: int, body: bytes) -> tuple[list[Any], int]:
    """The records a top-level record stands for (a chunk: those inside it), and where
    its checked fields end (a record no CRC guards: the bytes after that are padding or
    a message's data, which a wrong length field would have swallowed)."""
    f = _Fields(body)
    if op == OP_CHUNK:
        return list(_chunk_records(body)), len(body)
    out: list[Any] = []
    if op == OP_HEADER:
        f.string(), f.string()  # profile, library
    elif op == OP_SCHEMA:
        out = [_schema(f)]
    elif op == OP_CHANNEL:
        out = [_channel(f)]
    elif op == OP_MESSAGE:
        out = [_message(f)]
        return out, 22  # channel id, sequence, two times: the rest is data
    elif op == OP_METADATA:
        name = f.string()
        out = [Metadata(name=name, metadata=f.str_map())]
    else:
        if op == OP_FOOTER and len(body) < _FOOTER_LEN:
            raise _Bad(f"bad length: {len(body)} bytes, a footer has {_FOOTER_LEN}")
        return [], len(body)  # indexes, statistics, attachments, private records: unused
    return out, f.pos


def _resync(fh: Any, start: int, size: int, before: int | None = None) -> int | None:
    """The offset of the next chunk record from ``start`` on (and before ``before``)
    whose length fields, decompression and CRC check out, or None."""
    pos = start
    end = size - 9 - _CHUNK_FIXED if before is None else min(before, size - 9 - _CHUNK_FIXED)
    while pos < end:
        buf = _pread(fh, pos, _RESYNC_WINDOW + 64)
        i = buf.find(OP_CHUNK.to_bytes(1, "little"))
        while 0 <= i < _RESYNC_WINDOW and pos + i < end:
            cand = pos + i
            if _plausible_chunk(buf, i, size - cand) and _chunk_at(fh, cand, size):
                return cand
            i = buf.find(OP_CHUNK.to_bytes(1, "little"), i + 1)
        pos += _RESYNC_WINDOW
    return None


def _chunk_at(fh: Any, at: int, size: int) -> bool:
    head = _pread(fh, at, 9)
    if len(head) < 9 or head[0] != OP_CHUNK:
        return False
    length = int.from_bytes(head[1:], "little")
    if length < _CHUNK_FIXED or length > min(size - at - 9, MAX_RECORD_BYTES):
        return False
    try:
        _chunk_records(_pread(fh, at + 9, length))
    except _Bad:
        return False
    return True


def _summary_channels(fh: Any, size: int) -> tuple[dict[int, Schema], dict[int, Channel]]:
    """Schemas and channels of the summary section, when the file has a footer (for
    messages whose chunk of channel records was damaged); empty when it has none."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    footer_at = size - len(MAGIC) - 9 - _FOOTER_LEN
    if footer_at <= len(MAGIC):
        return schemas, channels
    tail = _pread(fh, footer_at, 9 + _FOOTER_LEN + len(MAGIC))
    if (
        tail[0] != OP_FOOTER
        or int.from_bytes(tail[1:9], "little") != _FOOTER_LEN
        or tail[-len(MAGIC) :] != MAGIC
    ):
        return schemas, channels
    start = int.from_bytes(tail[9:17], "little")
    if not len(MAGIC) < start < footer_at or footer_at - start > MAX_RECORD_BYTES:
        return schemas, channels
    data = _pread(fh, start, footer_at - start)
    crc = int.from_bytes(tail[25:29], "little")
    if crc != 0 and zlib.crc32(tail[:25], zlib.crc32(data)) != crc:
        return schemas, channels  # the summary is damaged: not trusted
    f = _Fields(data)
    try:
        while f.pos < len(data):
            op = f.take(1)[0]
            inner = _Fields(f.take(f.u64()))
            if op == OP_SCHEMA:
                s = _schema(inner)
                schemas[s.id] = s
            elif op == OP_CHANNEL:
                c = _channel(inner)
                channels[c.id] = c
    except _Bad:
        pass  # what was read before the bad record is kept
    return schemas, channels


def _open_recording(path: Path) -> Any:
    """``path`` opened for reading, after checking it is a regular file that starts with
    the MCAP magic; else :class:`RecordingError` naming the file and what it is."""
    try:
        fifo = stat.S_ISFIFO(os.stat(path).st_mode)
    except OSError:
        fifo = False  # said below, by open()
    if fifo:  # refused before opening: opening a named pipe waits for a writer
        raise RecordingError(f"{path}: a named pipe; an MCAP recording is read from a regular file")
    try:
        fh = open(path, "rb")  # noqa: SIM115 - the caller closes it
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise RecordingError(f"{path}: is a directory, expected an MCAP recording") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fh.fileno())
        if stat.S_ISDIR(st.st_mode):
            raise RecordingError(f"{path}: is a directory, expected an MCAP recording")
        if not stat.S_ISREG(st.st_mode):
            raise RecordingError(
                f"{path}: not a regular file (a device or pipe); an MCAP recording is read "
                "from a file"
            )
        head = fh.read(len(MAGIC))
        if not head:
            raise RecordingError(f"{path}: empty file (0 bytes), not an MCAP recording")
        if head != MAGIC:
            if MAGIC.startswith(head):
                raise RecordingError(
                    f"{path}: truncated inside the MCAP magic ({len(head)} bytes): "
                    "nothing was recorded"
                )
            raise RecordingError(
                f"{path}: not an MCAP file (it starts with {head!r}; a recording starts "
                f"with {MAGIC!r}){_looks_like(head)}"
            )
    except BaseException:
        fh.close()
        raise
    return fh


def _looks_like(head: bytes) -> str:
    if head.startswith(b"PK"):
        return " - a zip archive?"
    if head.startswith((b"\x1f\x8b", b"\x28\xb5\x2f\xfd")):
        return " - a compressed file (gzip/zstd)? decompress it first"
    try:
        head.decode("ascii")
    except UnicodeDecodeError:
        return ""
    return " - a text file (CSV, TOML, JSON)?"


def read_recording(path: str | Path) -> Recording:
    """A :class:`Recording` to stream with ``messages_iter()`` (fields fill as it goes).
    The file is checked at once: missing, not a regular file, empty or without the MCAP
    magic is a :class:`RecordingError` naming it."""
    p = Path(path)
    _open_recording(p).close()
    return Recording(p)


def scan(path: str | Path) -> tuple[Recording, dict[str, int]]:
    """One streaming pass: the recording's description and message count per topic."""
    rec = read_recording(path)
    counts: dict[str, int] = {}
    for m in rec.messages_iter():
        counts[m.topic] = counts.get(m.topic, 0) + 1
    return rec, counts


# -- recover --------------------------------------------------------------------------------


def recovered_path(src: str | Path) -> Path:
    """Where ``daq recover F.mcap`` writes by default: ``F.recovered.mcap`` beside it."""
    p = Path(src)
    stem = p.name[: -len(".mcap")] if p.name.endswith(".mcap") else p.name
    return p.with_name(stem + ".recovered.mcap")


def backup_path(src: str | Path) -> Path:
    """The copy of the original that ``recover --in-place`` keeps: ``F.mcap.bak``."""
    p = Path(src)
    return p.with_name(p.name + ".bak")


@dataclass
class Recovery:
    """What :func:`recover` did: ``recording`` is what the pass read; ``output`` the file
    written (None: nothing written, the input was complete); ``backup`` the original's
    copy of an in-place recovery."""

    recording: Recording
    output: Path | None
    backup: Path | None = None

    def as_dict(self, src: str | Path) -> dict[str, Any]:
        rec = self.recording
        return {
            "input": str(src),
            "complete": rec.complete,
            "output": None if self.output is None else str(self.output),
            "backup": None if self.backup is None else str(self.backup),
            "messages": rec.messages,
            "channels": len(rec.channels),
            "chunks": rec.chunks,
            "chunks_damaged": rec.chunks_damaged,
            "orphans": rec.orphans,
            "damaged": [d.as_dict() for d in rec.damaged],
            "input_state": "complete" if rec.complete else "damaged: " + rec.error,
        }


def _copy_messages(rec: Recording, out: Path) -> None:
    """Write every readable message of ``rec`` (one streaming pass) to ``out`` as a whole
    MCAP file: chunks, indexes, summary."""
    with open(out, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
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
        fh.flush()
        os.fsync(fh.fileno())


def recover(
    src: str | Path,
    dst: str | Path | None = None,
    *,
    in_place: bool = False,
    option: str = "-o/--output",
) -> Recovery:
    """Write every readable message of ``src`` (all whole chunks, those after a damaged
    one included) to a whole MCAP file with a summary; ``src`` is never changed.

    ``dst``: the output (default :func:`recovered_path`); ``in_place``: replace ``src``
    instead, after keeping the original as :func:`backup_path` (a hard link, else a
    copy). A complete ``src`` is left alone and nothing is written (``output`` None).
    The output is staged and moved into place only when whole (:class:`OutputSet`); an
    output that is ``src`` without ``in_place``, or a file without one readable message,
    is refused with :class:`RecordingError`."""
    src = Path(src)
    rec = read_recording(src)
    if in_place and dst is not None:
        raise RecordingError(f"{option} and --in-place: give one of them")
    target = src if in_place else Path(dst) if dst is not None else recovered_path(src)
    outputs = OutputSet(inputs=[] if in_place else [src], error=RecordingError)
    with outputs:
        staged = outputs.file(target, "--in-place" if in_place else option)
        _copy_messages(rec, staged)
        if rec.complete:
            outputs.discard()
            return Recovery(rec, None)
        if rec.messages == 0:
            raise RecordingError(
                f"{src}: no readable message ({rec.error}); nothing written"
                + (f" ({rec.orphans} messages lost their channel record)" if rec.orphans else "")
            )
        backup = None
        if in_place:
            backup = backup_path(src)
            if backup.exists() or backup.is_symlink():
                raise RecordingError(
                    f"--in-place: the backup {backup} exists already; move it away or "
                    "recover to another file with -o"
                )
            try:
                os.link(src, backup)
            except OSError:
                shutil.copy2(src, backup)
    return Recovery(rec, target, backup)


# -- commands --------------------------------------------------------------------------------


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
    print(json.dumps(doc, indent=1), flush=True)
    return 0 if rec.complete else 1


def main_record(args: Any, zc: Any) -> int:
    """``daq record``: subscribe to a key expression and write every sample to MCAP."""
    import signal

    import zenoh

    from daq.bus import fetch_schemas, open_session, require_peer

    # the file is written as samples come (a crash keeps what was closed): checked up
    # front, not staged
    config_path = getattr(args, "config", None) or os.environ.get("DAQ_CONFIG")
    check_stream_output(args.output, "-o/--output", [config_path])
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
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
    channels = _SubscribedChannels(rec, session, known, rate)
    sub = session.declare_subscriber(args.key, zenoh.handlers.FifoChannel(65536))
    print(json.dumps({"recording": str(rec.path), "key": args.key}), flush=True)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    try:
        while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
            sample = sub.try_recv()
            if sample is None:
                time.sleep(0.0005)
                continue
            channels.write(sample)
    finally:
        sub.undeclare()
        channels.flush()
        rec.close()
        session.close()
    return 0


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
    ) -> None:
        self.rec = rec
        self.session = session
        self.known = known
        self.rate_hz = rate_hz
        self.ids: dict[str, int] = {}  # -1: not recorded
        # viewer channels (daq.viewer) of the columnar keys, at their bounded rate
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
        view = self.viewers.get(key)
        if view is not None and view[0].due(now):
            try:
                view[0].add(decode(view[1], payload)[1], now)
            except DaqError as exc:  # a payload of another schema: the data is kept
                log.warning("%s: no viewer message: %s", key, exc)

    def _open(self, key: str, encoding: str) -> int:
        """The channel id of ``key`` (-1: not recorded)."""
        from daq.bus import fetch_schema
        from daq.viewer import StreamViewer

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
