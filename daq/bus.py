"""zenoh plumbing: session from the config, columnar publishers, schema queryable, receiver.

Key layout (docs/topics.md)::

    cell/<cell>/robot/<robot>/<device>/<channel>          columnar sample batches
    cell/<cell>/robot/<robot>/<device>/<channel>/@schema  the channel's JSON schema
    cell/<cell>/robot/<robot>/<device>/health             JSON health, once a second
    cell/<cell>/robot/<robot>/<device>                    liveliness token (device up)

``@schema`` is a zenoh *verbatim* chunk: ``*`` and ``**`` never match it, so a subscriber
to ``cell/**`` sees data and health only, and ``get("cell/**/@schema")`` asks for every
schema at once.
"""

from __future__ import annotations

import atexit
import collections
import json
import logging
import math
import os
import queue
import re
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from numpy.typing import NDArray

from daq.columnar import (
    ENCODING_NAME,
    Header,
    StreamSchema,
    decode,
    encode,
    encode_slices,
    read_header,
)
from daq.config import ZenohConfig
from daq.errors import ConfigError, SchemaError, TransportError
from daq.errors import PublishError as PublishError  # its old path, kept for callers
from daq.tls import check_tls_files, zenoh_tls_entries

log = logging.getLogger(__name__)

SCHEMA_SUFFIX = "@schema"
HEALTH_CHANNEL = "health"
DATA_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(ENCODING_NAME)
JSON_ENCODING = zenoh.Encoding.APPLICATION_JSON
CONGESTION = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}


def device_key(cell: str, robot: str, device: str) -> str:
    return f"cell/{cell}/robot/{robot}/{device}"


def channel_key(cell: str, robot: str, device: str, channel: str) -> str:
    return f"{device_key(cell, robot, device)}/{channel}"


def schema_key(key: str) -> str:
    return f"{key}/{SCHEMA_SUFFIX}"


def health_key(cell: str, robot: str, device: str) -> str:
    return f"{device_key(cell, robot, device)}/{HEALTH_CHANNEL}"


def zenoh_config(zc: ZenohConfig) -> zenoh.Config:
    """A zenoh ``Config`` from ours: explicit endpoints, scouting off unless asked."""
    conf = zenoh.Config()
    entries: dict[str, Any] = {
        "mode": zc.mode,
        "scouting/multicast/enabled": zc.multicast_scouting,
        "scouting/gossip/enabled": zc.gossip_scouting,
        "listen/endpoints": list(zc.listen),
        "connect/endpoints": list(zc.connect),
        "transport/shared_memory/enabled": zc.shared_memory,
        "transport/link/tx/queue/size/data": zc.tx_queue_batches,
    }
    entries.update(zenoh_tls_entries(zc))
    entries.update(zc.extra)
    for path, value in entries.items():
        try:
            conf.insert_json5(path, json.dumps(value))
        except Exception as exc:  # zenoh raises ZError
            raise TransportError(f"zenoh config {path} = {value!r}: {exc}") from exc
    return conf


def zenoh_reason(exc: BaseException) -> str:
    """A zenoh error's text without its Rust source locations (`` at /…/x.rs:12.``)."""
    return re.sub(r"\s*at \S+\.rs:\d+\.?", "", str(exc)).strip()


def open_session(zc: ZenohConfig) -> zenoh.Session:
    check_tls_files(zc, "zenoh settings")  # after any override (a sink's --connect)
    try:
        return zenoh.open(zenoh_config(zc))
    except TransportError:
        raise
    except Exception as exc:
        why = zenoh_reason(exc)
        if zc.connect and "connect" in why.lower():
            # a client (or the daemon's session towards its routers) that reached none
            ends = ", ".join(zc.connect)
            hint = ""
            if "tls/" in ends:
                hint = " (is it up, and does it accept this host's certificate?)"
            raise TransportError(
                f"[zenoh] connect: cannot reach {ends} ({zc.mode}){hint}: {why}"
            ) from exc
        raise TransportError(f"cannot open zenoh session ({zc.mode}, {zc.listen}): {why}") from exc


#: how long a sink that listens nowhere waits for its ``connect`` endpoints to answer (s)
PEER_WAIT_S = 3.0


