"""``daq echo``: subscribe to a key expression, print batches, and/or summarise them.

For people (one line per batch) and for tests and benchmarks (``--jsonl`` writes every
sample's columns; ``--stats`` prints one JSON summary at the end: counts, lost batches,
sequence gaps, order violations and latency percentiles per key).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import IO, Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from daq.bus import Receiver, open_session, require_peer
from daq.config import ZenohConfig
from edges.stop_signals import on_stop_signals

LATENCY_KEEP = 2_000_000  # latency values kept per key for the percentiles (bounded memory)


class LatencySeries:
    """Latencies in ns, appended one message at a time into a buffer that doubles as it
    fills, up to ``LATENCY_KEEP`` values (a list of per-message arrays cost an allocation
    and a concatenate per message; a 1 kHz stream sends one sample a message)."""

    def __init__(self) -> None:
        self._buf = np.empty(4096, np.int64)
        self.n = 0
        # (UTC second of receive, index of that second's first value): percentiles per
        # time window (``windows``) at the cost of one integer compare per message
        self._starts: list[tuple[int, int]] = []
        self._second = -1

    def _mark(self, at_ns: int) -> None:
        second = at_ns // 1_000_000_000
        if second != self._second:
            self._second = second
            self._starts.append((second, self.n))

    def _room(self, k: int) -> int:
        k = min(k, LATENCY_KEEP - self.n)
        if self.n + k > len(self._buf):
            grown = np.empty(min(LATENCY_KEEP, max(2 * len(self._buf), self.n + k)), np.int64)
            grown[: self.n] = self._buf[: self.n]
            self._buf = grown
        return k

    def add_one(self, value_ns: int, at_ns: int) -> None:
        """One latency of a message received at ``at_ns`` (UTC ns)."""
        self._mark(at_ns)
        if self._room(1):
            self._buf[self.n] = value_ns
            self.n += 1

    def add(self, values_ns: NDArray[np.int64], at_ns: int) -> None:
        """The latencies of one message received at ``at_ns`` (UTC ns)."""
        self._mark(at_ns)
        k = self._room(len(values_ns))
        self._buf[self.n : self.n + k] = values_ns[:k]
        self.n += k

    def values(self) -> NDArray[np.int64]:
        return self._buf[: self.n]

    def windows(self, width_s: int) -> list[dict[str, float]]:
        """Percentiles in ms per window of ``width_s`` seconds of receive time, aligned
        to UTC multiples of ``width_s``: ``t_s`` (the window's start, UTC s), ``n``,
        ``p50``, ``p99``, ``max``. Windows without values (none arrived, or they came
        after ``LATENCY_KEEP`` were kept) are left out."""
        if not self._starts:
            return []
        second, index = np.array(self._starts, np.int64).T
        window = second // width_s
        first = np.flatnonzero(np.r_[True, window[1:] != window[:-1]])
        bounds = np.r_[index[first], self.n]
        out: list[dict[str, float]] = []
        for j, f in enumerate(first.tolist()):
            v = self._buf[bounds[j] : bounds[j + 1]] / 1e6
            if v.size:
                p50, p99 = np.percentile(v, [50, 99])
                t_s = int(window[f]) * width_s
                out.append({"t_s": t_s, "n": int(v.size), "p50": float(p50), "p99": float(p99),
                            "max": float(v.max())})  # fmt: skip
        return out


@dataclass
class KeyStats:
    batches: int = 0
    samples: int = 0
    lost_batches: int = 0  # batch_seq jumps
    seq_gaps: int = 0  # samples missing by the device sequence number
    seq_breaks: int = 0  # sequence number went back (device restart) or repeated
    out_of_order: int = 0  # mapped time went back within an epoch
    unsettled: int = 0  # samples mapped before the clock fit settled (t_mapped_ok = 0)
    first_seq: int | None = None
    last_seq: int | None = None
    last_batch: int | None = None
    last_t_mapped: int | None = None
    last_epoch: int | None = None
    lat_mapped: LatencySeries = field(default_factory=LatencySeries)
    lat_rx: LatencySeries = field(default_factory=LatencySeries)
    #: the fields ``summary()`` reports as they are
    COUNTED: ClassVar[tuple[str, ...]] = (
        "batches",
        "samples",
        "lost_batches",
        "seq_gaps",
        "seq_breaks",
        "out_of_order",
        "unsettled",
        "first_seq",
        "last_seq",
    )

    def add(self, header: Any, cols: dict[str, np.ndarray], t_recv_ns: int) -> None:
        self.batches += 1
        n = header.n_samples
        self.samples += n
        if self.last_batch is not None and header.batch_seq != self.last_batch + 1:
            self.lost_batches += max(0, header.batch_seq - self.last_batch - 1)
        self.last_batch = header.batch_seq
        if n == 0 or "seq" not in cols:
            return
        if n == 1 and self._add_one(cols, t_recv_ns):
            return
        seq = cols["seq"].astype(np.int64)
        epoch = cols["epoch"].astype(np.int64) if "epoch" in cols else np.zeros(n, np.int64)
        prev_seq = seq[0] - 1 if self.last_seq is None else self.last_seq
        prev_ep = epoch[0] if self.last_epoch is None else self.last_epoch
        d = np.diff(np.concatenate([[prev_seq], seq]))
        same = np.diff(np.concatenate([[prev_ep], epoch])) == 0
        self.seq_gaps += int(np.sum(np.where(same & (d > 1), d - 1, 0)))
        self.seq_breaks += int(np.sum(same & (d < 1)) + np.sum(~same))
        if self.first_seq is None:
            self.first_seq = int(seq[0])
        self.last_seq = int(seq[-1])
        self.last_epoch = int(epoch[-1])
        if "t_mapped_ns" in cols:
            tm = cols["t_mapped_ns"].astype(np.int64)
            prev_t = tm[0] if self.last_t_mapped is None else self.last_t_mapped
            dt = np.diff(np.concatenate([[prev_t], tm]))
            self.out_of_order += int(np.sum(same & (dt < 0)))
            self.last_t_mapped = int(tm[-1])
            if "t_mapped_ok" in cols:  # a provisional clock fit says nothing of latency
                ok = cols["t_mapped_ok"] == 1
                self.unsettled += int(n - np.count_nonzero(ok))
                tm = tm[ok]
            self.lat_mapped.add(t_recv_ns - tm, t_recv_ns)
            if "t_host_rx_ns" in cols:
                self.lat_rx.add(t_recv_ns - cols["t_host_rx_ns"].astype(np.int64), t_recv_ns)

    def _add_one(self, cols: dict[str, np.ndarray], t_recv_ns: int) -> bool:
        """One sample following the last in the same epoch, in Python ints (the usual
        message of a 1 kHz device); False: anything else, for the general path."""
        ep = int(cols["epoch"][0]) if "epoch" in cols else 0
        s = int(cols["seq"][0])
        if self.last_seq is None or ep != self.last_epoch or s != self.last_seq + 1:
            return False
        self.last_seq = s
        if "t_mapped_ns" not in cols:
            return True
        tm = int(cols["t_mapped_ns"][0])
        if self.last_t_mapped is not None and tm < self.last_t_mapped:
            self.out_of_order += 1
        self.last_t_mapped = tm
        if "t_mapped_ok" in cols and int(cols["t_mapped_ok"][0]) != 1:
            self.unsettled += 1
        else:
            self.lat_mapped.add_one(t_recv_ns - tm, t_recv_ns)
        if "t_host_rx_ns" in cols:
            self.lat_rx.add_one(t_recv_ns - int(cols["t_host_rx_ns"][0]), t_recv_ns)
        return True

    def summary(self, window_s: int | None = None) -> dict[str, Any]:
        """Counts and latency percentiles (ms); with ``window_s``, also the device →
        subscriber latency per window of receive time (``latency_mapped_ms_windows``)."""
        out: dict[str, Any] = {k: getattr(self, k) for k in self.COUNTED}
        lat = (("latency_mapped_ms", self.lat_mapped), ("latency_rx_ms", self.lat_rx))
        for name, series in lat:
            v = series.values() / 1e6
            if v.size:
                out[name] = {
                    "p50": float(np.percentile(v, 50)),
                    "p99": float(np.percentile(v, 99)),
                    "max": float(v.max()),
                    "n": int(v.size),
                }
        if window_s is not None:
            out["latency_mapped_ms_windows"] = self.lat_mapped.windows(window_s)
        return out


def _jsonable(cols: dict[str, np.ndarray]) -> dict[str, Any]:
    return {k: v.tolist() for k, v in cols.items()}


class _Echo:
    """What an echo received (counts per key, the last JSON document per key) and where
    it goes (``lines``: JSON lines; else one printed line per message unless ``quiet``).
    Its handlers run on zenoh's callback thread, one message at a time."""

    def __init__(
        self, lines: IO[str] | None, *, quiet: bool, count: int | None, stop: threading.Event
    ) -> None:
        self.lines = lines
        self.quiet = quiet
        self.count = count
        self.stop = stop
        self.stats: dict[str, KeyStats] = {}
        self.health: dict[str, Any] = {}
        self.failed: list[BaseException] = []  # raised on zenoh's thread: re-raised on the caller's
        self.batches = 0
        self.last_rx = 0.0

    def on_zenoh_thread(self, handler: Callable[[Any], None]) -> Callable[[Any], None]:
        """``handler``, its exception kept and ``stop`` set: zenoh would only log it, and an
        output that fails (a closed pipe, a full disk) must stop the echo with that error,
        as it did on the main thread."""

        def call(arg: Any) -> None:
            try:
                handler(arg)
            except BaseException as exc:
                if not self.failed:
                    self.failed.append(exc)
                self.stop.set()

        return call

    def other(self, sample: Any) -> None:
        """A JSON message (a health document); anything else is ignored."""
        key = str(sample.key_expr)
        try:
            doc = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        self.health[key] = doc
        if self.lines is not None:
            self.lines.write(json.dumps({"key": key, "json": doc}) + "\n")
        elif not self.quiet:
            print(f"{key} {json.dumps(doc)}", flush=True)

    def batch(self, got: Any) -> None:
        """A decoded batch: counted, written or printed; ``stop`` set at ``count``."""
        # zenoh's callback thread (one message at a time): no hand-over to the caller's
        # thread, whose wake-up per message added to the latency (docs/daq.md "Speed")
        count = self.count
        if self.failed or (count is not None and self.batches >= count):
            return  # enough: the main thread is closing
        self.last_rx = time.monotonic()
        self.batches += 1
        st = self.stats.get(got.key)
        if st is None:  # not setdefault: that would build a KeyStats for every message
            st = self.stats[got.key] = KeyStats()
        st.add(got.header, got.columns, got.t_recv_ns)
        if self.lines is not None:
            rec = {
                "key": got.key,
                "batch_seq": got.header.batch_seq,
                "t_recv_ns": got.t_recv_ns,
                "columns": _jsonable(got.columns),
            }
            self.lines.write(json.dumps(rec) + "\n")
        elif not self.quiet:
            c = got.columns
            seq = c.get("seq")
            span = f"seq {int(seq[0])}..{int(seq[-1])}" if seq is not None and len(seq) else ""
            h = got.header
            print(f"{got.key} #{h.batch_seq} n={h.n_samples} {span}", flush=True)
        if count is not None and self.batches >= count:
            self.stop.set()

    def wait(
        self, recv: Receiver, t0: float, duration_s: float | None, idle_s: float | None
    ) -> None:
        """Until ``stop``, ``duration_s`` after ``t0`` (``time.monotonic()``), or ``idle_s``
        without a batch once one came and none is pending."""
        while not self.stop.wait(0.05):
            now = time.monotonic()
            if duration_s is not None and now - t0 >= duration_s:
                break
            idle = now - self.last_rx >= idle_s if idle_s is not None else False
            if idle and self.batches and not recv.pending:  # a backlog is not idle
                break


def run_echo(
    key_expr: str,
    zc: ZenohConfig,
    *,
    duration_s: float | None = None,
    count: int | None = None,
    idle_s: float | None = None,
    jsonl: IO[str] | Callable[[], IO[str]] | None = None,
    quiet: bool = False,
    stats_out: IO[str] | None = None,
    ready_out: IO[str] | None = None,
    stats_window_s: int | None = None,
) -> dict[str, Any]:
    """Receive until duration, batch count, idle time or SIGINT/SIGTERM; return stats
    (with ``stats_window_s``: latency percentiles per window of that many seconds too).
    ``jsonl``: a stream, or a function opening one, called once the session is open (a
    run that cannot connect leaves no file behind)."""
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        on_stop_signals(stop.set)  # not stop.set() in the handler: edges/stop_signals.py
    # the lines of a function are opened with the session
    echo = _Echo(None if callable(jsonl) else jsonl, quiet=quiet, count=count, stop=stop)
    session = open_session(zc)
    t0 = time.monotonic()
    recv: Receiver | None = None
    try:
        require_peer(session, zc)  # nobody there: said within seconds, no file opened
        if callable(jsonl):
            echo.lines = jsonl()
        recv = Receiver(
            session,
            key_expr,
            on_other=echo.on_zenoh_thread(echo.other),
            on_batch=echo.on_zenoh_thread(echo.batch),
        )
        if ready_out is not None:
            ready_out.write(json.dumps({"ready": key_expr}) + "\n")
            ready_out.flush()
        echo.wait(recv, t0, duration_s, idle_s)
        recv.close()  # no batch is handed over after this
    finally:
        session.close()
    if echo.failed:
        raise echo.failed[0]
    result = {
        "keys": {k: s.summary(stats_window_s) for k, s in sorted(echo.stats.items())},
        "health": echo.health,
        "undecodable": recv.undecodable if recv is not None else 0,
        "elapsed_s": time.monotonic() - t0,
    }
    if stats_out is not None:
        stats_out.write(json.dumps(result) + "\n")
        stats_out.flush()
    return result


def main_echo(args: Any, zc: ZenohConfig) -> int:
    from daq.cells import echo_key

    key = echo_key(args.key, getattr(args, "cell", None))  # refused before any output
    opened: list[IO[str]] = []
    jsonl: IO[str] | Callable[[], IO[str]] | None = None
    if args.jsonl == "-":
        jsonl = sys.stdout
    elif args.jsonl:
        # written as batches come: checked up front, not staged
        from daq.recording_writer import check_stream_output

        config_path = getattr(args, "config", None) or os.environ.get("DAQ_CONFIG")
        check_stream_output(args.jsonl, "--jsonl", [config_path], regular=False)

        def jsonl_open() -> IO[str]:
            opened.append(open(args.jsonl, "w", encoding="utf-8"))  # noqa: SIM115
            return opened[-1]

        jsonl = jsonl_open
    try:
        run_echo(
            key,
            zc,
            duration_s=args.duration,
            count=args.count,
            idle_s=args.idle,
            jsonl=jsonl,
            quiet=args.quiet or args.stats,
            stats_out=sys.stdout if args.stats else None,
            ready_out=sys.stderr if args.ready else None,
            stats_window_s=args.stats_window,
        )
    finally:
        for fh in opened:
            fh.close()
    return 0
