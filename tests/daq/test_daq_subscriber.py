"""The subscriber side: ``Receiver`` hands samples over without polling and holds zenoh
back when its queue is full; ``daq echo``'s per-key statistics give the same counts on
the one-sample fast path as on the general path; latency series stay bounded."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import daq.echo as echo
from daq.bus import _NEEDS_SCHEMA, ChannelPublisher, Receiver, SchemaServer, open_session
from daq.columnar import Column, StreamSchema
from daq.echo import KeyStats, LatencySeries
from daq.testing import free_port, loopback_sink, loopback_source

KEY = "cell/s/robot/r/dev/ch"
SCHEMA = StreamSchema(
    KEY,
    (
        Column("seq", "uint64"),
        Column("epoch", "int32"),
        Column("t_mapped_ns", "int64", unit="ns", clock="host_utc"),
        Column("t_mapped_ok", "uint8"),
    ),
)


def _cols(seq: list[int], epoch: list[int], t: list[int], ok: list[int]) -> dict[str, np.ndarray]:
    return {
        "seq": np.array(seq, np.uint64),
        "epoch": np.array(epoch, np.int32),
        "t_mapped_ns": np.array(t, np.int64),
        "t_mapped_ok": np.array(ok, np.uint8),
    }


def test_receiver_gets_every_message_in_order_through_a_full_queue():
    """capacity 4 against 200 messages sent at once: the callback waits for room, so
    nothing is dropped and order holds; an idle receive returns None after its timeout."""
    port = free_port()
    src = open_session(loopback_source(port))
    dst = open_session(loopback_sink(port))
    try:
        schemas = SchemaServer(src, "cell/s")
        pub = ChannelPublisher(src, SCHEMA, schemas=schemas)
        recv = Receiver(dst, "cell/s/**", capacity=4)
        time.sleep(0.5)  # subscription known to the publisher's session
        for k in range(200):
            pub.publish(_cols([k], [0], [k], [1]))
        got = []
        t_end = time.monotonic() + 20
        while len(got) < 200 and time.monotonic() < t_end:
            r = recv.receive(0.5)
            if r is not None:
                got.append(int(r.columns["seq"][0]))
                time.sleep(0.001)  # a slow reader: the queue fills
        assert got == list(range(200))
        t0 = time.monotonic()
        assert recv.receive(0.2) is None
        assert 0.15 <= time.monotonic() - t0 < 2.0
        recv.close()
        assert recv.receive(0.0) is None
    finally:
        dst.close()
        src.close()


def test_push_mode_delivers_in_order_across_schema_fetches(monkeypatch):
    """``on_batch`` on zenoh's thread: the first messages (schema not asked for yet) and
    those after a schema change wait in the backlog while it is fetched; every message
    arrives once, in order, decoded with the schema it was sent with. A JSON sample
    (health) in the backlog goes to ``on_other`` in its place, with no schema query."""
    import daq.bus as bus

    asked: list[str] = []
    real_fetch = bus.fetch_schema
    monkeypatch.setattr(bus, "fetch_schema", lambda s, key: asked.append(key) or real_fetch(s, key))
    port = free_port()
    src = open_session(loopback_source(port))
    dst = open_session(loopback_sink(port))
    wider = StreamSchema(KEY, (*SCHEMA.columns, Column("x", "float64")))
    got: list[tuple[int, int]] = []
    threads: set[str] = set()

    def on_batch(r):
        threads.add(threading.current_thread().name)
        got.append((int(r.columns["seq"][0]), len(r.columns)))

    def on_other(sample):
        got.append((-1, len(sample.payload.to_bytes())))

    class SlowToDrain(Receiver):
        """Messages keep coming after a fetch, before the backlog is delivered."""

        def _fetch_schema_for(self, sample):
            fetching = self._decode(sample, fetch=False) is _NEEDS_SCHEMA
            super()._fetch_schema_for(sample)
            if fetching:
                time.sleep(0.1)

    try:
        schemas = SchemaServer(src, "cell/s")
        pub = ChannelPublisher(src, SCHEMA, schemas=schemas)
        recv = SlowToDrain(
            dst, "cell/s/**", on_batch=on_batch, on_other=on_other, prefetch_schemas=False
        )
        time.sleep(0.5)  # subscription known to the publisher's session
        for k in range(100):
            pub.publish(_cols([k], [0], [k], [1]))
            if k == 3:  # while the backlog waits for the first schema
                src.put("cell/s/robot/r/dev/health", b'{"ok": 1}', encoding=bus.JSON_ENCODING)
            time.sleep(0.002)
            if k == 70:
                time.sleep(0.5)  # the backlog drains: the rest go straight to on_batch
        time.sleep(0.3)
        pub.close()
        pub = ChannelPublisher(src, wider, schemas=schemas)  # same key, new columns
        pub.batch_seq = 100
        for k in range(100, 200):
            pub.publish(_cols([k], [0], [k], [1]) | {"x": np.array([0.5])})
            time.sleep(0.002)
        t_end = time.monotonic() + 20
        while sum(g[0] >= 0 for g in got) < 200 and time.monotonic() < t_end:
            time.sleep(0.05)
        recv.close()
        assert got[4] == (-1, 9)  # the health sample, in its place
        got = [g for g in got if g[0] >= 0]  # (and the new schema's announcement)
        assert [g[0] for g in got] == list(range(200))
        assert {g[1] for g in got[:100]} == {4} and {g[1] for g in got[100:]} == {5}
        assert recv.undecodable == 0
        assert asked == [KEY, KEY]  # the first schema and the changed one, nothing else
        assert "receiver-backlog" in threads and len(threads) >= 2  # both paths were used
        with pytest.raises(RuntimeError, match="on_batch"):
            recv.receive(0.1)
    finally:
        dst.close()
        src.close()


def test_echo_stops_with_the_error_its_output_raised():
    """Batches are handled on zenoh's thread, which would only log an exception: a jsonl
    output that fails ends ``run_echo`` with that error, long before its duration."""

    class FullDisk:
        def write(self, text: str) -> int:
            raise OSError(28, "No space left on device")

    port = free_port()
    src = open_session(loopback_source(port))
    result: list[BaseException | None] = []

    def echo_thread() -> None:
        try:
            echo.run_echo("cell/s/**", loopback_sink(port), duration_s=30.0, jsonl=FullDisk())
            result.append(None)
        except BaseException as exc:
            result.append(exc)

    try:
        pub = ChannelPublisher(src, SCHEMA, schemas=SchemaServer(src, "cell/s"))
        th = threading.Thread(target=echo_thread, daemon=True)
        t0 = time.monotonic()
        th.start()
        k = 0
        while th.is_alive() and time.monotonic() - t0 < 20:  # bounded by time
            pub.publish(_cols([k], [0], [k], [1]))
            k += 1
            time.sleep(0.01)
        th.join(5)
        assert result and isinstance(result[0], OSError) and result[0].errno == 28
        assert time.monotonic() - t0 < 20
    finally:
        src.close()


def test_close_releases_a_callback_waiting_for_room():
    rec = Receiver.__new__(Receiver)  # the queue logic alone, no session
    import queue

    rec._queue = queue.SimpleQueue()
    rec._capacity = 1
    rec._closed = False
    rec._push("a")
    done = threading.Event()
    th = threading.Thread(target=lambda: (rec._push("b"), done.set()), daemon=True)
    th.start()
    assert not done.wait(0.1)  # full: the second push waits
    rec._closed = True
    assert done.wait(2.0)


def test_push_mode_backlog_is_bounded():
    """A full backlog (a schema that does not come) holds zenoh's thread back instead of
    growing; closing releases it."""
    import collections

    rec = Receiver.__new__(Receiver)  # the hand-over logic alone, no session
    rec._capacity = 1
    rec._closed = False
    rec._on_batch = lambda got: None
    rec._one_at_a_time = threading.Lock()
    rec._backlog = collections.deque([("waiting", 0)])
    rec._backlog_ready = threading.Event()
    done = threading.Event()
    th = threading.Thread(target=lambda: (rec._hand_over("next"), done.set()), daemon=True)
    th.start()
    assert not done.wait(0.1)  # full: the callback waits
    assert len(rec._backlog) == 1
    rec._closed = True
    assert done.wait(2.0)
    assert len(rec._backlog) == 1  # closed: nothing more is queued


def test_latency_series_grows_and_stays_bounded(monkeypatch):
    monkeypatch.setattr(echo, "LATENCY_KEEP", 10_000)
    s = LatencySeries()
    for k in range(3000):
        s.add_one(k, 0)
    s.add(np.arange(3000, 9000, dtype=np.int64), 0)
    assert np.array_equal(s.values(), np.arange(9000))
    s.add(np.arange(9000, 12000, dtype=np.int64), 0)  # only 1000 fit
    s.add_one(-1, 0)
    assert s.n == 10_000 and np.array_equal(s.values(), np.arange(10_000))


def test_latency_windows_follow_receive_time_aligned_to_utc(monkeypatch):
    s = LatencySeries()
    assert s.windows(10) == []
    sec = 1_000_000_000
    base = 1_763_860_000 * sec  # a multiple of 10 s
    s.add_one(1_000_000, base + sec // 2)  # 1 ms, in [base, base + 10 s)
    s.add(np.array([2_000_000, 9_000_000]), base + 9 * sec)  # same window, next second
    s.add_one(4_000_000, base + 10 * sec)  # the next window starts exactly here
    s.add_one(7_000_000, base + 25 * sec)  # a window with nothing before it skipped
    w = s.windows(10)
    assert [x["t_s"] for x in w] == [base // sec, base // sec + 10, base // sec + 20]
    assert [x["n"] for x in w] == [3, 1, 1]
    assert w[0]["max"] == pytest.approx(9.0) and w[0]["p50"] == pytest.approx(2.0)
    assert w[0]["p99"] == pytest.approx(np.percentile([1.0, 2.0, 9.0], 99))
    assert w[2]["p99"] == pytest.approx(7.0)
    one = s.windows(1)  # per second: 4 seconds had values
    assert [x["n"] for x in one] == [1, 2, 1, 1]
    # values past LATENCY_KEEP are not kept: their windows are left out, not empty
    monkeypatch.setattr(echo, "LATENCY_KEEP", s.n)
    s.add_one(5_000_000, base + 40 * sec)
    assert [x["t_s"] for x in s.windows(10)][-1] == base // sec + 20


def test_summary_windows_only_when_asked():
    s = KeyStats()
    s.add(SimpleNamespace(n_samples=1, batch_seq=0), _cols([1], [0], [0], [1]), 10**9)
    assert "latency_mapped_ms_windows" not in s.summary()
    w = s.summary(window_s=5)["latency_mapped_ms_windows"]
    assert w == [{"t_s": 0, "n": 1, "p50": 1000.0, "p99": 1000.0, "max": 1000.0}]


@pytest.mark.parametrize("bad", ["0", "-3", "1.5", "ten"])
def test_echo_stats_window_takes_whole_seconds_only(bad, capsys):
    from daq.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["echo", "--stats", "--stats-window", bad])
    err = capsys.readouterr().err
    assert "--stats-window" in err and repr(bad) in err
    assert build_parser().parse_args(["echo", "--stats-window", "10"]).stats_window == 10


def _general(stats: KeyStats, header: SimpleNamespace, cols: dict, t_recv: int) -> None:
    """The vectorised path, even for one sample."""
    orig = KeyStats._add_one
    try:
        KeyStats._add_one = lambda self, c, t: False  # type: ignore[method-assign]
        stats.add(header, cols, t_recv)
    finally:
        KeyStats._add_one = orig  # type: ignore[method-assign]


# one-sample messages: seq step (0 = repeat, 1 = next, more = gap), epoch bump, time
# step (may go back), settled flag
_message = st.tuples(
    st.integers(-1, 3),
    st.booleans(),
    st.sampled_from([-5, -1, 0, 1, 1000]),
    st.booleans(),
    st.booleans(),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(_message, min_size=1, max_size=40))
def test_one_sample_fast_path_counts_like_the_general_path(msgs):
    fast, slow = KeyStats(), KeyStats()
    seq, ep, t = 100, 0, 10**15
    for bseq, (dseq, bump, dt, ok, lost_batch) in enumerate(msgs):
        ep += bump
        seq = max(0, seq + dseq)
        t += dt
        h = SimpleNamespace(n_samples=1, batch_seq=2 * bseq if lost_batch else bseq)
        cols = _cols([seq], [ep], [t], [int(ok)])
        t_recv = t + 1000 + bseq
        fast.add(h, cols, t_recv)
        _general(slow, h, cols, t_recv)
    for f in (*KeyStats.COUNTED, "last_epoch", "last_t_mapped"):
        assert getattr(fast, f) == getattr(slow, f), f
    assert np.array_equal(fast.lat_mapped.values(), slow.lat_mapped.values())


def test_summary_reports_latency_of_settled_samples_only():
    s = KeyStats()
    s.add(SimpleNamespace(n_samples=2, batch_seq=0), _cols([1, 2], [0, 0], [0, 0], [0, 1]), 10**6)
    s.add(SimpleNamespace(n_samples=1, batch_seq=1), _cols([3], [0], [0], [1]), 3 * 10**6)
    out = s.summary()
    assert out["unsettled"] == 1 and out["latency_mapped_ms"]["n"] == 2
    assert out["latency_mapped_ms"]["max"] == pytest.approx(3.0)
