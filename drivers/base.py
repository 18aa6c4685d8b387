"""The adapter interface every device driver implements, and the batch types it returns.

A driver is opened on a URL, returns batches of samples with device timestamps, reports
health counters, and is closed. The base class :class:`Driver` owns the lifecycle, the
timeouts, host timestamps, counting and logging of faults, and reconnecting with backoff;
an adapter implements three private hooks:

* ``_connect()``: open the link (through :func:`drivers.transport.open_stream` for byte
  streams) and bring the device to the state where it produces samples;
* ``_read_batch(deadline_ns) -> SampleBatch | None``: the one read hook: return what
  arrived until ``deadline_ns`` (``time.monotonic_ns``), raise
  :class:`~drivers.errors.DeviceIOError` when the link is gone;
* ``_disconnect()``: release the link (must not raise).

Clocks are named: ``t_host_ns`` is ``time.monotonic_ns()`` on the host when the frame that
carried the sample was received; ``t_device_us`` is the device's own clock, unwrapped to
64 bits by :class:`DeviceClock` (``epoch`` counts the device restarts the driver saw; the
device clock is only comparable within one epoch). Mapping device time to host time is
the acquisition daemon's job, not the driver's.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import random
import threading
import time
import warnings
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import NDArray

from drivers.errors import DeviceIOError, DriverClosedError, DriverConfigError

log = logging.getLogger(__name__)

HOST_CLOCK = "time.monotonic_ns"

# -- schema and batches ---------------------------------------------------------------------


@dataclass(frozen=True)
class ChannelSchema:
    """One value column of a batch: name (with unit), unit, numpy dtype, description."""

    name: str
    unit: str
    dtype: str
    description: str = ""


@dataclass(frozen=True)
class BatchSchema:
    """What a driver's batches hold; sent once per stream, not with every sample."""

    kind: str
    channels: tuple[ChannelSchema, ...]
    status_bits: dict[int, str]
    device_clock: str
    host_clock: str = HOST_CLOCK
    source: str = ""

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    @property
    def value_dtype(self) -> np.dtype:
        return np.result_type(*(np.dtype(c.dtype) for c in self.channels))

    def describe(self) -> dict[str, Any]:
        """A JSON-friendly description (ophyd ``describe()`` style)."""
        return {
            "kind": self.kind,
            "source": self.source,
            "device_clock": self.device_clock,
            "host_clock": self.host_clock,
            "channels": [
                {"name": c.name, "unit": c.unit, "dtype": c.dtype, "description": c.description}
                for c in self.channels
            ],
            "status_bits": {str(k): v for k, v in self.status_bits.items()},
        }


@dataclass(frozen=True, eq=False)
class SampleBatch:
    """Samples as column arrays (never one object per sample). N samples, C channels.

    * ``seq`` ``(N,)`` uint64: sample sequence number (device's, unwrapped; gaps are
      samples the device dropped and are counted as ``lost_samples``).
    * ``t_device_us`` ``(N,)`` int64: device clock, µs, unwrapped, per ``epoch``.
    * ``epoch`` ``(N,)`` int32: number of device restarts seen before this sample.
    * ``t_host_ns`` ``(N,)`` int64: ``time.monotonic_ns()`` at reception of the frame.
    * ``values`` ``(N, C)``: in the units of ``schema.channels``.
    * ``status`` ``(N, C)`` uint16: per-channel status bits (``schema.status_bits``).
    """

    schema: BatchSchema
    seq: NDArray[np.uint64]
    t_device_us: NDArray[np.int64]
    epoch: NDArray[np.int32]
    t_host_ns: NDArray[np.int64]
    values: NDArray[Any]
    status: NDArray[np.uint16]

    def __len__(self) -> int:
        return int(self.seq.shape[0])

    def __getitem__(self, index: slice) -> SampleBatch:
        """Samples ``index`` (a slice; views, no copy)."""
        if not isinstance(index, slice):
            raise TypeError(f"SampleBatch indices are slices, not {type(index).__name__}")
        return SampleBatch(
            self.schema,
            self.seq[index],
            self.t_device_us[index],
            self.epoch[index],
            self.t_host_ns[index],
            self.values[index],
            self.status[index],
        )

    @classmethod
    def empty(cls, schema: BatchSchema) -> SampleBatch:
        c = schema.n_channels
        return cls(
            schema,
            np.empty(0, np.uint64),
            np.empty(0, np.int64),
            np.empty(0, np.int32),
            np.empty(0, np.int64),
            np.empty((0, c), schema.value_dtype),
            np.empty((0, c), np.uint16),
        )

    @classmethod
    def concat(cls, schema: BatchSchema, batches: list[SampleBatch]) -> SampleBatch:
        batches = [b for b in batches if len(b)]
        if not batches:
            return cls.empty(schema)
        if len(batches) == 1:
            return batches[0]
        return cls(
            schema,
            np.concatenate([b.seq for b in batches]),
            np.concatenate([b.t_device_us for b in batches]),
            np.concatenate([b.epoch for b in batches]),
            np.concatenate([b.t_host_ns for b in batches]),
            np.concatenate([b.values for b in batches]),
            np.concatenate([b.status for b in batches]),
        )


