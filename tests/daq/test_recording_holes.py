"""The hole finder of ``daq record`` (daq.recording_holes), the daemon's report to its
workers (daq.worker.DaemonReport) and the clock test hook (daq.bus.clock_shift_ns): their
logic without processes; tests/daq/test_router_faults.py runs them for real."""

from __future__ import annotations

import json

import pytest

from daq.bus import CLOCK_SHIFT_ENV, clock_shift_ns, utc_offset_ns
from daq.errors import ConfigError
from daq.recording_holes import HoleFinder, hole_reason
from daq.worker import DaemonReport

KEY = "cell/c/robot/r/tracker/samples"
HEALTH = "cell/c/robot/r/tracker/health"
S = 1_000_000_000


def _doc(unrouted: int | None = None, unsent: int = 0) -> dict:
    doc: dict = {"device": "tracker", "messages_unsent": unsent}
    if unrouted is not None:
        doc["messages_unrouted"] = unrouted
    return doc


def test_a_router_outage_seen_from_both_ends_is_router_down_with_the_publishers_count():
    changes = [0]
    f = HoleFinder(lambda: changes[0], wait_s=3.0)
    f.on_health(HEALTH, _doc(4), 1 * S)
    for i in range(10):
        f.on_batch(KEY, i, 2 * S + i)
    changes[0] = 2  # the recorder lost its router and found it again
    f.on_batch(KEY, 35, 5 * S)  # 25 messages never came
    assert f.due(5 * S) == []  # waits for the publisher's documents after the hole
    f.on_health(HEALTH, _doc(29), 5 * S + 1)
    assert f.due(5 * S + 2) == []  # the first may be behind the daemon's count
    f.on_health(HEALTH, _doc(30), 6 * S)
    (hole,) = f.due(6 * S)
    assert (hole.first_missing, hole.last_missing, hole.count) == (10, 34, 25)
    assert hole.reason == "router_down" and hole.recorder_lost_router
    assert hole.publisher_unrouted == 26 and hole.publisher_unsent == 0
    assert hole.t_before_ns == 2 * S + 9 and hole.t_after_ns == 5 * S
    assert json.loads(hole.to_json())["count"] == 25
    assert (f.holes, f.messages_missing) == (1, 25)
    assert f.due(7 * S) == []  # written once


@pytest.mark.parametrize("outage_first", [True, False])
def test_a_message_lost_beside_a_router_outage_is_the_outages_event(outage_first: bool):
    """A router's restart seen by both ends, and one message lost just after (or before)
    while the recorder had its router: no publisher document between them, one event."""
    changes = [0]
    f = HoleFinder(lambda: changes[0], wait_s=3.0)
    f.on_health(HEALTH, _doc(4), 1 * S)
    for i in range(10):
        f.on_batch(KEY, i, 2 * S + i)
    if outage_first:
        changes[0] = 2
        f.on_batch(KEY, 40, 5 * S)  # 10..39 lost with the router
        f.on_batch(KEY, 42, 5 * S + 2_000_000)  # 41 lost as the links came back
    else:
        f.on_batch(KEY, 11, 2 * S + 20)  # 10 lost as the router went down
        changes[0] = 2
        f.on_batch(KEY, 42, 5 * S)  # 12..41 lost with the router
    f.on_health(HEALTH, _doc(33), 5 * S + 10_000_000)
    f.on_health(HEALTH, _doc(35), 6 * S)
    holes = f.due(6 * S)
    assert sum(h.count for h in holes) == 31 and len(holes) == 2
    assert {h.reason for h in holes} == {"router_down"}, holes
    assert all(h.recorder_lost_router and h.publisher_unrouted == 31 for h in holes)


def test_holes_with_a_publisher_document_between_them_are_separate_events():
    changes = [0]
    f = HoleFinder(lambda: changes[0], wait_s=3.0)
    f.on_health(HEALTH, _doc(0), 1 * S)
    f.on_batch(KEY, 0, 2 * S)
    changes[0] = 2
    f.on_batch(KEY, 5, 3 * S)  # the router's restart
    f.on_health(HEALTH, _doc(4), 3 * S + 1)
    f.on_batch(KEY, 6, 4 * S)
    f.on_batch(KEY, 8, 4 * S + 1)  # later, the publisher's link alone
    f.on_health(HEALTH, _doc(5), 4 * S + 2)
    f.on_health(HEALTH, _doc(5), 5 * S)
    f.on_health(HEALTH, _doc(5), 6 * S)
    reasons = [h.reason for h in sorted(f.due(6 * S), key=lambda h: h.first_missing)]
    assert reasons == ["router_down", "publisher_link"]


