"""Map a device's clock onto the host clock, online.

Each sample carries a device timestamp (ticks of the device's own oscillator) and the host
time at which the driver received it. The receive time is the latch instant plus a
transport delay that is never negative, usually small and now and then large (a busy
host, a retried frame). So the device→host relation is the *lower envelope* of the
(device, host) points, not their mean:

* points are grouped in host-time buckets and only each bucket's smallest apparent delay
  is kept (this throws away delayed samples before any fit);
* a line host = offset + rate·device is fitted to the bucket minima of a sliding window,
  and minima lying far above it (a bucket where every sample was late) are dropped by a
  median-absolute-deviation rule before the final fit;
* the device counter may wrap (``wrap_ticks``) and is unwrapped; a device that restarts
  (its clock jumps back, or stops agreeing with the host by more than
  ``restart_tolerance_s``) starts a new segment with a fresh fit, and is counted.

Mapped times therefore estimate *latch instant + minimum transport delay*; the minimum
delay of a link is a constant that a user can subtract (``latency_ns``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class ClockFitQuality:
    """How well the device clock is tracked right now (published on the health topic)."""

    offset_ns: int  # host time of device tick 0 of the current segment, per the fit
    drift_ppm: float  # device rate error: (host s per device s − 1)·1e6
    envelope_rms_ns: float  # scatter of bucket minima about the fitted line
    points: int  # bucket minima in the current fit
    restarts: int  # device restarts detected so far
    wraps: int  # counter wraps unwrapped so far
    outliers: int  # bucket minima of the current window rejected as late


class DeviceClockMap:
    """Online, outlier-robust map from device ticks to host nanoseconds.

    ``tick_s`` is the nominal length of one device tick (1e-6 for a µs clock).
    """

    def __init__(
        self,
        *,
        tick_s: float = 1e-6,
        wrap_ticks: int | None = None,
        window_s: float = 60.0,
        bucket_s: float = 0.25,
        restart_tolerance_s: float = 0.5,
        latency_ns: int = 0,
    ) -> None:
        if tick_s <= 0 or window_s <= 0 or bucket_s <= 0:
            raise ValueError("tick_s, window_s and bucket_s must be positive")
        self.tick_s = tick_s
        self.wrap_ticks = wrap_ticks
        self.window_ns = int(window_s * 1e9)
        self.bucket_ns = int(bucket_s * 1e9)
        self.restart_tolerance_ns = int(restart_tolerance_s * 1e9)
        self.latency_ns = int(latency_ns)
        self.restarts = 0
        self.wraps = 0
        self._reset_segment()

    def _reset_segment(self) -> None:
        self._last_raw: int | None = None
        self._last_dev = 0
        self._wrap_base = 0
        self._dev0: int | None = None  # unwrapped tick of the segment origin
        self._host0 = 0
        # bucket index -> (device s since dev0, apparent delay s) of the lowest point
        self._buckets: deque[tuple[int, float, float]] = deque()
        self._fit = (0.0, 1.0)  # host_s = a + b * dev_s (relative to the origins)
        self._rms_s = 0.0
        self._used = 0
        self._rejected = 0

    # -- input -----------------------------------------------------------------------
    def _unwrap(self, raw: IntArray) -> IntArray:
        """Unwrapped ticks; detects wraps inside and between batches."""
        raw = raw.astype(np.int64)
        if self.wrap_ticks is None:
            self._last_raw = int(raw[-1])
            return raw
        w = self.wrap_ticks
        prev = np.concatenate([[raw[0] if self._last_raw is None else self._last_raw], raw[:-1]])
        # a step back by more than half the range is a wrap, not a restart
        wrapped = (raw - prev) < -(w // 2)
        steps = np.cumsum(wrapped)
        self.wraps += int(steps[-1])
        out: NDArray[np.int64] = raw + (self._wrap_base + steps * w)
        self._wrap_base += int(steps[-1]) * w
        self._last_raw = int(raw[-1])
        return out

    def update(self, device_ticks: ArrayLike, host_ns: ArrayLike) -> NDArray[np.int64]:
        """Feed one batch (device ticks, host receive ns; equal shapes) and map it.

        Returns the mapped host times (ns) of the batch's samples.
        """
        dev_raw = np.asarray(device_ticks, dtype=np.int64).ravel()
        host = np.asarray(host_ns, dtype=np.int64).ravel()
        if dev_raw.shape != host.shape:
            raise ValueError("device_ticks and host_ns must have the same length")
        if dev_raw.size == 0:
            return np.empty(0, dtype=np.int64)
        dev = self._unwrap(dev_raw)
        cut = self._restart_index(dev, host)
        if cut is not None:
            head = self._absorb(dev[:cut], host[:cut]) if cut > 0 else np.empty(0, np.int64)
            self.restarts += 1
            self._reset_segment()
            dev = self._unwrap(dev_raw[cut:])
            tail = self._absorb(dev, host[cut:])
            return np.concatenate([head, tail])
        return self._absorb(dev, host)

    def _restart_index(self, dev: IntArray, host: IntArray) -> int | None:
        """Index of the first sample of a new device run, if the device restarted."""
        if self._dev0 is None:
            return None
        back = np.flatnonzero(np.diff(np.concatenate([[self._last_dev], dev])) < 0)
        if back.size:
            return int(back[0])
        # clock no longer agrees with the host: host earlier than predicted by far, or later
        predicted = self._map_unwrapped(dev)
        delay = host - predicted
        bad = np.flatnonzero(np.abs(delay) > self.restart_tolerance_ns)
        if bad.size and self._buckets:
            return int(bad[0])
        return None

    def _absorb(self, dev: IntArray, host: IntArray) -> IntArray:
        if dev.size == 0:
            return np.empty(0, dtype=np.int64)
        if self._dev0 is None:
            self._dev0, self._host0 = int(dev[0]), int(host[0])
        self._last_dev = int(dev[-1])
        dev_s = (dev - self._dev0) * self.tick_s
        host_s = (host - self._host0) * 1e-9
        apparent = host_s - dev_s  # delay plus clock offset and drift: its minimum matters
        bucket = (host - self._host0) // self.bucket_ns
        order = np.lexsort((apparent, bucket))
        first = np.concatenate([[True], np.diff(bucket[order]) != 0])
        closed = not self._buckets
        for idx in order[first]:
            b, d, a = int(bucket[idx]), float(dev_s[idx]), float(apparent[idx])
            if self._buckets and self._buckets[-1][0] == b:
                if a < self._buckets[-1][2]:
                    self._buckets[-1] = (b, d, a)
            else:
                self._buckets.append((b, d, a))
                closed = True
        horizon = self._buckets[-1][0] - self.window_ns // self.bucket_ns
        while self._buckets and self._buckets[0][0] < horizon:
            self._buckets.popleft()
        # refit when a bucket closes (a few times a second), not on every batch
        if closed or len(self._buckets) < 3:
            self._refit()
        return self._map_unwrapped(dev)

    def _refit(self) -> None:
        data = np.array([(d, a) for _, d, a in self._buckets])
        dev_s, app = data[:, 0], data[:, 1]
        if len(data) < 3 or np.ptp(dev_s) < 1.0:
            self._fit = (float(app.min()), 1.0)
            self._rms_s, self._used, self._rejected = 0.0, len(data), 0
            return
        keep = np.ones(len(data), dtype=bool)
        for _ in range(3):
            slope, icept = np.polyfit(dev_s[keep], app[keep], 1)
            resid = app - (icept + slope * dev_s)
            mad = np.median(np.abs(resid[keep] - np.median(resid[keep]))) + 1e-9
            new_keep = resid < np.median(resid[keep]) + 4.0 * 1.4826 * mad
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
        slope, icept = np.polyfit(dev_s[keep], app[keep], 1)
        resid = app[keep] - (icept + slope * dev_s[keep])
        self._fit = (float(icept), 1.0 + float(slope))
        self._rms_s = float(np.sqrt(np.mean(resid**2)))
        self._used = int(keep.sum())
        self._rejected = int((~keep).sum())

    def _map_unwrapped(self, dev: IntArray) -> IntArray:
        assert self._dev0 is not None
        a, b = self._fit
        # host0 + rint((a + b·(dev - dev0)·tick)·1e9) - latency, in place: called per read
        x = (dev - self._dev0).astype(np.float64)
        x *= b * self.tick_s * 1e9
        x += a * 1e9
        np.rint(x, out=x)
        out = x.astype(np.int64)
        out += self._host0 - self.latency_ns
        return out

    # -- output ----------------------------------------------------------------------
    def map(self, device_ticks: ArrayLike) -> IntArray:
        """Host ns of raw device ticks of the current segment and wrap epoch (no update)."""
        if self._dev0 is None:
            raise RuntimeError("no samples yet: call update() first")
        dev = np.asarray(device_ticks, dtype=np.int64)
        if self._wrap_base:
            dev = dev + self._wrap_base
        return self._map_unwrapped(dev)

    def quality(self) -> ClockFitQuality:
        a, b = self._fit
        offset = self._host0 + round(a * 1e9) - round((self._dev0 or 0) * self.tick_s * b * 1e9)
        return ClockFitQuality(
            offset_ns=offset,
            drift_ppm=(b - 1.0) * 1e6,
            envelope_rms_ns=self._rms_s * 1e9,
            points=self._used,
            restarts=self.restarts,
            wraps=self.wraps,
            outliers=self._rejected,
        )