def require_peer(session: zenoh.Session, zc: ZenohConfig, wait_s: float = PEER_WAIT_S) -> None:
    """Refuse (:class:`TransportError`, exit 2) a sink session that listens nowhere and has
    reached no zenoh peer or router within ``wait_s`` seconds: it would print or record
    nothing for its whole run. A sink that listens (``--listen``) waits for sources to
    connect to it, and a client's session opens only once it reached a router."""
    if zc.listen or zc.mode == "client":
        return
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if any(True for _ in session.info.peers_zid()) or any(
            True for _ in session.info.routers_zid()
        ):
            return
        time.sleep(0.05)
    where = " ".join(zc.connect) or "(no endpoint)"
    raise TransportError(
        f"--connect {where}: nobody answers there (no zenoh peer or router within "
        f"{wait_s:g} s): is the daemon (or a zenoh router) running and listening on it?"
    )


class SchemaServer:
    """One queryable on ``cell/<cell>/**/@schema`` answering for every registered key."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self._schemas: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self._session = session
        self._queryable: zenoh.Queryable[None] | None = session.declare_queryable(
            f"{prefix}/**/{SCHEMA_SUFFIX}", self._on_query
        )

    def register(self, key: str, schema_json: bytes, *, announce: bool = True) -> None:
        with self._lock:
            self._schemas[key] = schema_json
        if announce:  # once per key, for subscribers already listening
            self._session.put(schema_key(key), schema_json, encoding=JSON_ENCODING)

    def _on_query(self, query: zenoh.Query) -> None:
        with self._lock:
            items = list(self._schemas.items())
        for key, data in items:
            skey = schema_key(key)
            if zenoh.KeyExpr(skey).intersects(query.key_expr):
                query.reply(skey, data, encoding=JSON_ENCODING)

    def close(self) -> None:
        q, self._queryable = self._queryable, None
        if q is not None:
            q.undeclare()


class ChannelPublisher:
    """Publishes columnar batches on one key, numbering them (``batch_seq``)."""

    def __init__(
        self,
        session: zenoh.Session,
        schema: StreamSchema,
        *,
        congestion: str = "block",
        schemas: SchemaServer | None = None,
    ) -> None:
        self.schema = schema
        self.key = schema.key
        self.batch_seq = 0
        self.messages = 0
        self.bytes = 0
        self.put_errors = 0  # puts that raised (their batch_seq is skipped on the wire)
        #: messages put while no subscriber matched the key anywhere zenoh could see
        #: (none listening, or the router out of reach): sent to nobody
        self.unmatched = 0
        self._pub: zenoh.Publisher | None = session.declare_publisher(
            self.key, encoding=DATA_ENCODING, congestion_control=CONGESTION[congestion]
        )
        # kept up to date by zenoh's thread: a flag read per put instead of a call
        # (zenoh 1.10's stub says bool; it returns a MatchingStatus)
        status: Any = self._pub.matching_status
        self._matching = bool(getattr(status, "matching", status))
        self._matching_listener: Any = self._pub.declare_matching_listener(self._on_matching)
        if schemas is not None:
            schemas.register(self.key, schema.dumps())

    def _on_matching(self, status: Any) -> None:
        self._matching = bool(status.matching)

    def publish(self, columns: dict[str, Any]) -> bytes:
        """Encode and put one batch; returns the payload (for the recorder)."""
        payload = encode(self.schema, columns, self.batch_seq)
        self.put(payload)
        self.batch_seq += 1
        return payload

    def publish_slices(self, columns: dict[str, Any], step: int) -> list[bytes]:
        """Encode and put consecutive batches of at most ``step`` samples; returns every
        payload, sent or not. A failed put still uses up its ``batch_seq`` (subscribers
        count the hole as a lost batch) and is counted in ``put_errors``; the remaining
        slices are still sent. Raises the first put error after trying them all (the
        caller records the payloads regardless)."""
        payloads = encode_slices(self.schema, columns, self.batch_seq, step)
        if self._pub is None:
            self.batch_seq += len(payloads)
            self.put_errors += len(payloads)
            raise PublishError(payloads, TransportError(f"publisher {self.key} is closed"))
        put = self._pub.put
        error: Exception | None = None
        failed = failed_bytes = 0
        for p in payloads:  # per message nothing but the put (a try costs nothing in 3.11)
            try:
                put(p)
            except Exception as exc:  # this one is lost; the rest are still tried
                failed += 1
                failed_bytes += len(p)
                error = error or exc
        self.put_errors += failed
        if not self._matching:
            self.unmatched += len(payloads) - failed
        self.batch_seq += len(payloads)
        self.messages += len(payloads) - failed
        self.bytes += sum(map(len, payloads)) - failed_bytes
        if error is not None:
            raise PublishError(payloads, error) from error
        return payloads

    def put(self, payload: bytes) -> None:
        if self._pub is None:
            raise TransportError(f"publisher {self.key} is closed")
        self._pub.put(payload)
        if not self._matching:
            self.unmatched += 1
        self.messages += 1
        self.bytes += len(payload)

    def close(self) -> None:
        pub, self._pub = self._pub, None
        listener, self._matching_listener = self._matching_listener, None
        if listener is not None:
            listener.undeclare()
        if pub is not None:
            pub.undeclare()


def _schema_replies(
    session: zenoh.Session, key_expr: str, timeout_s: float
) -> Iterator[tuple[str, bytes]]:
    """(data key, schema JSON) of each reply to ``get(<key_expr>/@schema)``."""
    for reply in session.get(schema_key(key_expr), timeout=timeout_s):
        if reply.ok is not None:
            key = str(reply.ok.key_expr).removesuffix("/" + SCHEMA_SUFFIX)
            yield key, reply.ok.payload.to_bytes()


def fetch_schema(session: zenoh.Session, key: str, timeout_s: float = 2.0) -> StreamSchema:
    """Ask the network for the schema of ``key`` (``get(<key>/@schema)``)."""
    for _, data in _schema_replies(session, key, timeout_s):
        return StreamSchema.loads(data)
    raise SchemaError(f"no schema answered for {key!r} within {timeout_s}s")


def fetch_schemas(
    session: zenoh.Session, key_expr: str, timeout_s: float = 2.0
) -> dict[str, StreamSchema]:
    """Every schema the network has under ``key_expr`` (``get(<key_expr>/@schema)``), by
    key; empty if none answers. Subscribers ask this *before* declaring their subscriber
    (see :class:`Receiver`)."""
    out: dict[str, StreamSchema] = {}
    try:
        for key, data in _schema_replies(session, key_expr, timeout_s):
            try:
                out[key] = StreamSchema.loads(data)
            except SchemaError as exc:
                log.warning("bad schema for %s: %s", key, exc)
    except Exception as exc:  # a key expression zenoh cannot extend: ask per key later
        log.debug("schema prefetch for %s failed: %s", key_expr, exc)
    return out


@dataclass(frozen=True)
class Received:
    """One decoded batch: its key, header, columns and host UTC ns at reception."""

    key: str
    header: Header
    columns: dict[str, NDArray[Any]]
    t_recv_ns: int
    schema: StreamSchema
    #: the message as received (what a recorder writes)
    payload: bytes = b""


_NEEDS_SCHEMA = object()  # Receiver._decode: the schema must be fetched first

#: Receivers not closed yet: closed when the interpreter shuts down. zenoh-python runs a
#: subscriber's Python callback on a non-daemon thread of its own, which the interpreter
#: waits for before exit: a script that received and returned without close() never ended.
_OPEN_RECEIVERS: weakref.WeakSet[Receiver] = weakref.WeakSet()


def _close_open_receivers() -> None:
    for receiver in list(_OPEN_RECEIVERS):
        try:
            receiver.close()
        except Exception:  # the session may be gone already: exit anyway
            logging.getLogger(__name__).debug("receiver close at exit", exc_info=True)


# before the interpreter joins its non-daemon threads (atexit would come after: too late);
# the hook concurrent.futures uses for its workers
getattr(threading, "_register_atexit", atexit.register)(_close_open_receivers)


class Receiver:
    """Subscribes to a key expression and decodes columnar batches (schemas fetched once).

    zenoh's callback thread hands samples to the caller's thread through a queue the
    caller blocks on, so an idle wait costs no CPU and a sample wakes it at once (polling
    a ``FifoChannel`` every 0.2 ms cost 0.06 core idle, and at 3 kHz of small messages
    0.175 core against 0.133 and a p50 of 0.32 ms against 0.21 ms). At most ``capacity``
    samples wait: beyond that the callback waits too, which holds zenoh back, as a full
    ``FifoChannel`` would. Non-columnar samples on the key expression (health JSON) are
    passed to ``on_other`` if given, else skipped.

    The schemas under ``key_expr`` are asked for *before* the subscriber is declared. A
    schema ``get`` issued on the first data message instead, while the subscription was
    a few ms old, coincided with 1-2 messages missing right after the first one received
    (zenoh 1.10: in 7 of ~65 subscriptions joining a running 3 kHz stream right after a
    throughput benchmark, 0 of 20 without one; 0 of 25 after one with the schemas asked
    first). A key that appears later is still fetched on its first message.

    With ``on_batch``, each batch is decoded and handed to it on zenoh's callback thread
    instead (``receive`` then has nothing to return): no queue, no second thread to wake
    per message. ``on_batch`` must be quick, since zenoh waits for it (which is the
    back-pressure), and is called for one message at a time. Samples of a key whose schema
    must be fetched first, and all after them, wait in a backlog (at most ``capacity``)
    that a thread of the Receiver's own delivers in order. Measured on the 3 x 1 kHz cell,
    both on one daemon at once: p50 0.1-0.3 ms and p99 up to a third lower than through
    the queue, level with a minimal subscriber (docs/daq.md "Speed").
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str | tuple[str, ...] | list[str],
        *,
        capacity: int = 65536,
        on_other: Callable[[zenoh.Sample], None] | None = None,
        on_batch: Callable[[Received], None] | None = None,
        prefetch_schemas: bool = True,
    ) -> None:
        self._session = session
        _OPEN_RECEIVERS.add(self)
        self._schemas: dict[str, StreamSchema] = {}
        # several key expressions: one subscriber each, into the same queue or callback
        # (the exact keys of a few streams instead of a wildcard that brings others too)
        exprs = (key_expr,) if isinstance(key_expr, str) else tuple(key_expr)
        if prefetch_schemas:
            for expr in exprs:
                self._schemas.update(fetch_schemas(session, expr))
        # (sample, host UTC ns when zenoh handed it over)
        self._queue: queue.SimpleQueue[tuple[zenoh.Sample, int]] = queue.SimpleQueue()
        self._capacity = capacity
        self._closed = False
        self._on_other = on_other
        self._on_batch = on_batch
        self._one_at_a_time = threading.Lock()  # zenoh may call back from several threads
        # push mode: samples waiting for a schema (and those after them, to keep order)
        self._backlog: collections.deque[tuple[zenoh.Sample, int]] = collections.deque()
        self._backlog_ready = threading.Event()
        self.undecodable = 0
        push = self._push
        self._drainer: threading.Thread | None = None
        if on_batch is not None:
            push = self._hand_over
            self._drainer = threading.Thread(target=self._drain, name="receiver-backlog")
            self._drainer.daemon = True
            self._drainer.start()
        self._subs = [
            session.declare_subscriber(expr, zenoh.handlers.Callback(push)) for expr in exprs
        ]
        self._sub: Any = self._subs[0] if self._subs else None

    def _push(self, sample: zenoh.Sample) -> None:
        # zenoh's callback thread: a full queue waits for the reader (back-pressure)
        t_recv = time.time_ns()
        while self._queue.qsize() >= self._capacity and not self._closed:
            time.sleep(0.0005)
        self._queue.put((sample, t_recv))

    def _hand_over(self, sample: zenoh.Sample) -> None:
        # zenoh's callback thread, push mode: decode and deliver here, unless the schema
        # must be fetched first: a query waited for on this thread would wait for its
        # own reply, so that sample and every one after it go to the backlog thread
        t_recv = time.time_ns()
        assert self._on_batch is not None
        while len(self._backlog) >= self._capacity and not self._closed:
            time.sleep(0.0005)  # a schema that never comes: hold zenoh back, as _push does
        with self._one_at_a_time:
            if self._closed:
                return
            if not self._backlog:
                got = self._decode(sample, t_recv, fetch=False)
                if got is not _NEEDS_SCHEMA:
                    if got is not None:
                        self._on_batch(got)  # type: ignore[arg-type]
                    return
            self._backlog.append((sample, t_recv))
            self._backlog_ready.set()

    def _drain(self) -> None:
        # push mode's backlog, in arrival order: fetch the schema with no lock held, then
        # deliver under the lock (the callback thread meanwhile only appends)
        assert self._on_batch is not None
        while not self._closed:
            if not self._backlog_ready.wait(0.1):
                continue
            with self._one_at_a_time:
                if not self._backlog:
                    self._backlog_ready.clear()
                    continue
                sample, t_recv = self._backlog[0]
            self._fetch_schema_for(sample)
            with self._one_at_a_time:
                if self._closed:
                    return
                self._backlog.popleft()
                got = self._decode(sample, t_recv, fetch=False)
                if got is _NEEDS_SCHEMA:  # the fetch failed (and said why)
                    self.undecodable += 1
                elif got is not None:
                    self._on_batch(got)  # type: ignore[arg-type]

    def _fetch_schema_for(self, sample: zenoh.Sample) -> None:
        if not str(sample.encoding).endswith(ENCODING_NAME):
            return  # health JSON and the like: no schema to ask for
        key = str(sample.key_expr)
        try:
            known = self._schemas.get(key)
            if known is None or read_header(sample.payload.to_bytes()).schema_id != known.schema_id:
                self._schemas[key] = fetch_schema(self._session, key)
        except SchemaError as exc:
            log.warning("cannot decode %s: %s", key, exc)

    @property
    def pending(self) -> int:
        """Samples received but not handed over yet (push mode: waiting for a schema)."""
        return len(self._backlog) if self._on_batch is not None else self._queue.qsize()

    def schema(self, key: str) -> StreamSchema:
        s = self._schemas.get(key)
        if s is None:
            s = self._schemas[key] = fetch_schema(self._session, key)
        return s

    def _decode(
        self, sample: zenoh.Sample, t_recv: int | None = None, fetch: bool = True
    ) -> Received | object | None:
        """The decoded batch; None for other samples (given to ``on_other``) and for
        undecodable ones (counted); ``_NEEDS_SCHEMA`` if ``fetch`` is False and the key's
        schema is unknown or stale."""
        if t_recv is None:
            t_recv = time.time_ns()
        enc = str(sample.encoding)
        if not enc.endswith(ENCODING_NAME):
            if self._on_other is not None:
                self._on_other(sample)
            return None
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        try:
            schema = self._schemas.get(key)
            if schema is None or read_header(payload).schema_id != schema.schema_id:
                if not fetch:
                    return _NEEDS_SCHEMA
                self._schemas.pop(key, None)  # unknown, or the schema changed: (re)fetch
                schema = self.schema(key)
            header, cols = decode(schema, payload)
        except SchemaError as exc:
            self.undecodable += 1
            log.warning("cannot decode %s: %s", key, exc)
            return None
        return Received(key, header, cols, t_recv, schema, payload)

    def receive(self, timeout_s: float) -> Received | None:
        """The next decoded batch, or None after ``timeout_s`` without one."""
        if self._on_batch is not None:
            raise RuntimeError("this Receiver hands its batches to on_batch; receive() has none")
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                sample, t_recv = self._queue.get_nowait()
            except queue.Empty:
                left = deadline - time.monotonic()
                if left <= 0 or self._sub is None:
                    return None
                try:
                    sample, t_recv = self._queue.get(timeout=left)
                except queue.Empty:
                    return None
            got = self._decode(sample, t_recv)
            if got is not None:
                return got  # type: ignore[return-value]

    def __iter__(self) -> Iterator[Received]:
        while self._sub is not None:
            got = self.receive(0.1)
            if got is not None:
                yield got

    def close(self) -> None:
        subs, self._subs, self._sub = self._subs, [], None
        self._closed = True  # a callback waiting for room gives up
        for sub in subs:
            sub.undeclare()
        with self._one_at_a_time:  # a batch being handed over is finished with
            pass
        if self._drainer is not None:  # not left inside a zenoh query at exit (that aborts)
            self._drainer.join(timeout=5.0)  # a schema fetch waits at most 2 s


