"""Holes in a subscriber's recording: a ``batch_seq`` jump on a data key, written as a
record of its own with the reason when it can be told (docs/topics.md, "Holes").

A recorder that subscribes (``daq record``, on another host than the daemon) misses what
zenoh could not deliver: the router was down, a link dropped for longer than zenoh's
lease, the publisher's put failed. Each data message carries its key's ``batch_seq``
(docs/topics.md), so a jump of ``k + 1`` is ``k`` messages lost, end to end. The reason
comes from the two ends:

* the recorder's own session lost its router between the messages either side
  (``recorder_lost_router``, from :class:`daq.router_link.RouterLink`);
* the publisher's health documents counted messages it could not hand to a router
  (``messages_unrouted``) or whose put failed (``messages_unsent``) over the hole: their
  growth from the last document before the hole to the latest one after it. A document
  published during the hole is lost too, so the hole waits for documents after it
  (``DOCS_AFTER``, at most ``wait_s``) before it is written.

Holes of one key with no document of its publisher between them are one event as far as
the evidence can tell: the publisher's counters grew over all of them, so they share the
recorder's evidence too. A router's restart can leave, besides its long hole, a message
lost as the links come back, after the recorder had its router again; it is
``router_down`` with the rest, not ``publisher_link`` on the outage's count.

``reason``: ``router_down`` (both ends lost the router: it was down, or unreachable from
both), ``publisher_link`` (only the publisher counted unrouted messages: its link or its
side of the router), ``recorder_link`` (only the recorder lost its router),
``publish_failed`` (the publisher's puts failed), ``unknown`` (none of these: a full
queue, a subscriber too slow).
"""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass

from daq.recording_reader import HOLES_TOPIC as HOLES_TOPIC  # readers know the topic

#: MCAP channel of the hole records: its schema name, and ``daq.kind``
HOLES_SCHEMA_NAME = "daq.hole.v1"
KIND_HOLES = "holes"
HOLES_SCHEMA = {
    "title": HOLES_SCHEMA_NAME,
    "description": "Messages a subscriber's recording lacks, with the reason (docs/topics.md)",
    "type": "object",
    "properties": {
        "key": {"type": "string"},
        "first_missing": {"type": "integer"},
        "last_missing": {"type": "integer"},
        "count": {"type": "integer"},
        "t_before_ns": {"type": "integer"},
        "t_after_ns": {"type": "integer"},
        "duration_s": {"type": "number"},
        "reason": {"type": "string"},
        "recorder_lost_router": {"type": "boolean"},
        "publisher_unrouted": {"type": ["integer", "null"]},
        "publisher_unsent": {"type": ["integer", "null"]},
    },
}
#: health documents of the publisher after a hole awaited before it is written: the first
#: may carry a count the daemon passed to its worker before the router came back
DOCS_AFTER = 2


@dataclass(frozen=True)
class Hole:
    """Messages ``first_missing..last_missing`` (``batch_seq``, ``count`` of them) of
    ``key`` never arrived; ``t_before_ns``/``t_after_ns``: the recorder's UTC ns at the
    messages either side. ``publisher_unrouted``/``publisher_unsent``: the growth of the
    publisher's counters over the hole (None: its health documents do not say)."""

    key: str
    first_missing: int
    last_missing: int
    count: int
    t_before_ns: int
    t_after_ns: int
    duration_s: float
    reason: str
    recorder_lost_router: bool
    publisher_unrouted: int | None
    publisher_unsent: int | None

    def to_json(self) -> bytes:
        return json.dumps(asdict(self)).encode()


def hole_reason(lost_router: bool, unrouted: int | None, unsent: int | None) -> str:
    """The reason code of a hole from its evidence (module docstring)."""
    if unrouted and lost_router:
        return "router_down"
    if unrouted:
        return "publisher_link"
    if lost_router:
        return "recorder_link"
    if unsent:
        return "publish_failed"
    return "unknown"


@dataclass
class _Pending:
    key: str
    first: int
    last: int
    t_before: int
    t_after: int
    lost_router: bool
    base: tuple[int | None, int | None]  # the publisher's counters before the hole
    base_ns: int | None  # when that document arrived (None: none had)
    docs_after: int = 0


