"""``daq replay``: republish an MCAP recording over zenoh, as recorded.

Every data and health message goes out on its recorded key with its recorded payload
bytes and encoding (so sample timestamps, sequence numbers and ``batch_seq`` are those of
the recording), paced by the recorded ``log_time``: real time (``speed`` 1), ×N, or as
fast as possible. Schemas are served from the recording by the same ``<key>/@schema``
queryable as the daemon's, and a liveliness token is held per recorded device. Options:
loop, start offset (seconds after the first message), key-expression filter. Derived
viewer channels (Foxglove) are not republished. The file is streamed, so a truncated
recording replays up to its last complete chunk, and a damaged chunk in the middle costs
only that chunk (``daq.recording_reader``; the result's ``damaged`` lists the regions skipped).
``daq replay`` refuses such a file unless ``--allow-partial`` (:func:`survey` reads it
once before anything is published), and says on stderr what was readable and what not.
A data key whose schema is missing or unreadable is never republished: every subscriber
would fail to decode it (``not_republished`` in the result says why).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import sys
import threading
import time
from typing import Any, NamedTuple

import zenoh

from daq.bus import DATA_ENCODING, JSON_ENCODING, SchemaServer, device_key, open_session
from daq.columnar import ENCODING_NAME, StreamSchema
from daq.config import ZenohConfig
from daq.errors import DaqError, RecordingError
from daq.recording_holes import HOLES_TOPIC, KIND_HOLES
from daq.recording_reader import RecordedMessage, Recording, read_recording
from daq.recording_writer import KIND_FOXGLOVE
from edges.stop_signals import on_stop_signals

log = logging.getLogger(__name__)


class _Topic:
    def __init__(self, publisher: Any) -> None:
        self.publisher = publisher
        self.messages = 0
        self.bytes = 0


def schema_problem(m: RecordedMessage) -> str:
    """Why ``m``'s data cannot be decoded by a subscriber ("" when it can): a columnar
    key whose schema record was lost, or whose schema does not parse (cut, damaged)."""
    if m.channel.message_encoding != ENCODING_NAME:
        return ""
    if m.schema is None:
        return "its schema record is missing (lost in a damaged region)"
    try:
        StreamSchema.loads(m.schema.data)
    except (DaqError, ValueError, KeyError, TypeError) as exc:
        return f"its schema does not parse ({exc})"
    return ""


class Survey(NamedTuple):
    """One pass over a recording without publishing: the pass (its damage and counts)
    and the keys whose schema is missing or unreadable, with why."""

    recording: Recording
    bad_schemas: dict[str, str]

    def problems(self) -> str:
        """What was readable and what was not, in words ("" for a whole file; a missing
        footer alone, a recording that was not closed, is not a problem)."""
        rec = self.recording
        lost = [d for d in rec.damaged if d.record != "footer"]
        parts = []
        if lost:
            skipped = sum(max(d.end - d.offset, 0) for d in lost)
            parts.append(
                f"{len(lost)} damaged region(s), {skipped} of {rec.size} bytes unreadable "
                f"(first: {lost[0]})"
            )
        for topic, why in sorted(self.bad_schemas.items()):
            parts.append(f"key {topic}: {why}")
        if not parts:
            return ""
        return f"read {rec.messages} messages in {rec.chunks} whole chunks; " + "; ".join(parts)


def survey(path: str) -> Survey:
    """Read ``path`` once, publishing nothing (the cost of a replay at full speed without
    the network)."""
    rec = read_recording(path)
    bad: dict[str, str] = {}
    seen: set[str] = set()
    for m in rec.messages_iter():
        if m.topic in seen:
            continue
        seen.add(m.topic)
        why = schema_problem(m)
        if why:
            bad[m.topic] = why
    return Survey(rec, bad)


class _Pace(NamedTuple):
    """How a pass sends: ``speed`` × real time, or as ``fast`` as it can, from ``start_s``
    (s) after the recording's first message, until ``duration_s`` (s, wall time; None:
    no limit) since the replay began."""

    speed: float
    fast: bool
    start_s: float
    duration_s: float | None

    @classmethod
    def checked(cls, speed: float, fast: bool, start_s: float, duration_s: float | None) -> _Pace:
        """Refused with :class:`RecordingError`: a non-finite or non-positive ``speed``,
        a non-finite or negative ``start_s``."""
        if not math.isfinite(speed) or speed <= 0:
            raise RecordingError(f"--speed: must be a finite number > 0, got {speed}")
        if not math.isfinite(start_s) or start_s < 0:
            raise RecordingError(f"--start: must be a finite number >= 0 (seconds), got {start_s}")
        return cls(speed, fast, start_s, duration_s)


class _Pass(NamedTuple):
    """What one pass over the recording sent: messages, and the first and last
    ``log_time`` it read (ns; None: no message passed the filter)."""

    sent: int
    t_first: int | None
    t_last: int | None


class _Publishers:
    """The zenoh side of a replay: a publisher per republished key, declared at the key's
    first message, with its schema served and its device's liveliness token held."""

    def __init__(
        self,
        session: Any,
        filters: list[zenoh.KeyExpr] | None,
        congestion: str,
        wait_subscribers_s: float,
        stop: threading.Event,
    ) -> None:
        self.session = session
        self.schemas = SchemaServer(session, "cell")
        self.filters = filters
        self.out: dict[str, _Topic] = {}
        self.skipped: set[str] = set()
        self.undecodable: dict[str, str] = {}  # key: why its schema cannot decode it
        self.tokens: dict[tuple[str, str, str], Any] = {}
        self.cc = (
            zenoh.CongestionControl.BLOCK if congestion == "block" else zenoh.CongestionControl.DROP
        )
        self.wait_subscribers_s = wait_subscribers_s
        self.waited = wait_subscribers_s <= 0
        self.stop = stop
        # the recording's hole records (a subscriber's recording: daq.recording_holes),
        # reported, not republished; read in the first pass
        self.holes: list[dict[str, Any]] = []
        self.first_pass = True

    def open(self, m: RecordedMessage) -> _Topic | None:
        """The publisher of ``m``'s key, declared now; None: the key is not republished
        (a viewer channel, or outside the filter), and is skipped from now on."""
        topic = m.topic
        meta = m.channel.metadata
        kind = meta.get("daq.kind", "")
        wanted = kind not in (KIND_FOXGLOVE, KIND_HOLES) and (
            self.filters is None or any(zenoh.KeyExpr(topic).intersects(f) for f in self.filters)
        )
        if not wanted:
            self.skipped.add(topic)
            return None
        why = schema_problem(m)
        if why:  # never republish what no subscriber can decode
            self.skipped.add(topic)
            self.undecodable[topic] = why
            return None
        if m.channel.message_encoding == ENCODING_NAME:
            enc = DATA_ENCODING
            if m.schema is not None:
                self.schemas.register(topic, m.schema.data)
        else:
            enc = JSON_ENCODING
        t = self.out[topic] = _Topic(
            self.session.declare_publisher(topic, encoding=enc, congestion_control=self.cc)
        )
        cell, robot, device = meta.get("cell"), meta.get("robot"), meta.get("device")
        if cell and robot and device and (cell, robot, device) not in self.tokens:
            self.tokens[cell, robot, device] = self.session.liveliness().declare_token(
                device_key(cell, robot, device)
            )
        if not self.waited:
            self._wait_for_subscriber(t)
        return t

    def _wait_for_subscriber(self, t: _Topic) -> None:
        """Up to ``wait_subscribers_s`` for a subscriber of the first key (once a replay)."""
        deadline = time.monotonic() + self.wait_subscribers_s
        while (
            not t.publisher.matching_status.matching
            and time.monotonic() < deadline
            and not self.stop.is_set()
        ):
            time.sleep(0.01)
        self.waited = True

    def close(self) -> None:
        for t in self.out.values():
            t.publisher.undeclare()
        for tok in self.tokens.values():
            tok.undeclare()
        self.schemas.close()