#: test hook (docs/deployment.md, "Faults"): seconds added to :func:`utc_offset_ns`, as
#: if this host's clock were that far off (its stamps and daq.host_clock's reads shift)
CLOCK_SHIFT_ENV = "DAQ_TEST_CLOCK_SHIFT_S"


def utc_offset_ns() -> int:
    """``time.time_ns() - time.monotonic_ns()`` now (median of a few reads), plus the
    test hook's shift (``$DAQ_TEST_CLOCK_SHIFT_S`` seconds; unset: none)."""
    reads = []
    for _ in range(5):
        a = time.monotonic_ns()
        u = time.time_ns()
        b = time.monotonic_ns()
        reads.append(u - (a + b) // 2)
    return int(np.median(reads)) + clock_shift_ns()


def clock_shift_ns() -> int:
    """The test hook's shift in ns (0 when unset); a value that is not a finite number
    of seconds is refused, naming the variable."""
    raw = os.environ.get(CLOCK_SHIFT_ENV, "").strip()
    if not raw:
        return 0
    try:
        shift = float(raw)
    except ValueError:
        shift = math.nan
    if not math.isfinite(shift):
        raise ConfigError(f"${CLOCK_SHIFT_ENV}: expected seconds, got {raw!r}")
    return round(shift * 1e9)