# -- device clock and sequence unwrapping ------------------------------------------------------


class DeviceClock:
    """Unwraps a ``bits``-wide device µs clock into int64 and detects restarts.

    A forward step modulo ``2**bits`` below ``max_gap_us`` is normal (a wrap if the raw
    value fell); anything else (the clock went back, or jumped far ahead) is a restart:
    ``epoch`` increments and the unwrapped clock restarts from the raw value. A caller may
    also force a restart (e.g. the device reports a new boot id).
    """

    def __init__(self, bits: int = 32, max_gap_us: int = 60_000_000) -> None:
        self.modulus = 1 << bits
        self.max_gap_us = max_gap_us
        self.offset = 0
        self.last_raw: int | None = None
        self.epoch = 0
        self.wraps = 0
        self.restarts = 0

    def restart(self) -> None:
        self.restarts += 1
        self.epoch += 1
        self.offset = 0
        self.last_raw = None

    def unwrap(self, raw: NDArray[Any]) -> tuple[NDArray[np.int64], NDArray[np.int32]]:
        """Unwrapped µs ``(N,)`` and epoch ``(N,)`` for raw clock values ``(N,)``."""
        raw = np.asarray(raw, dtype=np.int64)
        n = raw.shape[0]
        if n and self.last_raw is not None:
            # the usual case, cheaply: moving forward in small steps, no wrap, no restart
            lo = int(raw[0]) - self.last_raw
            if 0 <= lo < self.max_gap_us:
                steps = np.diff(raw) if n > 1 else None
                if steps is None or (steps.min() >= 0 and steps.max() < self.max_gap_us):
                    self.last_raw = int(raw[-1])
                    return raw + self.offset, np.full(n, self.epoch, np.int32)
        out = np.empty(n, np.int64)
        epochs = np.empty(n, np.int32)
        if n == 0:
            return out, epochs
        prev = np.empty(n, np.int64)
        prev[1:] = raw[:-1]
        prev[0] = raw[0] if self.last_raw is None else self.last_raw
        wide = self.modulus > (1 << 62)  # a 63/64-bit clock never wraps in practice
        step = raw - prev if wide else (raw - prev) % self.modulus
        events = np.flatnonzero((step >= self.max_gap_us) | (raw < prev))
        start = 0
        for i in events.tolist():
            out[start:i] = raw[start:i] + self.offset
            epochs[start:i] = self.epoch
            if not wide and 0 <= step[i] < self.max_gap_us:  # fell but moved on: a wrap
                self.wraps += 1
                self.offset += self.modulus
            else:
                self.restarts += 1
                self.epoch += 1
                self.offset = 0
            start = i
        out[start:] = raw[start:] + self.offset
        epochs[start:] = self.epoch
        self.last_raw = int(raw[-1])
        return out, epochs


# -- options ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Option:
    """One driver option: type, default and a line of documentation."""

    type: type
    default: Any
    doc: str
    choices: tuple[Any, ...] | None = None


BASE_OPTIONS: dict[str, Option] = {
    "reconnect_min_s": Option(float, 0.05, "first reconnect delay"),
    "reconnect_max_s": Option(float, 2.0, "longest reconnect delay (exponential backoff)"),
    "read_timeout_s": Option(float, 0.1, "default timeout of read()"),
}


