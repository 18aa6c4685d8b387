"""How far this host's clock is from the router's: round trips over zenoh, Cristian's way.

Samples carry host timestamps (``t_host_rx_ns``, ``t_mapped_ns``: docs/topics.md), the
twin pairs the tracker's and the gratings' by time, and latencies compare clocks of
different hosts. A host whose clock is off shifts all of them by as much. So ``daq
router`` answers queries on :data:`CLOCK_KEY` with its UTC clock (:func:`serve_clock`),
and a daemon that is a client of routers asks it every ``period_s``
(:class:`HostClockWatch`): a query sent at ``t0`` and answered at ``t1`` (this host's
clock) with the router's ``t_ref`` gives

    offset = (t0 + t1) / 2 - t_ref,  uncertain by ± (t1 - t0) / 2

(the answer was made somewhere in the round trip). Of ``ROUNDS`` round trips the shortest
is kept. The offset goes into each device's health document (``host_clock``), and one
line is logged when it leaves ``tolerance_s`` (beyond its uncertainty) and one when it
is back (within it by more than its uncertainty: an estimate whose round trip was long
changes neither). The daemon measures the clock its samples are stamped with (monotonic + the UTC
offset taken at start), so a clock stepped after the start is seen too.

Test hook: ``DAQ_TEST_CLOCK_SHIFT_S`` (seconds, :func:`daq.bus.utc_offset_ns`) shifts a
daemon's stamps and the clock this watch reads, as a host clock that far off would.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import zenoh

from daq.bus import JSON_ENCODING

log = logging.getLogger(__name__)

#: the key ``daq router`` answers with its clock
CLOCK_KEY = "daq/clock"
#: round trips per estimate (the shortest kept), and how long one may take (s)
ROUNDS = 5
QUERY_TIMEOUT_S = 1.0


@dataclass(frozen=True)
class ClockOffset:
    """This host's clock minus the reference's (ms; positive: this host is ahead), ±
    ``uncertainty_ms`` (half the shortest round trip, ``rtt_ms``), measured at
    ``t_host_ns`` (this host's clock); ``within_tolerance``: \\|offset\\| − uncertainty
    ≤ the tolerance."""

    offset_ms: float
    uncertainty_ms: float
    rtt_ms: float
    reference: str
    t_host_ns: int
    within_tolerance: bool

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def serve_clock(session: zenoh.Session, name: str) -> zenoh.Queryable[None]:
    """Answer :data:`CLOCK_KEY` queries with ``{"t_utc_ns": now, "reference": name}``;
    the queryable (undeclared with the session)."""

    def answer(query: zenoh.Query) -> None:
        doc = {"t_utc_ns": time.time_ns(), "reference": name}
        query.reply(CLOCK_KEY, json.dumps(doc), encoding=JSON_ENCODING)

    return session.declare_queryable(CLOCK_KEY, answer)


def measure(
    session: zenoh.Session,
    now_ns: Callable[[], int],
    tolerance_s: float,
    rounds: int = ROUNDS,
    stop: threading.Event | None = None,
) -> ClockOffset | None:
    """One estimate of the offset (None: no reference answered, or ``stop`` was set)."""
    best: tuple[int, float, str] | None = None  # rtt ns, offset ns, reference
    for _ in range(rounds):
        if stop is not None and stop.is_set():
            return None
        t0 = now_ns()
        got: tuple[int, str] | None = None
        for reply in session.get(CLOCK_KEY, timeout=QUERY_TIMEOUT_S):
            if got is None and reply.ok is not None:
                try:
                    doc = json.loads(reply.ok.payload.to_bytes())
                    got = (int(doc["t_utc_ns"]), str(doc.get("reference", "")))
                except (ValueError, KeyError, TypeError):
                    continue
        t1 = now_ns()
        if got is None:
            continue
        rtt = t1 - t0
        if best is None or rtt < best[0]:
            best = (rtt, (t0 + t1) / 2 - got[0], got[1])
    if best is None:
        return None
    rtt, offset, ref = best
    uncertainty = rtt / 2
    return ClockOffset(
        offset_ms=round(offset / 1e6, 3),
        uncertainty_ms=round(uncertainty / 1e6, 3),
        rtt_ms=round(rtt / 1e6, 3),
        reference=ref,
        t_host_ns=now_ns(),
        within_tolerance=abs(offset) - uncertainty <= tolerance_s * 1e9,
    )


def clock_verdict(got: ClockOffset, tolerance_s: float) -> str | None:
    """``"beyond"`` the tolerance by more than the estimate's uncertainty, ``"within"`` it
    by more than that, or None: the estimate cannot tell (its round trip was too long)."""
    tol_ms = tolerance_s * 1e3
    if abs(got.offset_ms) - got.uncertainty_ms > tol_ms:
        return "beyond"
    if abs(got.offset_ms) + got.uncertainty_ms <= tol_ms:
        return "within"
    return None


class HostClockWatch:
    """Estimates this host's clock offset every ``period_s`` in a thread of its own;
    ``latest``: the newest estimate (None: none yet, or no reference answers)."""

    def __init__(
        self,
        session: zenoh.Session,
        now_ns: Callable[[], int],
        tolerance_s: float,
        period_s: float = 2.0,
    ) -> None:
        self._session = session
        self._now_ns = now_ns
        self.tolerance_s = tolerance_s
        self.period_s = period_s
        self.latest: ClockOffset | None = None
        self.warnings = 0  # times the offset left the tolerance
        self._beyond = False  # the verdict of the last conclusive estimate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="host-clock", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                got = measure(self._session, self._now_ns, self.tolerance_s, stop=self._stop)
            except Exception:  # the session is closing, or zenoh refused the query
                log.debug("host clock: no estimate", exc_info=True)
                got = None
            if got is not None:
                self._say(got)
                self.latest = got
            self._stop.wait(self.period_s)

    def _say(self, got: ClockOffset) -> None:
        # only a conclusive estimate changes the verdict: one whose round trip was long (a
        # link dropping, a router restarting) can tell neither "beyond" nor "within"
        verdict = clock_verdict(got, self.tolerance_s)
        if verdict == "beyond" and not self._beyond:
            self._beyond = True
            self.warnings += 1
            side = "ahead of" if got.offset_ms > 0 else "behind"
            log.warning(
                "this host's clock is %.1f ms %s the router's (± %.1f ms, tolerance %.0f ms): "
                "its samples' times are off by as much; set the clocks (NTP/PTP)",
                abs(got.offset_ms), side, got.uncertainty_ms, self.tolerance_s * 1e3,
            )  # fmt: skip
        elif verdict == "within" and self._beyond:
            self._beyond = False
            log.warning(
                "this host's clock is within %.0f ms of the router's again (%.1f ms)",
                self.tolerance_s * 1e3, got.offset_ms,
            )  # fmt: skip

    def doc(self) -> dict[str, Any] | None:
        """The health document's ``host_clock`` (None: no estimate yet)."""
        got = self.latest
        return got.as_dict() if got is not None else None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=QUERY_TIMEOUT_S + 0.5)  # a query in flight ends by then