def replay(
    path: str,
    zc: ZenohConfig,
    *,
    speed: float = 1.0,
    fast: bool = False,
    loop: bool = False,
    start_s: float = 0.0,
    topics: list[str] | None = None,
    duration_s: float | None = None,
    wait_subscribers_s: float = 0.0,
    stop: threading.Event | None = None,
    congestion: str = "block",
) -> dict[str, Any]:
    """Replay ``path``; returns per-topic counts, the elapsed time and the damage found.

    Refused with :class:`RecordingError` (naming the file or the option): a file that
    is not an MCAP recording (checked before the session opens), a pass that found
    nothing to send (no readable message, a ``--topic`` that matches no recorded key,
    a ``--start`` past the end), a non-finite or non-positive ``speed``, a negative
    ``start_s``. Long for its options (the signature alone is 14 lines)."""
    pace = _Pace.checked(speed, fast, start_s, duration_s)
    read_recording(path)  # not a recording: said before any session opens
    stop = stop or threading.Event()
    filters = [zenoh.KeyExpr(t) for t in topics] if topics else None
    session = open_session(zc)
    try:
        pubs = _Publishers(session, filters, congestion, wait_subscribers_s, stop)
    except BaseException:
        session.close()
        raise
    t_wall0 = time.monotonic()
    passes = 0
    truncated = False
    damaged: list[dict[str, Any]] = []
    try:
        while not stop.is_set():
            rec = read_recording(path)
            got = _one_pass(rec, pubs, pace, t_wall0, stop)
            truncated = truncated or rec.truncated
            pubs.first_pass = False
            if passes == 0:
                damaged = [d.as_dict() for d in rec.damaged if d.record != "footer"]
            passes += 1
            if got.sent == 0 and not stop.is_set():
                _nothing_sent(path, rec, topics, start_s, got.t_first, got.t_last)
            if not loop:
                break
    finally:
        pubs.close()
        session.close()
    return {
        "file": str(path),
        "passes": passes,
        "truncated": truncated,
        "damaged": damaged,
        "not_republished": dict(sorted(pubs.undecodable.items())),
        "holes": pubs.holes,
        "elapsed_s": time.monotonic() - t_wall0,
        "topics": {
            k: {"messages": v.messages, "bytes": v.bytes} for k, v in sorted(pubs.out.items())
        },
    }