class HoleFinder:
    """Finds holes in the messages a recorder receives; ``router_changes``: how often the
    recorder's session lost or regained its router so far (None: it cannot tell)."""

    def __init__(
        self, router_changes: Callable[[], int] | None = None, wait_s: float = 3.0
    ) -> None:
        self._changes = router_changes
        self.wait_ns = int(wait_s * 1e9)
        self._last: dict[str, tuple[int, int, int]] = {}  # key: batch_seq, t_ns, changes
        # health key: (arrival ns, messages_unrouted, messages_unsent) of recent documents
        self._docs: dict[str, deque[tuple[int, int | None, int | None]]] = {}
        self._pending: list[_Pending] = []
        self.holes = 0
        self.messages_missing = 0

    @staticmethod
    def health_key_of(data_key: str) -> str:
        """The health key of a data key's device (``…/<device>/<channel>``)."""
        return data_key.rsplit("/", 1)[0] + "/health"

    def on_batch(self, key: str, batch_seq: int, t_ns: int) -> None:
        """A data message of ``key`` arrived at ``t_ns``."""
        changes = self._changes() if self._changes is not None else 0
        last = self._last.get(key)
        self._last[key] = (batch_seq, t_ns, changes)
        # a first message, or the sequence starting again (the publisher restarted): no hole
        if last is None or batch_seq <= last[0] + 1:
            return
        docs = self._docs.get(self.health_key_of(key))
        base: tuple[int | None, int | None] = (None, None)
        base_ns = None
        for arrived, unrouted, unsent in docs or ():
            if arrived <= last[1]:
                base, base_ns = (unrouted, unsent), arrived
        hole = _Pending(
            key, last[0] + 1, batch_seq - 1, last[1], t_ns, changes != last[2], base, base_ns
        )
        self._pending.append(hole)
        if base_ns is None:  # no publisher evidence spans it: its own stands
            return
        # one event with the key's holes since the same publisher document (module doc)
        event = [p for p in self._pending if (p.key, p.base_ns) == (key, base_ns)]
        lost = any(p.lost_router for p in event)
        for p in event:
            p.lost_router = lost

    def on_health(self, key: str, doc: object, t_ns: int) -> None:
        """A health document (parsed JSON) of health key ``key`` arrived at ``t_ns``."""
        if not isinstance(doc, dict):
            return
        counts = []
        for name in ("messages_unrouted", "messages_unsent"):
            v = doc.get(name)
            counts.append(v if isinstance(v, int) else None)
        docs = self._docs.setdefault(key, deque(maxlen=16))
        docs.append((t_ns, counts[0], counts[1]))
        for p in self._pending:
            if self.health_key_of(p.key) == key and t_ns > p.t_after:
                p.docs_after += 1

    def due(self, now_ns: int) -> list[Hole]:
        """Holes ready to write: their publisher's documents after them came, or
        ``wait_s`` passed."""
        ready = [
            p
            for p in self._pending
            if p.docs_after >= DOCS_AFTER or now_ns - p.t_after >= self.wait_ns
        ]
        self._pending = [p for p in self._pending if p not in ready]
        return [self._hole(p) for p in ready]

    def drain(self) -> list[Hole]:
        """Every hole not written yet (the recording ends)."""
        ready, self._pending = self._pending, []
        return [self._hole(p) for p in ready]

    def _hole(self, p: _Pending) -> Hole:
        docs = self._docs.get(self.health_key_of(p.key)) or deque()
        now = docs[-1] if docs and docs[-1][0] > p.t_after else None

        def growth(i: int) -> int | None:
            before, after = p.base[i], (now[i + 1] if now is not None else None)
            if after is None or before is None:  # not said before or after the hole
                return None
            return after - before

        unrouted, unsent = growth(0), growth(1)
        count = p.last - p.first + 1
        self.holes += 1
        self.messages_missing += count
        return Hole(
            key=p.key,
            first_missing=p.first,
            last_missing=p.last,
            count=count,
            t_before_ns=p.t_before,
            t_after_ns=p.t_after,
            duration_s=round((p.t_after - p.t_before) * 1e-9, 6),
            reason=hole_reason(p.lost_router, unrouted, unsent),
            recorder_lost_router=p.lost_router,
            publisher_unrouted=unrouted,
            publisher_unsent=unsent,
        )
