"""DeviceClockMap against a simulated truth: drift, delays, outliers, wraps, restarts."""

from __future__ import annotations

import numpy as np
import pytest

from daq.clock_sync import DeviceClockMap

WRAP = 2**32


def simulate(
    seed: int,
    *,
    seconds: float = 120.0,
    rate_hz: float = 1000.0,
    drift_ppm: float = 50.0,
    dev_start: int = 123_456,
    batch: int = 10,
):
    """Latch instants (host ns, truth), device µs stamps and host receive times."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    t_true = 1_000_000_000_000 + np.arange(n) * int(1e9 / rate_hz)
    dev = dev_start + np.rint((t_true - t_true[0]) * 1e-3 * (1 + drift_ppm * 1e-6)).astype(np.int64)
    # transport: 80 µs floor + exponential jitter, batches leave together, 1 % late by 5-50 ms
    delay = 80_000 + rng.exponential(150_000, n)
    late = rng.random(n) < 0.01
    delay[late] += rng.uniform(5e6, 50e6, late.sum())
    host = t_true + delay.astype(np.int64)
    # a batch is received when its last sample is: earlier samples look even later
    for start in range(0, n, batch):
        host[start : start + batch] = host[start : start + batch].max()
    return t_true, dev, host


def feed(clock: DeviceClockMap, dev, host, batch: int = 10):
    out = [clock.update(dev[i : i + batch], host[i : i + batch]) for i in range(0, len(dev), batch)]
    return np.concatenate(out)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_drift_and_delays_tracked_to_tens_of_microseconds(seed):
    t_true, dev, host = simulate(seed)
    clock = DeviceClockMap(tick_s=1e-6, latency_ns=80_000)
    mapped = feed(clock, dev, host)
    err_us = (mapped - t_true) * 1e-3
    settled = err_us[len(err_us) // 4 :]  # after the first 30 s of the window
    assert np.percentile(np.abs(settled), 99) < 25.0, np.percentile(np.abs(settled), 99)
    q = clock.quality()
    assert q.drift_ppm == pytest.approx(-50.0 / (1 + 50e-6), abs=2.0)
    assert q.restarts == 0 and q.wraps == 0


def test_raw_receive_time_is_much_worse_than_the_map():
    t_true, dev, host = simulate(4)
    mapped = feed(DeviceClockMap(latency_ns=80_000), dev, host)
    half = len(t_true) // 2
    raw_err = np.abs(host - t_true)[half:].mean()
    map_err = np.abs(mapped - t_true)[half:].mean()
    assert map_err * 5 < raw_err


def test_counter_wrap_is_unwrapped_and_counted():
    t_true, dev, host = simulate(5, seconds=40.0, dev_start=WRAP - 10_000_000)
    clock = DeviceClockMap(wrap_ticks=WRAP, latency_ns=80_000)
    mapped = feed(clock, dev % WRAP, host)
    assert clock.quality().wraps == 1
    assert clock.quality().restarts == 0
    err_us = np.abs(mapped - t_true)[len(t_true) // 2 :] * 1e-3
    assert np.percentile(err_us, 99) < 150.0


def test_device_restart_starts_a_new_segment():
    t_true, dev, host = simulate(6, seconds=60.0)
    cut = len(dev) // 2
    dev = dev.copy()
    dev[cut:] = dev[cut:] - dev[cut] + 7  # the device rebooted: its clock starts over
    clock = DeviceClockMap(latency_ns=80_000)
    mapped = feed(clock, dev, host)
    assert clock.quality().restarts == 1
    # a few seconds after the restart the map is good again
    after = slice(cut + 5_000, None)
    assert np.percentile(np.abs(mapped[after] - t_true[after]) * 1e-3, 99) < 150.0


def test_restart_to_a_larger_clock_value_is_detected():
    _, dev, host = simulate(7, seconds=30.0)
    cut = len(dev) // 2
    dev = dev.copy()
    dev[cut:] += 3_000_000_000  # jumps far ahead: host and device disagree by ~50 min
    clock = DeviceClockMap()
    feed(clock, dev, host)
    assert clock.quality().restarts == 1


def test_quality_reports_outlier_buckets_and_rms():
    t_true, dev, host = simulate(8, seconds=60.0)
    host = host.copy()
    # a whole 2 s host stall: every bucket in it is late
    stall = (t_true > t_true[20_000]) & (t_true < t_true[22_000])
    host[stall] += 30_000_000
    clock = DeviceClockMap()
    feed(clock, dev, host)
    q = clock.quality()
    assert q.outliers >= 4
    assert 0.0 < q.envelope_rms_ns < 100_000


def test_bad_arguments():
    with pytest.raises(ValueError):
        DeviceClockMap(tick_s=0)
    clock = DeviceClockMap()
    with pytest.raises(ValueError):
        clock.update([1, 2], [3])
    with pytest.raises(RuntimeError):
        clock.map([1])
    assert clock.update([], []).size == 0
