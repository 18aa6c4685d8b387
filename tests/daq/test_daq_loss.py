"""Nothing vanishes silently: a put that fails is counted, leaves a ``batch_seq`` hole that
subscribers count as a lost batch, and is still recorded; rows a driver holds when the
daemon stops are published."""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np

from daq.bus import Receiver, SchemaServer, open_session
from daq.config import DaqConfig, DeviceConfig
from daq.device_recording import DeviceRecording
from daq.echo import KeyStats
from daq.pipeline import DeviceStream, build_schemas
from daq.testing import FAKE_SCHEMA, FakeDriver, free_port, loopback_source
from drivers.base import SampleBatch


class ListRecorder:
    def __init__(self) -> None:
        self.messages: list[tuple[int, bytes, int]] = []  # the columnar data
        self.viewer: list[tuple[int, bytes, int]] = []  # derived viewer channels (JSON)

    def add_columnar(self, schema: Any, meta: Any = None) -> int:
        return 1

    def add_json(self, *a: Any, **kw: Any) -> int:
        return 2

    def write(self, cid: int, data: bytes, t_log: int, t_pub: int, seq: int = 0) -> None:
        (self.messages if cid == 1 else self.viewer).append((cid, data, seq))


def batch(k0: int, n: int) -> SampleBatch:
    k = np.arange(k0, k0 + n, dtype=np.int64)
    t = 1_000_000_000 + k * 1_000_000
    return SampleBatch(
        FAKE_SCHEMA,
        k.astype(np.uint64),
        5_000_000 + k * 1000,
        np.zeros(n, np.int32),
        t + 200_000,
        np.repeat(k[:, None], 3, axis=1),
        np.ones((n, 3), np.uint16),
    )


DEV = DeviceConfig(name="d1", driver="fake", url="fake://", robot="r1", rate_hz=1000.0)


def stream(
    cfg: DaqConfig,
    driver: Any,
    session: Any,
    schemas: SchemaServer,
    rec: ListRecorder,
    stop: threading.Event,
) -> DeviceStream:
    """The device stream of ``DEV`` on ``driver``, recording into ``rec``."""
    groups = build_schemas(cfg, DEV, driver.schema, 0)
    return DeviceStream(
        cfg,
        DEV,
        driver,
        session,
        schemas,
        groups=groups,
        recording=DeviceRecording(rec, cfg, DEV, [g for g, _ in groups]),  # type: ignore[arg-type]
        utc_offset_ns=0,
        stop=stop,
    )


class FailOnce:
    """Wraps a zenoh publisher; the ``fail_at``-th put raises."""

    def __init__(self, pub: Any, fail_at: int) -> None:
        self.pub, self.fail_at, self.n = pub, fail_at, 0

    def put(self, payload: bytes) -> None:
        self.n += 1
        if self.n == self.fail_at:
            raise RuntimeError("injected put failure")
        self.pub.put(payload)

    def undeclare(self) -> None:
        self.pub.undeclare()


def test_failed_put_is_counted_recorded_and_seen_as_lost_batch():
    cfg = DaqConfig()
    cfg = replace(
        cfg,
        zenoh=loopback_source(free_port()),
        publish=replace(cfg.publish, max_batch_samples=4),
    )
    session = open_session(cfg.zenoh)
    try:
        schemas = SchemaServer(session, "cell/cell1")
        rec = ListRecorder()
        st = stream(cfg, FakeDriver(), session, schemas, rec, threading.Event())
        recv = Receiver(session, "cell/**")
        time.sleep(0.2)
        pub = st.publishers[0]
        pub._pub = FailOnce(pub._pub, fail_at=3)  # message #2 (0-based) fails
        st._process([batch(0, 4)])  # batch_seq 0
        st._process([batch(4, 8)])  # batch_seq 1, 2 (the put of 2 fails)
        st._process([batch(12, 2)])  # batch_seq 3
        assert pub.batch_seq == 4
        assert st.counters.publish_errors == 1
        assert st.counters.messages_unsent == 1
        assert [s for _, _, s in rec.messages] == [0, 1, 2, 3]  # all four recorded
        health = st.health(1.0)
        assert health["publish_errors"] == 1 and health["messages_unsent"] == 1
        stats = KeyStats()
        deadline = time.monotonic() + 5
        while stats.batches < 3 and time.monotonic() < deadline:
            got = recv.receive(0.2)
            if got is not None:
                stats.add(got.header, got.columns, got.t_recv_ns)
        assert stats.batches == 3
        assert stats.lost_batches == 1  # the hole is visible at the subscriber
        assert stats.seq_gaps == 4  # and the samples it held
        recv.close()
        st.close()
        schemas.close()
    finally:
        session.close()


