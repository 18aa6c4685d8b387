"""Helpers for tests and benchmarks: free loopback ports, loopback zenoh configs, and an
in-process fake device that speaks the driver interface (no wire, no sim)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from daq.config import ZenohConfig
from drivers.base import BatchSchema, ChannelSchema, Driver, SampleBatch
from edges.channel_names import GRATING, counts_column


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def daq_cli(*args: str, **kw: Any) -> subprocess.Popen[str]:
    """``python -m daq.cli ARGS`` with text stdout and stderr pipes (extra Popen ``kw``)."""
    return subprocess.Popen(
        [sys.executable, "-m", "daq.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def child_pids(pid: int) -> list[int]:
    """The process ids of ``pid``'s children (Linux: ``/proc/<pid>/task/*/children``)."""
    kids: list[int] = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/children", encoding="ascii") as fh:
                kids += [int(k) for k in fh.read().split()]
        except OSError:  # the thread ended meanwhile
            continue
    return kids


def loopback_source(port: int) -> ZenohConfig:
    """Peer listening on 127.0.0.1:port only, no scouting, no shared memory."""
    return ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",), connect=())


def loopback_sink(port: int) -> ZenohConfig:
    """Peer connecting to 127.0.0.1:port, listening nowhere, no scouting."""
    return ZenohConfig(listen=(), connect=(f"tcp/127.0.0.1:{port}",))


def _counts_schema(kind: str, n_joints: int) -> BatchSchema:
    """A fake device's schema: one grating count per joint, a valid bit."""
    return BatchSchema(
        kind=kind,
        channels=tuple(
            ChannelSchema(counts_column(GRATING, i + 1), "count", "int64", f"joint {i + 1}")
            for i in range(n_joints)
        ),
        status_bits={1: "valid"},
        device_clock="fake µs clock",
        source="in-process",
    )


FAKE_SCHEMA = _counts_schema("fake", 3)


# read-only constants, sliced per read: contiguous like a real driver's arrays (a
# broadcast status would cost the encoder a slow copy with an inner loop of 3)
_ZEROS_I32 = np.zeros(1 << 16, np.int32)
_VALID = np.ones((1 << 16, 3), np.uint16)
_ZEROS_I32.flags.writeable = False
_VALID.flags.writeable = False


class FakeDriver(Driver):
    """A device sampling at ``rate_hz`` on its own drifting µs clock, in process.

    Samples are latched at host monotonic times ``t0 + k / rate``; the device clock reads
    ``start_us + (t - t0)·1e6·(1 + ppm·1e-6)``. Values are ``k`` in every channel, so
    tests can check continuity. ``max_read`` caps the samples one read returns (a source
    faster than the daemon then builds a backlog instead of ever larger reads).
    ``away(from_s, for_s)`` makes the link fail for a while
    (the samples of that time are lost, as with an unplugged device).
    """

    kind = "fake"
    OPTIONS: ClassVar[dict[str, Any]] = {}

    def __init__(
        self,
        url: str = "fake://",
        rate_hz: float = 1000.0,
        ppm: float = 30.0,
        max_read: int | None = None,
        **kw: Any,
    ) -> None:
        super().__init__(url, **kw)
        self.rate_hz = rate_hz
        self.max_read = max_read
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
        return self.t0_ns + self._latch_offset_ns(np.asarray(seq, dtype=np.float64)).astype(
            np.int64
        )

    def _latch_offset_ns(self, k: np.ndarray) -> np.ndarray:
        """ns from t0 to the latch of samples ``k`` (float, whole numbers)."""
        return np.rint(k * (1e9 / self.rate_hz))

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
            # wake when the next sample is latched (as a device's frame would wake a read)
            next_ns = self.t0_ns + int(self.k * 1e9 / self.rate_hz) + 1
            time.sleep(max(0.0, (min(next_ns, deadline_ns) - now) / 1e9))
        if k_end <= self.k:
            return None
        if self.max_read is not None:  # a device buffer read in pieces (a backlog waits)
            k_end = min(k_end, self.k + self.max_read)
        # few numpy calls per read: the fake device's cost should stay small beside the
        # daemon's (a read at 1 kHz holds one sample); same numbers as truth_ns()
        k = np.arange(self.k, k_end, dtype=np.int64)
        self.k = k_end
        n = len(k)
        x = self._latch_offset_ns(k)  # the same latch instants as truth_ns()
        x *= 1e-3 * (1 + self.ppm * 1e-6)
        np.rint(x, out=x)
        dev_us = x.astype(np.int64)
        dev_us += self.start_us
        const = n <= len(_ZEROS_I32)
        return SampleBatch(
            FAKE_SCHEMA,
            k.view(np.uint64),
            dev_us,
            _ZEROS_I32[:n] if const else np.zeros(n, np.int32),
            np.full(n, now, np.int64),
            # large reads: read-only views (broadcast), small ones: the cheaper call
            np.broadcast_to(k[:, None], (n, 3)) if n > 64 else np.repeat(k[:, None], 3, 1),
            _VALID[:n] if const else np.ones((n, 3), np.uint16),
        )


GRATING6_SCHEMA = _counts_schema("fake_grating", 6)


class FakeGratingDriver(FakeDriver):
    """:class:`FakeDriver` with a six-joint grating box's channels (``grating1_counts`` …
    ``grating6_counts``), so the live twin takes it for the gratings: joint ``j`` reads
    ``offset_j + k`` at sample ``k`` (a slow, steady move). For latency benchmarks of the
    twin without an emulator's CPU in the way (``benchmarks.bench_daq --twin``, which
    starts it at the benchmark calibration's Home counts: ``options = { counts = [...] }``)."""

    kind = "fake_grating"

    def __init__(
        self, url: str = "fake://", counts: ArrayLike = (0, 0, 0, 0, 0, 0), **kw: Any
    ) -> None:
        super().__init__(url, **kw)
        self.counts0 = np.asarray(counts, dtype=np.int64).reshape(6)

    @property
    def schema(self) -> BatchSchema:
        return GRATING6_SCHEMA

    def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
        b = super()._read_batch(deadline_ns)
        if b is None:
            return None
        k = b.seq.view(np.int64)
        n = len(k)
        return SampleBatch(
            GRATING6_SCHEMA,
            b.seq,
            b.t_device_us,
            b.epoch,
            b.t_host_ns,
            k[:, None] + self.counts0,
            np.ones((n, 6), np.uint16),
        )


def recorded_columns(path: str | Path, key: str) -> dict[str, np.ndarray]:
    """Every column of ``key``'s columnar messages in an MCAP recording, concatenated in
    file order (a streaming read: a truncated file gives what its complete chunks hold)."""
    from daq.columnar import StreamSchema, decode
    from daq.recording_reader import read_recording

    parts: dict[str, list[np.ndarray]] = {}
    for m in read_recording(path).messages_iter({key}):
        if m.schema is None:
            raise ValueError(f"{path}: {key} has no schema")
        _, cols = decode(StreamSchema.loads(m.schema.data), m.data)
        for k, v in cols.items():
            parts.setdefault(k, []).append(v)
    return {k: np.concatenate(v) for k, v in parts.items()}
