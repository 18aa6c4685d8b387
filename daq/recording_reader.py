"""MCAP reading that survives damage: :func:`read_recording` streams a file, killed or
damaged ones included, and :class:`Damage` reports each region it skipped.

A recording that was not closed has no summary (:mod:`daq.recording_writer`), so this
reader *streams*: it checks every chunk (lengths, decompression to the stated size, CRC)
and uses it whole or not at all, skips a damaged region by resynchronising on the next
chunk that checks out, and lists every region it skipped (:class:`Damage`: byte offsets,
record kind, reason). A file that is not MCAP (no magic), empty, a directory or a device
is a :class:`~daq.errors.RecordingError` naming it.
"""

from __future__ import annotations

import os
import stat
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from mcap.records import Channel, Message, Metadata, Schema

from daq.errors import RecordingError

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
#: the topic of a subscriber's hole records (written by daq.recording_holes: what a
#: ``daq record`` file lacks, and why); readers report them, replays skip them
HOLES_TOPIC = "daq/holes"
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