def validate_options(
    cls_name: str, table: dict[str, Option], given: dict[str, Any]
) -> dict[str, Any]:
    """Options ``given`` checked against ``table``; defaults filled in."""
    unknown = sorted(set(given) - set(table))
    if unknown:
        raise DriverConfigError(
            f"{cls_name}: unknown option {unknown[0]!r} (allowed: {', '.join(sorted(table))})"
        )
    out: dict[str, Any] = {}
    for name, opt in table.items():
        value = given.get(name, opt.default)
        if value is not None and not isinstance(value, opt.type):
            if opt.type is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            else:
                raise DriverConfigError(
                    f"{cls_name}: option {name!r} must be {opt.type.__name__}, got {value!r}"
                )
        if opt.choices is not None and value not in opt.choices:
            raise DriverConfigError(
                f"{cls_name}: option {name!r} must be one of {opt.choices}, got {value!r}"
            )
        out[name] = value
    return out


# -- health ---------------------------------------------------------------------------------------

#: Counters every driver reports (adapters may add their own).
COUNTERS: tuple[str, ...] = (
    "samples",
    "batches",
    "timeouts",
    "crc_errors",
    "garbage_bytes",
    "truncated_frames",
    "exception_responses",
    "protocol_errors",
    "lost_samples",
    "disconnects",
    "reconnects",
    "connect_failures",
    "device_restarts",
    "clock_wraps",
    "counter_wraps",
)


@dataclass(frozen=True)
class Health:
    """A snapshot of a driver's state and counters."""

    kind: str
    url: str
    state: str  # "closed" | "connected" | "reconnecting"
    counters: dict[str, int]
    last_sample_host_ns: int | None
    next_reconnect_in_s: float | None
    info: dict[str, Any] = field(default_factory=dict)


# -- the driver base ---------------------------------------------------------------------