def test_rows_held_by_the_driver_at_stop_are_published():
    """The device thread reads once more without waiting when stopping."""
    cfg = DaqConfig()
    cfg = replace(cfg, zenoh=loopback_source(free_port()))

    class Holding(FakeDriver):
        """Returns nothing while running; its rows come out on the final read."""

        def __init__(self) -> None:
            super().__init__()
            self.held = batch(0, 7)
            self.stop: threading.Event | None = None

        def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
            if self.stop is not None and self.stop.is_set():
                b, self.held = self.held, None
                return b
            time.sleep(0.001)
            return None

    session = open_session(cfg.zenoh)
    try:
        schemas = SchemaServer(session, "cell/cell1")
        stop = threading.Event()
        drv = Holding()
        drv.stop = stop
        rec = ListRecorder()
        st = stream(cfg, drv, session, schemas, rec, stop)
        st.start()
        deadline = time.monotonic() + 5
        while st.state != "connected" and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        stop.set()
        st.join(5)
        assert st.counters.samples == 7
        assert len(rec.messages) == 1
        st.close()
        schemas.close()
    finally:
        session.close()


def test_a_source_ahead_gets_full_messages_and_the_tail_waits_for_its_age():
    """Reads larger than ``max_batch_samples`` go out as full messages only; the rest
    waits for the next read or ``max_batch_age_s``, and no sample is lost or reordered."""
    cfg = DaqConfig()
    cfg = replace(
        cfg,
        zenoh=loopback_source(free_port()),
        publish=replace(cfg.publish, max_batch_samples=100, max_batch_age_s=0.3),
    )

    class Scripted(FakeDriver):
        def __init__(self) -> None:
            super().__init__()
            self.reads = [batch(0, 250), batch(250, 130)]

        def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
            if self.reads:  # received now (the age counts from the host receive time)
                b = self.reads.pop(0)
                return replace(b, t_host_ns=np.full(len(b), time.monotonic_ns(), np.int64))
            time.sleep(0.002)
            return None

    session = open_session(cfg.zenoh)
    try:
        schemas = SchemaServer(session, "cell/cell1")
        stop = threading.Event()
        rec = ListRecorder()
        st = stream(cfg, Scripted(), session, schemas, rec, stop)
        t0 = time.monotonic()
        st.start()
        while len(rec.messages) < 3 and time.monotonic() - t0 < 5:
            time.sleep(0.005)
        full_at = time.monotonic() - t0
        sizes = [int.from_bytes(data[12:16], "little") for _, data, _ in rec.messages]
        assert sizes == [100, 100, 100]  # the 80-sample tail is held back
        while len(rec.messages) < 4 and time.monotonic() - t0 < 5:
            time.sleep(0.005)
        tail_at = time.monotonic() - t0
        stop.set()
        st.join(5)
        sizes = [int.from_bytes(data[12:16], "little") for _, data, _ in rec.messages]
        assert sizes == [100, 100, 100, 80]
        assert tail_at - full_at > 0.2  # it waited for its age (0.3 s), not for the stop
        assert [s for _, _, s in rec.messages] == [0, 1, 2, 3]
        assert st.counters.samples == 380 and st.counters.gaps == 0
        assert st.counters.seq_breaks == 0
        st.close()
        schemas.close()
    finally:
        session.close()


def test_sample_batch_slices_are_views_of_every_column():
    b = batch(10, 6)
    part = b[2:5]
    assert len(part) == 3
    assert part.seq.tolist() == [12, 13, 14]
    assert part.values[:, 0].tolist() == [12, 13, 14] and part.status.shape == (3, 3)
    assert np.shares_memory(part.t_host_ns, b.t_host_ns)
    import pytest

    with pytest.raises(TypeError, match="slices"):
        b[0]  # type: ignore[index]
