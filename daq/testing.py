"""Helpers for tests and benchmarks: free loopback ports, loopback zenoh configs, and an
in-process fake device that speaks the driver interface (no wire, no sim)."""

from __future__ import annotations

import socket
import time
from typing import Any, ClassVar

import numpy as np

from daq.config import ZenohConfig

try:  # the fake driver needs the drivers package's base classes
    from drivers.base import BatchSchema, ChannelSchema, Driver, SampleBatch
except ImportError:  # pragma: no cover - drivers is part of this repository
    Driver = object  # type: ignore[assignment,misc]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback_source(port: int) -> ZenohConfig:
    """Peer listening on 127.0.0.1:port only, no scouting, no shared memory."""
    return ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), connect=())


def loopback_sink(port: int) -> ZenohConfig:
    """Peer connecting to 127.0.0.1:port, listening nowhere, no scouting."""
    return ZenohConfig(listen=(), connect=(f"tcp/127.0.0.1:{port}",))


FAKE_SCHEMA = (
    BatchSchema(
        kind="fake",
        channels=tuple(
            ChannelSchema(f"grating{i + 1}_counts", "count", "int64", f"joint {i + 1}")
            for i in range(3)
        ),
        status_bits={1: "valid"},
        device_clock="fake µs clock",
        source="in-process",
    )
    if Driver is not object
    else None
)


class FakeDriver(Driver):  # type: ignore[misc,valid-type]
    """A device sampling at ``rate_hz`` on its own drifting µs clock, in process.

    Samples are latched at host monotonic times ``t0 + k / rate``; the device clock reads
    ``start_us + (t - t0)·1e6·(1 + ppm·1e-6)``. Values are ``k`` in every channel, so
    tests can check continuity. ``away(from_s, for_s)`` makes the link fail for a while
    (the samples of that time are lost, as with an unplugged device).
    """

    kind = "fake"
    OPTIONS: ClassVar[dict[str, Any]] = {}

    def __init__(
        self, url: str = "fake://", rate_hz: float = 1000.0, ppm: float = 30.0, **kw: Any
    ) -> None:
        super().__init__(url, **kw)
        self.rate_hz = rate_hz
        self.ppm = ppm
        self.start_us = 5_000_000
        self.t0_ns = 0
        self.k = 0
        self.away_window: tuple[float, float] | None = None

    @property
    def schema(self) -> BatchSchema:
        return FAKE_SCHEMA

    def truth_ns(self, seq: np.ndarray) -> np.ndarray:
        """Host monotonic ns at which samples ``seq`` were latched."""
        return self.t0_ns + np.rint(np.asarray(seq, dtype=np.float64) * 1e9 / self.rate_hz).astype(
            np.int64
        )

    def away(self, from_s: float, for_s: float) -> None:
        self.away_window = (from_s, for_s)

    def _is_away(self, now_ns: int) -> bool:
        if self.away_window is None or not self.t0_ns:
            return False
        t = (now_ns - self.t0_ns) / 1e9
        return self.away_window[0] <= t < self.away_window[0] + self.away_window[1]

    def _connect(self) -> None:
        from drivers.errors import DeviceIOError

        if self._is_away(time.monotonic_ns()):
            raise DeviceIOError("fake device unplugged")
        if not self.t0_ns:
            self.t0_ns = time.monotonic_ns()
        else:  # samples latched while the device was away are lost for good
            now = time.monotonic_ns()
            self.k = max(self.k, int((now - self.t0_ns) * self.rate_hz / 1e9))

    def _disconnect(self) -> None:
        pass

    def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
        from drivers.errors import DeviceIOError

        while True:
            now = time.monotonic_ns()
            if self._is_away(now):
                raise DeviceIOError("fake device unplugged")
            k_end = int((now - self.t0_ns) * self.rate_hz / 1e9) + 1
            if k_end > self.k or now >= deadline_ns:
                break
            time.sleep(min(0.0005, max(0.0, (deadline_ns - now) / 1e9)))
        if k_end <= self.k:
            return None
        k = np.arange(self.k, k_end, dtype=np.int64)
        self.k = k_end
        t_latch = self.truth_ns(k)
        dev_us = self.start_us + np.rint(
            (t_latch - self.t0_ns) * 1e-3 * (1 + self.ppm * 1e-6)
        ).astype(np.int64)
        n = len(k)
        return SampleBatch(
            FAKE_SCHEMA,
            k.astype(np.uint64),
            dev_us,
            np.zeros(n, np.int32),
            np.full(n, now, np.int64),
            np.repeat(k[:, None], 3, axis=1),
            np.ones((n, 3), np.uint16),
        )