class Driver(abc.ABC):
    """Base of every device driver: lifecycle, timeouts, counters, reconnect with backoff.

    Use as a context manager or call :meth:`open` / :meth:`close`. :meth:`read` never
    raises for device faults: they are counted in :meth:`health`, logged, and the driver
    reconnects with exponential backoff when the link is lost.
    """

    kind: ClassVar[str] = "abstract"
    OPTIONS: ClassVar[dict[str, Option]] = {}

    def __init__(self, url: str, **options: Any) -> None:
        self.url = url
        self.options = validate_options(
            type(self).__name__, {**BASE_OPTIONS, **self.OPTIONS}, options
        )
        self.counters: Counter[str] = Counter({k: 0 for k in COUNTERS})
        self.info: dict[str, Any] = {}
        self._state = "closed"
        self._opened = False
        self._closed = False
        self._connected = False
        self._backoff_s = self.options["reconnect_min_s"]
        self._last_connect_error = ""  # the last connect failure, for open()'s error
        self._next_attempt_ns = 0
        self._last_sample_ns: int | None = None
        self._lock = threading.RLock()

    # -- hooks -------------------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def schema(self) -> BatchSchema:
        """The schema of this driver's batches."""

    @abc.abstractmethod
    def _connect(self) -> None:
        """Open the link; raise DeviceIOError on failure."""

    @abc.abstractmethod
    def _read_batch(self, deadline_ns: int) -> SampleBatch | None:
        """Return samples that arrived until ``deadline_ns``; DeviceIOError if link lost."""

    @abc.abstractmethod
    def _disconnect(self) -> None:
        """Release the link; must not raise."""

    # -- counting ----------------------------------------------------------------------------
    def count(self, name: str, n: int = 1, detail: str = "") -> None:
        """Add ``n`` to counter ``name`` and log it (1st, 2nd, 4th, 8th... occurrence)."""
        if n <= 0:
            return
        before = self.counters[name]
        after = before + n
        self.counters[name] = after
        if name in ("samples", "batches"):
            return
        if before == 0 or (after.bit_length() > before.bit_length()):
            log.warning("%s %s: %s now %d %s", self.kind, self.url, name, after, detail)

    # -- lifecycle ---------------------------------------------------------------------------
    def open(self, timeout_s: float = 5.0) -> Self:
        """Connect, retrying with backoff for up to ``timeout_s``; DeviceIOError if never."""
        if self._closed:
            raise DriverClosedError(f"{self.kind} driver on {self.url} was closed")
        self._opened = True
        deadline = time.monotonic() + timeout_s
        while True:
            if self._try_connect():
                return self
            if time.monotonic() >= deadline:
                self._opened = False
                why = self._last_connect_error
                raise DeviceIOError(
                    f"{self.kind}: cannot connect to {self.url} in {timeout_s:.3g} s"
                    + (f" ({why})" if why else "")
                )
            time.sleep(min(self._backoff_s, max(0.0, deadline - time.monotonic())))

    def _try_connect(self) -> bool:
        try:
            self._connect()
        except DeviceIOError as exc:
            self._last_connect_error = str(exc)
            self.count("connect_failures", detail=str(exc))
            self._safe_disconnect()
            self._schedule_reconnect()
            self._state = "reconnecting"
            return False
        self._connected = True
        self._state = "connected"
        self._backoff_s = self.options["reconnect_min_s"]
        return True

    def _schedule_reconnect(self) -> None:
        jitter = 1.0 + 0.2 * random.random()
        self._next_attempt_ns = time.monotonic_ns() + int(self._backoff_s * jitter * 1e9)
        self._backoff_s = min(self._backoff_s * 2.0, self.options["reconnect_max_s"])

    def _safe_disconnect(self) -> None:
        try:
            self._disconnect()
        except Exception:  # a hook must not raise; never let it crash the caller
            log.exception("%s %s: error in _disconnect", self.kind, self.url)

    def _link_lost(self, exc: BaseException) -> None:
        self.count("disconnects", detail=str(exc))
        self._connected = False
        self._state = "reconnecting"
        self._safe_disconnect()
        self._schedule_reconnect()

    def read(self, timeout_s: float | None = None) -> SampleBatch:
        """Samples that arrived within ``timeout_s`` (may be empty; never raises for faults)."""
        if self._closed:
            raise DriverClosedError(f"{self.kind} driver on {self.url} was closed")
        if not self._opened:
            raise DriverClosedError(f"{self.kind} driver on {self.url} is not open")
        timeout = self.options["read_timeout_s"] if timeout_s is None else timeout_s
        deadline = time.monotonic_ns() + int(timeout * 1e9)
        with self._lock:
            if not self._connected:
                now = time.monotonic_ns()
                if now < self._next_attempt_ns:
                    time.sleep(max(0.0, min(self._next_attempt_ns, deadline) - now) / 1e9)
                    if time.monotonic_ns() < self._next_attempt_ns:
                        return SampleBatch.empty(self.schema)
                if not self._try_connect():
                    return SampleBatch.empty(self.schema)
                self.count("reconnects")
            try:
                batch = self._read_batch(deadline)
            except DeviceIOError as exc:
                self._link_lost(exc)
                return SampleBatch.empty(self.schema)
            except Exception as exc:  # an adapter bug must not kill the acquisition
                log.exception("%s %s: unexpected error in _read_batch", self.kind, self.url)
                self.count("protocol_errors", detail=repr(exc))
                self._link_lost(exc)
                return SampleBatch.empty(self.schema)
        if batch is None or len(batch) == 0:
            return SampleBatch.empty(self.schema)
        self.count("samples", len(batch))
        self.count("batches")
        self._last_sample_ns = int(batch.t_host_ns[-1])
        return batch

    def health(self) -> Health:
        nxt = None
        if self._state == "reconnecting":
            nxt = max(0.0, (self._next_attempt_ns - time.monotonic_ns()) / 1e9)
        return Health(
            kind=self.kind,
            url=self.url,
            state=self._state,
            counters=dict(self.counters),
            last_sample_host_ns=self._last_sample_ns,
            next_reconnect_in_s=nxt,
            info=dict(self.info),
        )

    def close(self) -> None:
        """Release the device; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        with self._lock:
            if self._connected or self._opened:
                self._safe_disconnect()
            self._connected = False
            self._state = "closed"

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Self:
        if not self._opened:
            self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_opened", False) and not getattr(self, "_closed", True):
            warnings.warn(
                f"{type(self).__name__} on {self.url} was not closed",
                ResourceWarning,
                stacklevel=2,
            )
            with contextlib.suppress(Exception):
                self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url} {self._state}>"