def test_without_publisher_documents_each_hole_keeps_its_own_evidence():
    changes = [0]
    f = HoleFinder(lambda: changes[0], wait_s=3.0)
    f.on_batch(KEY, 0, 0)
    changes[0] = 2
    f.on_batch(KEY, 5, S)
    f.on_batch(KEY, 7, S + 1)
    reasons = [h.reason for h in sorted(f.drain(), key=lambda h: h.first_missing)]
    assert reasons == ["recorder_link", "unknown"]


def test_reasons_from_each_end_alone_and_none():
    assert hole_reason(False, 5, 0) == "publisher_link"
    assert hole_reason(True, 0, 0) == "recorder_link"
    assert hole_reason(True, None, None) == "recorder_link"
    assert hole_reason(False, 0, 3) == "publish_failed"
    assert hole_reason(False, None, None) == "unknown"


def test_without_documents_a_hole_is_written_after_the_wait_and_at_the_end():
    f = HoleFinder(None, wait_s=1.0)
    f.on_batch(KEY, 0, 0)
    f.on_batch(KEY, 3, S)
    assert f.due(S + S // 2) == []
    (hole,) = f.due(2 * S)
    assert hole.count == 2 and hole.reason == "unknown" and hole.publisher_unrouted is None
    f.on_batch(KEY, 9, 3 * S)
    (last,) = f.drain()
    assert (last.first_missing, last.last_missing) == (4, 8)


def test_a_sequence_that_starts_again_or_repeats_is_no_hole():
    f = HoleFinder(None)
    for seq in (0, 1, 2, 0, 1, 1, 2):  # a publisher restarted; a repeat
        f.on_batch(KEY, seq, seq)
    assert f.drain() == []


def test_a_count_not_said_before_the_hole_is_not_attributed():
    f = HoleFinder(None, wait_s=10.0)
    f.on_batch(KEY, 0, 0)
    f.on_batch(KEY, 5, S)
    f.on_health(HEALTH, _doc(100), 2 * S)  # a recorder that started mid-run
    f.on_health(HEALTH, _doc(100), 3 * S)
    (hole,) = f.due(3 * S)
    assert hole.publisher_unrouted is None and hole.publisher_unsent is None
    assert hole.reason == "unknown"


def test_the_daemons_report_reaches_the_health_document():
    r = DaemonReport()
    assert r.add_to({"a": 1}) == {"a": 1}  # nothing said: nothing added
    r.read('{"messages_unrouted": 7, "host_clock": {"offset_ms": 500.0}}\n')
    r.read('{"messages_unrouted": 9}\n')  # the clock kept
    r.read("not json\n")  # ignored, logged
    assert r.add_to({}) == {"messages_unrouted": 9, "host_clock": {"offset_ms": 500.0}}


def test_the_clock_hook_shifts_the_offset_and_refuses_what_is_not_seconds(monkeypatch):
    monkeypatch.delenv(CLOCK_SHIFT_ENV, raising=False)
    base = utc_offset_ns()
    monkeypatch.setenv(CLOCK_SHIFT_ENV, "0.5")
    assert clock_shift_ns() == 500_000_000
    assert abs(utc_offset_ns() - base - 500_000_000) < 5_000_000
    for bad in ("abc", "nan", "inf"):
        monkeypatch.setenv(CLOCK_SHIFT_ENV, bad)
        with pytest.raises(ConfigError, match=rf"\${CLOCK_SHIFT_ENV}: expected seconds"):
            clock_shift_ns()


def test_a_clock_estimate_changes_the_verdict_only_when_it_is_conclusive():
    """The router restarting or a link dropping makes a round trip long: such an estimate
    (0.5 s off ± 0.47 s) can tell neither beyond nor within a 10 ms tolerance, and must
    not say "within again" (a namespace run logged exactly that once)."""
    from daq.host_clock import ClockOffset, clock_verdict

    def est(offset_ms: float, unc_ms: float) -> ClockOffset:
        return ClockOffset(offset_ms, unc_ms, 2 * unc_ms, "router", 0, True)

    assert clock_verdict(est(500.0, 0.3), 0.01) == "beyond"
    assert clock_verdict(est(-500.0, 0.3), 0.01) == "beyond"
    assert clock_verdict(est(2.0, 0.3), 0.01) == "within"
    assert clock_verdict(est(32.2, 470.0), 0.01) is None
    assert clock_verdict(est(8.0, 5.0), 0.01) is None