def _one_pass(
    rec: Recording, pubs: _Publishers, pace: _Pace, t_wall0: float, stop: threading.Event
) -> _Pass:
    """Publish ``rec``'s messages once, paced by their ``log_time``; ``pace.duration_s``
    after ``t_wall0`` (``time.monotonic()``, the replay's start) sets ``stop``."""
    out, skipped = pubs.out, pubs.skipped
    speed, fast, start_s, duration_s = pace
    t_first: int | None = None
    t_last: int | None = None
    t_rec0: int | None = None
    w0 = 0.0
    sent = 0
    for m in rec.messages_iter():
        if stop.is_set():
            break
        if duration_s is not None and time.monotonic() - t_wall0 >= duration_s:
            stop.set()
            break
        topic = m.topic
        if topic == HOLES_TOPIC and pubs.first_pass:
            with contextlib.suppress(ValueError):
                pubs.holes.append(json.loads(m.data))
        if topic in skipped:
            continue
        t = out.get(topic)
        if t is None:
            t = pubs.open(m)
            if t is None:
                continue
        if t_first is None:
            t_first = m.log_time
        t_last = m.log_time
        if m.log_time < t_first + int(start_s * 1e9):
            continue
        if t_rec0 is None:
            t_rec0 = m.log_time
            w0 = time.monotonic()
        if not fast:
            target = w0 + (m.log_time - t_rec0) / 1e9 / speed
            delay = target - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
        t.publisher.put(m.data)
        t.messages += 1
        t.bytes += len(m.data)
        sent += 1
    return _Pass(sent, t_first, t_last)


def _nothing_sent(
    path: str,
    rec: Recording,
    topics: list[str] | None,
    start_s: float,
    t_first: int | None,
    t_last: int | None,
) -> None:
    """Why a whole pass sent nothing, as a :class:`RecordingError` (a loop would spin)."""
    if rec.messages == 0:
        why = rec.error or "it holds no message"
        raise RecordingError(f"{path}: no readable message to replay ({why})")
    if t_first is None:  # every message skipped by the filter (or a viewer channel)
        recorded = sorted({c.topic for c in rec.channels.values()})
        shown = ", ".join(recorded[:8]) + (", ..." if len(recorded) > 8 else "")
        if topics:
            raise RecordingError(
                f"--topic {' '.join(topics)}: matches none of the recorded keys ({shown})"
            )
        raise RecordingError(f"{path}: only viewer channels, nothing to republish ({shown})")
    length_s = ((t_last or t_first) - t_first) / 1e9
    raise RecordingError(
        f"--start {start_s:g}: past the end of the recording ({length_s:.3f} s long)"
    )


def main_replay(args: Any, zc: ZenohConfig) -> int:
    stop = threading.Event()
    on_stop_signals(stop.set)  # not stop.set() in the handler: edges/stop_signals.py
    found = survey(args.file)  # not a recording, or damaged: refused before anything is said
    problems = found.problems()
    if found.recording.messages == 0:
        why = found.recording.error or "it holds no message"
        raise RecordingError(f"{args.file}: no readable message to replay ({why})")
    if problems and not args.allow_partial:
        raise RecordingError(
            f"{args.file}: damaged recording: {problems}: refused; pass --allow-partial to "
            "replay the readable part (daq info shows where, daq recover writes a whole file)"
        )
    print(json.dumps({"replay": args.file, "listen": list(zc.listen)}), flush=True)
    result = replay(
        args.file,
        zc,
        speed=args.speed,
        fast=args.fast,
        loop=args.loop,
        start_s=args.start,
        topics=args.topic,
        duration_s=args.duration,
        wait_subscribers_s=args.wait_subscribers,
        stop=stop,
    )
    result["allow_partial"] = bool(args.allow_partial)
    print(json.dumps(result), flush=True)
    if problems:
        print(
            f"daq replay: warning: {args.file}: damaged recording: {problems}; replayed "
            "every readable message"
            + (" of the keys a subscriber can decode" if found.bad_schemas else "")
            + " (--allow-partial; daq info shows where, daq recover writes them to a whole "
            "file)",
            file=sys.stderr,
        )
    elif found.recording.truncated:
        print(
            f"daq replay: warning: {args.file}: not closed (no footer); every record read",
            file=sys.stderr,
        )
    return 0
