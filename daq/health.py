"""The health loop: once a period, each device stream's health document (docs/topics.md)
published on its health key and written to its recording.

The daemon runs one over the device streams in its own process; a worker process
(:mod:`daq.worker`) runs one over its one stream, and the daemon records that worker's
documents from its subscription (the process boundary). Rounds keep to a fixed grid from
the start: a late round does not delay the next ones, and a round more than a period late
starts the grid again from itself. A document's rates are over the time since the
previous round.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import zenoh

from daq.bus import JSON_ENCODING
from daq.device_recording import DeviceRecording

log = logging.getLogger(__name__)

#: the shortest period a document's rates are taken over (a last round right after one)
MIN_PERIOD_S = 1e-3


class HealthSource(Protocol):
    """What the loop asks: a device's health key, its recording (None: not recorded
    here) and its document over the last ``period_s`` seconds (which resets its window)."""

    @property
    def health_key(self) -> str: ...

    @property
    def recording(self) -> DeviceRecording | None: ...

    def health(self, period_s: float) -> dict[str, Any]: ...


class HealthLoop:
    """Publishes (and records) the health of ``add``-ed sources every ``period_s``."""

    def __init__(self, session: zenoh.Session, period_s: float) -> None:
        self.session = session
        self.period_s = period_s
        self.last: list[dict[str, Any]] = []  # the documents of the latest round
        self._sources: list[tuple[HealthSource, Any]] = []
        self._last_round = time.monotonic()

    def add(self, source: HealthSource) -> None:
        pub = self.session.declare_publisher(source.health_key, encoding=JSON_ENCODING)
        self._sources.append((source, pub))

    def run(
        self,
        stop: threading.Event,
        duration_s: float | None = None,
        on_round: Callable[[], None] | None = None,
    ) -> None:
        """Publish once a period until ``stop`` is set or ``duration_s`` has passed;
        ``on_round`` is called before each round."""
        t0 = self._last_round = time.monotonic()
        next_round = t0 + self.period_s
        while not stop.is_set():
            now = time.monotonic()
            if duration_s is not None and now - t0 >= duration_s:
                break
            wait = next_round - now
            if duration_s is not None:
                wait = min(wait, t0 + duration_s - now)
            if stop.wait(max(0.0, wait)):
                break
            now = time.monotonic()
            if now >= next_round:
                if on_round is not None:
                    on_round()
                self.publish()
                next_round += self.period_s
                if next_round < now:
                    next_round = now + self.period_s

    def publish(self) -> list[dict[str, Any]]:
        """One round now: every source's document, published and recorded."""
        now = time.monotonic()
        period_s = max(MIN_PERIOD_S, now - self._last_round)
        self._last_round = now
        docs = []
        for source, pub in self._sources:
            doc = source.health(period_s)
            data = json.dumps(doc).encode()
            try:
                pub.put(data)
            except Exception:
                log.exception("health publish failed for %s", source.health_key)
            if source.recording is not None:
                source.recording.write_health(data)
            docs.append(doc)
        self.last = docs
        return docs

    def close(self) -> None:
        for _, pub in self._sources:
            try:
                pub.undeclare()
            except Exception:  # session already closed
                log.debug("health undeclare failed", exc_info=True)
        self._sources = []
