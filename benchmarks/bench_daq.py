"""Acquisition daemon benchmarks: throughput vs raw zenoh, full cell CPU/latency/loss, soak.

Every figure comes from separate processes on loopback, measured in the same run:

* ``throughput``: the daemon (``daq run``, a device source producing as fast as it can,
  batches of ``B`` samples) → a subscriber process, in messages/s, against raw
  eclipse-zenoh pub/sub of the *same messages*: same payload bytes, key expression and
  zenoh Encoding, BLOCK congestion control, from a publisher in this process, to the same
  subscriber code subscribed to that exact key in both runs. (A wildcard subscription,
  ``cell/**``, costs the *subscriber's* zenoh 25-40 % of its rate; were only one side to
  use it, the ratio would measure the subscription, not the daemon.) Ratio = daemon / raw
  samples per second (medians of alternating rounds with ``--full``). The daemon's source
  outruns it: a backlog read ``MAX_READ`` samples at a time.
* ``cell``: the full cell at 1 kHz per device (three devices), ``daq run`` → ``daq echo
  --stats``: the daemon's CPU (its own process, from /proc), latency device → subscriber
  p50/p99 (subscriber receive time − mapped device latch time, same host clock), and
  sample loss (sequence gaps + lost batches seen by the subscriber).
* ``--soak S``: the cell benchmark for S seconds (the 10-minute soak: ``--soak 600``;
  ``--record``: the daemon records MCAP meanwhile; ``--reference``: a raw zenoh latency
  reference runs alongside, as it does in ``--full``'s cell run). The cell run also
  gives its latency per 10 s window beside what a sleeping 1 kHz loop in this process
  and the hypervisor's steal counter showed in that window, and splits the windows by
  whether that loop ever woke over 5 ms late (``windows_host_quiet`` /
  ``windows_host_stalled``) and by the steal in them (``windows_by_steal_cores``);
  ``--windows FILE`` writes every window as JSON lines.

Devices: the emulated cell (``sim-cell``) when ``--emulated`` is given, else in-process
fake devices (``daq.testing.FakeDriver``: a drifting µs clock, 1 kHz, no wire).

    python -m benchmarks.bench_daq            # quick smoke run (~15 s)
    python -m benchmarks.bench_daq --full     # 3 alternating 5 s throughput rounds, 60 s cell
    python -m benchmarks.bench_daq --soak 600 # 10-minute soak of the cell at 1 kHz/device
    python -m benchmarks.bench_daq --soak 600 --windows soak.jsonl  # and its 10 s windows
    python -m benchmarks.bench_daq --wildcard # raw zenoh: a cell/** subscriber vs the exact key
    python -m benchmarks.bench_daq --full --tx-queue 2  # with zenoh's default transmit queue

``run(quick) -> list[dict]`` is the entry point for the generic runner.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

CLK_TCK = os.sysconf("SC_CLK_TCK")
#: samples one read of the throughput benchmark's source returns at most
MAX_READ = 20_000
PY = sys.executable
#: cell and robot of the benchmark configurations (``_cell_config``)
CELL, ROBOT = "bench", "r1"
#: the throughput runs' data key: the daemon's first device's samples
DATA_KEY = f"cell/{CELL}/robot/{ROBOT}/dev1/samples"


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (Linux /proc)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def _tree_cpu_s(pid: int) -> float:
    """``_cpu_s`` of ``pid`` and its live children (the daemon and its device workers)."""
    kids: list[str] = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/children", encoding="ascii") as fh:
                kids += fh.read().split()
        except OSError:  # the thread ended meanwhile
            continue
    total = _cpu_s(pid)
    for k in kids:
        try:
            total += _cpu_s(int(k))
        except OSError:  # the child ended meanwhile
            continue
    return total


def _host_steal_s() -> float:
    """CPU seconds the hypervisor gave to others, all CPUs (Linux /proc/stat ``steal``)."""
    with open("/proc/stat", encoding="ascii") as fh:
        fields = fh.readline().split()
    return int(fields[8]) / CLK_TCK if len(fields) > 8 else 0.0


def _free_port() -> int:
    from daq.testing import free_port

    return free_port()


def _sample_payload(batch: int, k: int = 0) -> bytes:
    """A daemon payload of ``batch`` samples of the fake 3-channel device (same layout),
    the ``k``-th of a run."""
    from daq.columnar import encode
    from daq.config import DaqConfig, DeviceConfig
    from daq.pipeline import build_schemas
    from daq.testing import FAKE_SCHEMA

    cfg = DaqConfig()
    dev = DeviceConfig(name="fake", driver="fake", url="fake://", robot="r1")
    schema, _ = build_schemas(cfg, dev, FAKE_SCHEMA, 0)[0]
    n = batch
    seq = np.arange(k * n, (k + 1) * n)
    cols = {
        "seq": seq.astype(np.uint64),
        "epoch": np.zeros(n, np.int32),
        "t_device_us": seq * 1000,
        "t_host_rx_ns": np.full(n, time.time_ns()),
        "t_mapped_ns": np.full(n, time.time_ns()),
        "t_mapped_ok": np.ones(n, np.uint8),
        "status": np.ones((n, 3), np.uint16),
    }
    for i in range(3):
        cols[f"grating{i + 1}_counts"] = seq
    return encode(schema, cols, k)


# -- raw zenoh sink (a separate process) ----------------------------------------------------


def _sink_main(port: int, key: str, seconds: float, idle_s: float) -> None:
    import zenoh

    from daq.bus import open_session
    from daq.testing import loopback_sink

    session = open_session(loopback_sink(port))
    sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(1 << 16))
    print(json.dumps({"ready": True}), flush=True)
    n = nbytes = samples = 0
    t_first = t_last = 0.0
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        s = sub.try_recv()
        if s is None:
            if n and time.monotonic() - t_last > idle_s:
                break
            time.sleep(0.0002)
            continue
        t_last = time.monotonic()
        if not n:
            t_first = t_last
        n += 1
        payload = s.payload.to_bytes()
        nbytes += len(payload)
        if n > 1 and payload[:4] == b"DQC1":  # not health JSON; after the first message
            samples += int.from_bytes(payload[12:16], "little")  # the header's n_samples
    sub.undeclare()
    session.close()
    dt = max(1e-9, t_last - t_first)
    print(
        json.dumps(
            {
                "messages": n,
                "bytes": nbytes,
                "seconds": dt,
                "msg_per_s": (n - 1) / dt,
                "samples_per_s": samples / dt,
            }
        )
    )


def _start_sink(port: int, key: str, seconds: float, idle_s: float = 1.0) -> subprocess.Popen:
    return _start_main(f"_sink_main({port}, {key!r}, {seconds}, {idle_s})")


# -- raw zenoh latency reference (two separate processes) ----------------------------------


def _ref_pub_main(port: int, seconds: float, size: int, rate_hz: float, keys: int) -> None:
    """``keys`` streams at ``rate_hz``: at each tick, one ``size``-byte message per key
    carrying the tick's host UTC ns (the "latch") and a counter. No encoding, no clock
    map: what a minimal Python publisher on zenoh achieves on this host right now."""
    import zenoh

    from daq.bus import open_session, utc_offset_ns
    from daq.testing import loopback_source

    session = open_session(loopback_source(port))
    pubs = [
        session.declare_publisher(
            f"ref/{CELL}/dev{i + 1}", congestion_control=zenoh.CongestionControl.BLOCK
        )
        for i in range(keys)
    ]
    print(json.dumps({"ready": True}), flush=True)
    off = utc_offset_ns()
    pad = bytes(max(0, size - 16))
    period_ns = int(1e9 / rate_hz)
    t0 = time.monotonic_ns()
    n_max = int(seconds * rate_hz)
    for k in range(n_max):  # bounded by count (and so by time)
        tick = t0 + k * period_ns
        wait = (tick - time.monotonic_ns()) / 1e9
        if wait > 0:
            time.sleep(wait)
        head = (tick + off).to_bytes(8, "little") + k.to_bytes(8, "little")
        for p in pubs:
            p.put(head + pad)
    time.sleep(0.5)
    session.close()


def _ref_sub_main(port: int, seconds: float, idle_s: float) -> None:
    """Latency of ``_ref_pub_main``'s messages: receive time − tick time, and losses."""
    import queue

    import zenoh

    from daq.bus import open_session
    from daq.testing import loopback_sink

    session = open_session(loopback_sink(port))
    q: queue.SimpleQueue[Any] = queue.SimpleQueue()
    sub = session.declare_subscriber(f"ref/{CELL}/**", zenoh.handlers.Callback(q.put))
    print(json.dumps({"ready": True}), flush=True)
    lat = np.empty(int(seconds * 1000 * 8) + 1, np.int64)  # up to 8 kHz of messages
    n = lost = 0
    last: dict[str, int] = {}
    t_end = time.monotonic() + seconds
    t_last = time.monotonic()
    while time.monotonic() < t_end and n < len(lat):
        try:
            s = q.get(timeout=0.05)
        except queue.Empty:
            if n and time.monotonic() - t_last > idle_s:
                break
            continue
        t = time.time_ns()
        t_last = time.monotonic()
        b = s.payload.to_bytes()
        key = str(s.key_expr)
        k = int.from_bytes(b[8:16], "little")
        lost += max(0, k - last.get(key, k - 1) - 1)
        last[key] = k
        lat[n] = t - int.from_bytes(b[:8], "little")
        n += 1
    sub.undeclare()
    session.close()
    v = lat[:n] / 1e6
    print(
        json.dumps(
            {
                "messages": n,
                "lost": lost,
                "p50": float(np.percentile(v, 50)) if n else None,
                "p99": float(np.percentile(v, 99)) if n else None,
                "max": float(v.max()) if n else None,
            }
        )
    )


def _start_main(call: str, realtime: int = 0) -> subprocess.Popen:
    """``python -c`` of a function of this module (it prints a ready line first), under
    SCHED_FIFO priority ``realtime`` if not 0."""
    code = f"import benchmarks.bench_daq as b; b.{call}"
    if realtime:
        code = f"from daq.scheduling import set_realtime; set_realtime({realtime}, 'bench'); {code}"
    p = subprocess.Popen(
        [PY, "-c", code], stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parents[1]
    )
    assert p.stdout is not None
    json.loads(p.stdout.readline())
    return p


def raw_zenoh_throughput(
    payload: bytes, seconds: float, subscription: str = DATA_KEY, tx_queue: int | None = None
) -> dict[str, Any]:
    """Raw pub/sub of ``payload`` on ``DATA_KEY`` over loopback: publisher here, subscriber
    process subscribed to ``subscription`` (the key itself, or a key expression matching it).
    ``tx_queue``: ``[zenoh] tx_queue_batches`` (None: the daemon's default)."""
    import dataclasses

    import zenoh

    from daq.bus import DATA_ENCODING, open_session
    from daq.testing import loopback_source

    port = _free_port()
    zc = loopback_source(port)
    if tx_queue is not None:
        zc = dataclasses.replace(zc, tx_queue_batches=tx_queue)
    session = open_session(zc)
    try:
        sink = _start_sink(port, subscription, seconds + 10)
        pub = session.declare_publisher(
            DATA_KEY, encoding=DATA_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK
        )
        t_end = time.monotonic() + 5
        while not pub.matching_status.matching and time.monotonic() < t_end:
            time.sleep(0.01)
        t_end = time.monotonic() + seconds
        sent = 0
        while time.monotonic() < t_end:  # bounded by time
            for _ in range(100):
                pub.put(payload)
            sent += 100
        out, _ = sink.communicate(timeout=seconds + 30)
        res = json.loads(out.strip().splitlines()[-1])
        res["sent"] = sent
        pub.undeclare()
        return res
    finally:
        session.close()


def _cell_config(
    port: int,
    devices: int,
    rate_hz: float,
    batch: int,
    age_s: float,
    max_read: int = 0,
    tx_queue: int | None = None,
    threads: bool = False,
) -> str:
    # with a backlog (max_read) device time lags the wall clock: no expected rate, so no
    # time-gap counting against it
    extra = f", max_read = {max_read}" if max_read else ""
    declared = "" if max_read else f"rate_hz = {rate_hz}\n"
    out = [
        f'[cell]\nname = "{CELL}"\nrobot = "{ROBOT}"\n',
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        + (f"tx_queue_batches = {tx_queue}\n" if tx_queue is not None else ""),
        f"[publish]\nmax_batch_samples = {batch}\nmax_batch_age_s = {age_s}\n"
        + ("process_per_device = false\n" if threads else ""),
    ]
    for i in range(devices):
        out.append(
            f'[[device]]\nname = "dev{i + 1}"\ndriver = "daq.testing:FakeDriver"\n'
            f'url = "fake://{i}"\n{declared}'
            f"options = {{ rate_hz = {rate_hz}{extra} }}\n"
        )
    return "\n".join(out)


#: the cell run's latency and the host's figures are also given per window of this many
#: seconds (UTC-aligned), so a tail can be read against what the host did in that window
WINDOW_S = 10


@dataclass
class HostProbe:
    """What the host let a plain sleeping loop in this process do over a window: how late
    each wake-up was (``late_ms``) and when it woke (``at_s``, UTC s), and the
    hypervisor's steal counter once a second (``steal``: rows of UTC s, CPU-seconds
    stolen so far). A stalled host delays every process alike: read the daemon's
    latency against it."""

    late_ms: NDArray[np.float64]
    at_s: NDArray[np.float64]
    steal: NDArray[np.float64]

    def summary(self, seconds: float) -> dict[str, float]:
        w = self.late_ms
        return {
            "p50": float(np.percentile(w, 50)),
            "p99": float(np.percentile(w, 99)),
            "max": float(w.max()),
            # wall time the loop spent stalled beyond 5 ms: a stall delays every sample
            # in flight, so 1 % of the run stalled puts the daemon's p99 in the stalls
            "stalled_fraction_over_5ms": float(w[w > 5.0].sum() / 1e3 / max(seconds, 1e-9)),
        }

    def windows(self, width_s: int) -> dict[int, dict[str, float | None]]:
        """Per window of ``width_s`` s aligned to UTC multiples of it (key: its start,
        UTC s): ``stalled_fraction_over_5ms`` of the window and ``steal_cores``."""
        out: dict[int, dict[str, float | None]] = {}
        window = (self.at_s // width_s).astype(np.int64)
        stalled = np.where(self.late_ms > 5.0, self.late_ms / 1e3, 0.0)
        for w in np.unique(window).tolist():
            t0 = w * width_s
            span = min(t0 + width_s, self.at_s[-1]) - max(t0, self.at_s[0])
            st = self.steal[(self.steal[:, 0] >= t0) & (self.steal[:, 0] <= t0 + width_s)]
            steal = (st[-1, 1] - st[0, 1]) / (st[-1, 0] - st[0, 0]) if len(st) > 1 else None
            out[t0] = {
                "stalled_fraction_over_5ms": float(stalled[window == w].sum() / max(span, 1e-3)),
                "steal_cores": None if steal is None else float(steal),
            }
        return out


def _probe_host(seconds: float, period_s: float = 0.001, *, realtime: int = 0) -> HostProbe:
    """Sleep ``period_s`` at a time for ``seconds`` (at most ``seconds / period_s``
    wake-ups, at least one) and note how late each wake-up was; read the steal counter
    once a second. ``realtime``: the loop runs under SCHED_FIFO of that priority, as the
    cell does (a normal loop would measure the cell's real-time threads, not the host)."""
    from daq.scheduling import normal_for_this_thread

    if realtime:  # this thread only (set_realtime would take the whole process)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(realtime))
    try:
        return _probe_loop(seconds, period_s)
    finally:
        normal_for_this_thread()


def _probe_loop(seconds: float, period_s: float) -> HostProbe:
    late = np.empty(int(seconds / period_s) + 1)
    at = np.empty_like(late)
    steal = [(time.time(), _host_steal_s())]
    n = 0
    t_end = time.monotonic() + seconds
    while n == 0 or (n < len(late) and time.monotonic() < t_end):
        t = time.perf_counter()
        time.sleep(period_s)
        late[n] = (time.perf_counter() - t - period_s) * 1e3
        at[n] = time.time()
        if at[n] - steal[-1][0] >= 1.0:
            steal.append((at[n], _host_steal_s()))
        n += 1
    steal.append((time.time(), _host_steal_s()))
    return HostProbe(late[:n], at[:n], np.array(steal))


def _run_daemon_and_echo(
    config_text: str | None,
    port: int,
    seconds: float,
    warmup_s: float = 2.0,
    record: bool = False,
    reference: int = 0,
    realtime: int = 0,
) -> dict[str, Any]:
    """``daq run`` for ``seconds`` + ``daq echo --stats``; CPU of the daemon process.
    ``record``: the daemon also records every stream to an MCAP file (deleted after).
    ``reference``: meanwhile, that many raw zenoh streams at 1 kHz between two other
    processes (``_ref_pub_main``), whose latency the same host noise shapes.
    ``realtime``: SCHED_FIFO priority of the daemon (``[publish] realtime_priority``) and
    of the echo (``--realtime-priority``); 0: normal scheduling."""
    with tempfile.TemporaryDirectory() as tmp:
        args = [PY, "-m", "daq.cli", "run", "--duration", str(seconds + warmup_s)]
        if config_text is not None:
            cfg = Path(tmp) / "cell.toml"
            # a configured cell says "no recording" in its file (--no-record is the
            # emulated cell's flag: refused beside --config)
            off = (
                "" if record or "[recording]" in config_text else "\n[recording]\nenabled = false\n"
            )
            cfg.write_text(config_text + off)
            args += ["--config", str(cfg)]
            args += ["--record", str(Path(tmp) / "bench.mcap")] if record else []
        else:
            args += ["--listen", f"tcp/127.0.0.1:{port}"]
            args += ["--record", str(Path(tmp) / "bench.mcap")] if record else ["--no-record"]
        procs: list[subprocess.Popen] = []
        ref: list[subprocess.Popen] = []
        try:
            if reference:  # first: its start-up must not eat into the daemon's window
                rport = _free_port()
                span = seconds + warmup_s + 5.0  # and the daemon's and echo's start-up
                size = len(_sample_payload(1))  # a daemon message of one sample
                ref.append(_start_main(f"_ref_sub_main({rport}, {span + 30}, 3.0)", realtime))
                procs.append(ref[0])
                call = f"_ref_pub_main({rport}, {span}, {size}, 1000.0, {reference})"
                ref.append(_start_main(call, realtime))
                procs.append(ref[1])
            env = {**os.environ, "DAQ_PUBLISH_REALTIME_PRIORITY": str(realtime)}
            d = subprocess.Popen(
                args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
            )
            procs.append(d)
            assert d.stdout is not None
            started = json.loads(d.stdout.readline())
            e = subprocess.Popen(
                [PY, "-m", "daq.cli", "echo", "cell/**", "--stats", "--idle", "3",
                 "--stats-window", str(WINDOW_S), "--realtime-priority", str(realtime),
                 "--duration", str(seconds + warmup_s + 30), "--connect", f"tcp/127.0.0.1:{port}"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            procs.append(e)
            time.sleep(warmup_s)
            c0, s0, t0 = _tree_cpu_s(d.pid), _host_steal_s(), time.monotonic()
            probe = _probe_host(max(0.0, seconds - 0.5), realtime=realtime)
            c1, s1, t1 = _tree_cpu_s(d.pid), _host_steal_s(), time.monotonic()
            if d.poll() is not None:  # its workers' CPU would be missing, the window wrong
                raise RuntimeError("daq run ended inside the measurement window")
            out, err = d.communicate(timeout=seconds + 60)
            e_out, e_err = e.communicate(timeout=60)
            if d.returncode != 0:
                raise RuntimeError(f"daq run failed: {err[-2000:]}")
            if not e_out.strip():
                raise RuntimeError(f"daq echo failed: {e_err[-2000:]}")
            stats = json.loads(e_out.strip().splitlines()[-1])
            summary = json.loads(out.strip().splitlines()[-1])
            ref_stats = None
            if ref:
                ref[1].communicate(timeout=60)
                r_out, _ = ref[0].communicate(timeout=60)
                ref_stats = json.loads(r_out.strip().splitlines()[-1])
        finally:  # a failed step leaves no process behind
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
    return {
        "raw_reference": ref_stats,
        "started": started,
        "summary": summary,
        "echo": stats,
        "cpu_fraction": (c1 - c0) / (t1 - t0),
        "steal_cores": (s1 - s0) / (t1 - t0),
        "wakeup_late_ms": probe.summary(t1 - t0),
        "probe": probe,
    }


def daemon_throughput(
    batch: int, seconds: float, tx_queue: int | None = None, threads: bool = False
) -> dict[str, Any]:
    """``daq run`` with a source far faster than it (full batches back to back) → the same
    counting subscriber process as the raw measurement."""
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "cell.toml"
        # a source far ahead of the daemon: a growing backlog read MAX_READ samples at a
        # time, so the daemon, not the source, sets the rate
        cfg.write_text(_cell_config(port, 1, 1e9, batch, 0.0, MAX_READ, tx_queue, threads))
        d = subprocess.Popen(
            [PY, "-m", "daq.cli", "run", "--config", str(cfg), "--duration", str(seconds + 1)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert d.stdout is not None
        json.loads(d.stdout.readline())
        sink = _start_sink(port, DATA_KEY, seconds + 30)
        time.sleep(0.5)
        c0, t0 = _tree_cpu_s(d.pid), time.monotonic()
        time.sleep(max(0.1, seconds - 1.0))
        c1, t1 = _tree_cpu_s(d.pid), time.monotonic()
        _, err = d.communicate(timeout=seconds + 60)
        out, _ = sink.communicate(timeout=60)
        if d.returncode != 0:
            raise RuntimeError(f"daq run failed: {err[-2000:]}")
    res = json.loads(out.strip().splitlines()[-1])
    res["cpu_fraction"] = (c1 - c0) / (t1 - t0)
    return res


def throughput(
    seconds: float,
    batch: int = 100,
    rounds: int = 1,
    tx_queue: int | None = None,
    threads: bool = False,
) -> dict[str, Any]:
    """Daemon vs raw zenoh, ``rounds`` times each, alternating (raw, daemon, raw, ...), so
    both see the same machine; rates are the medians of the rounds (this machine swings
    ±30 % from one window to the next). ``tx_queue``: both sides' ``[zenoh]
    tx_queue_batches`` (None: the default)."""
    payload = _sample_payload(batch)
    raws: list[dict[str, Any]] = []
    dmns: list[dict[str, Any]] = []
    for _ in range(rounds):
        raws.append(raw_zenoh_throughput(payload, seconds, tx_queue=tx_queue))
        dmn = daemon_throughput(batch, seconds, tx_queue, threads)
        if dmn["messages"] < 2:  # the subscriber missed the run (a stalled start): once more
            dmn = daemon_throughput(batch, seconds, tx_queue, threads)
        dmns.append(dmn)

    def med(runs: list[dict[str, Any]], key: str) -> float:
        return float(np.median([r[key] for r in runs]))

    raw_sps, dmn_sps = med(raws, "samples_per_s"), med(dmns, "samples_per_s")
    return {
        "payload_bytes": len(payload),
        "batch_samples": batch,
        "rounds": rounds,
        "raw_msg_per_s": med(raws, "msg_per_s"),
        "raw_samples_per_s": raw_sps,
        "daemon_msg_per_s": med(dmns, "msg_per_s"),
        "daemon_samples_per_s": dmn_sps,
        # samples, not messages: a daemon message may carry fewer samples than a raw one
        "ratio": dmn_sps / raw_sps,
        "ratio_per_round": [
            d["samples_per_s"] / r["samples_per_s"] for r, d in zip(raws, dmns, strict=True)
        ],
        "daemon_cpu_fraction": med(dmns, "cpu_fraction"),
    }


def wildcard_cost(seconds: float, batch: int = 100, rounds: int = 3) -> dict[str, Any]:
    """Raw pub/sub rate with the subscriber on ``cell/**`` against the exact key, in
    alternating rounds: what a wildcard subscription costs the subscriber's zenoh."""
    payload = _sample_payload(batch)
    exact, wild = [], []
    for _ in range(rounds):
        exact.append(raw_zenoh_throughput(payload, seconds)["msg_per_s"])
        wild.append(raw_zenoh_throughput(payload, seconds, "cell/**")["msg_per_s"])
    return {
        "payload_bytes": len(payload),
        "exact_msg_per_s": float(np.median(exact)),
        "wildcard_msg_per_s": float(np.median(wild)),
        "ratio": float(np.median(wild)) / float(np.median(exact)),
        "ratio_per_round": [w / e for e, w in zip(exact, wild, strict=True)],
    }


def cell(
    seconds: float,
    emulated: bool = False,
    record: bool = False,
    devices: int = 3,
    reference: bool = False,
    threads: bool = False,
    realtime: int = 0,
) -> dict[str, Any]:
    """``reference``: raw zenoh streams at 1 kHz, one per device, run meanwhile between
    two other processes: the latency this host allows a minimal Python pub/sub now.
    ``realtime``: SCHED_FIFO priority of the daemon and the echo (0: normal)."""
    port = _free_port()
    # the daemon's default batching (500 samples, age 0: every read is published)
    text = None if emulated else _cell_config(port, devices, 1000.0, 500, 0.0, threads=threads)
    res = _run_daemon_and_echo(
        text,
        port,
        seconds,
        record=record,
        reference=devices if reference else 0,
        realtime=realtime,
    )
    keys = res["echo"]["keys"]
    lat_m = [v["latency_mapped_ms"] for v in keys.values() if "latency_mapped_ms" in v]
    lat_r = [v["latency_rx_ms"] for v in keys.values() if "latency_rx_ms" in v]
    samples = sum(v["samples"] for v in keys.values())
    # loss, attributed: samples missing by device sequence at the subscriber (whoever lost
    # them), messages missing by batch_seq (lost after the daemon encoded them: a failed
    # put, zenoh, the subscriber) and payloads the subscriber could not decode; the
    # daemon's own counters (last health document) say which part the device or its
    # driver lost before the daemon saw it
    loss = sum(v["seq_gaps"] for v in keys.values())
    lost_messages = sum(v["lost_batches"] for v in keys.values())
    undecodable = int(res["echo"].get("undecodable", 0))
    daemon_side: dict[str, Any] = {}
    for hk, doc in res["echo"].get("health", {}).items():
        dc = doc.get("driver_counters", {})
        daemon_side[doc.get("device", hk)] = {
            f: doc.get(f)
            for f in (
                "gaps",
                "samples_missing",
                "lost_samples",
                "time_gaps",
                "publish_errors",
                "messages_unsent",
                "reconnects",
                "scheduling",
            )
        } | {k: v for k, v in dc.items() if k in ("missed_syncs", "crc_errors", "timeouts")}
    return {
        "devices": len(keys),
        "seconds": seconds,
        "realtime_priority": realtime,
        "samples_received": samples,
        "loss_samples": loss,
        "loss_fraction": loss / max(1, samples + loss),
        "lost_messages": lost_messages,
        "undecodable": undecodable,
        "latency_p50_ms": max(x["p50"] for x in lat_m),
        "latency_p99_ms": max(x["p99"] for x in lat_m),
        "latency_rx_p50_ms": max(x["p50"] for x in lat_r),
        "latency_rx_p99_ms": max(x["p99"] for x in lat_r),
        "daemon_cpu_fraction": res["cpu_fraction"],
        # the host's scheduling noise meanwhile: a sleeping 1 kHz loop in this process
        "host_wakeup_late_ms": res["wakeup_late_ms"],
        # and CPU the hypervisor took away (cores, over all CPUs): not ours to fix
        "host_steal_cores": res["steal_cores"],
        # raw zenoh at the same rates meanwhile (None: not run): the host's latency floor
        "raw_reference_latency_ms": res["raw_reference"],
        **_windows_by_host_state(keys, res["probe"]),
        "daemon_side": daemon_side,
        "per_key": keys,
    }


# -- the live twin's hop --------------------------------------------------------------------

#: the calibration the benchmark's live twin runs (the twin of the small test campaign)
TWIN_CALIBRATED = Path(__file__).parents[1] / "tests" / "data" / "twin_calibrated_small"
GRATING_KEY = f"cell/{CELL}/robot/{ROBOT}/grating/samples"
TWIN_STATE_KEY = f"twin/{CELL}/robot/{ROBOT}/state"


def _twin_sub_main(port: int, warmup_s: float, seconds: float) -> None:
    """One subscriber to the daemon's grating key and the twin's state (exact keys, both
    through the daemon's endpoint), decoding on zenoh's callback thread; after
    ``warmup_s``, for ``seconds``: the daemon's latency (receive − mapped latch time,
    settled clock maps) and the twin's (its ``t_publish_ns`` − the same mapped time: device
    → twin output; and this subscriber's receive − mapped: device → twin → subscriber)."""
    from daq.bus import Receiver, open_session
    from daq.testing import loopback_sink

    session = open_session(loopback_sink(port))
    parts: dict[str, list[np.ndarray]] = {"daemon": [], "twin_out": [], "twin_sub": []}
    counts = {"grating_unsettled": 0, "grating": 0, "twin": 0}
    t_from = time.time_ns() + int(warmup_s * 1e9)
    t_to = t_from + int(seconds * 1e9)

    def on_batch(got: Any) -> None:
        if not t_from <= got.t_recv_ns < t_to:
            return
        c = got.columns
        t_map = c["t_mapped_ns"]
        if got.key == GRATING_KEY:
            ok = c["t_mapped_ok"] == 1
            counts["grating"] += len(t_map)
            counts["grating_unsettled"] += int(np.count_nonzero(~ok))
            parts["daemon"].append(got.t_recv_ns - t_map[ok])
        elif got.key == TWIN_STATE_KEY:
            counts["twin"] += len(t_map)
            parts["twin_out"].append(c["t_publish_ns"] - t_map)
            parts["twin_sub"].append(got.t_recv_ns - t_map)

    rx = Receiver(session, [GRATING_KEY, TWIN_STATE_KEY], on_batch=on_batch)
    print(json.dumps({"ready": True}), flush=True)
    end = time.monotonic() + warmup_s + seconds + 0.5  # bounded by time
    while time.monotonic() < end:
        time.sleep(0.1)
    rx.close()
    session.close()
    out: dict[str, Any] = dict(counts)
    for name, ps in parts.items():
        v = np.concatenate(ps) / 1e6 if ps else np.zeros(0)
        out[name] = (
            {
                "p50": float(np.percentile(v, 50)),
                "p99": float(np.percentile(v, 99)),
                "max": float(v.max()),
                "n": int(v.size),
            }
            if v.size
            else None
        )
    print(json.dumps(out), flush=True)


def _twin_cell_config(port: int) -> str:
    # the fake box starts at the calibration's Home counts and moves 1 count per sample
    # (0.1-0.5 °/s per joint): a slow steady move in the calibrated range
    home = json.loads((TWIN_CALIBRATED / "phases.json").read_text())["home_counts"]
    counts = ", ".join(str(round(c)) for c in home)
    return (
        f'[cell]\nname = "{CELL}"\nrobot = "{ROBOT}"\n\n'
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n\n'
        '[[device]]\nname = "grating"\ndriver = "daq.testing:FakeGratingDriver"\n'
        'url = "fake://grating"\nrate_hz = 1000.0\n'
        f"options = {{ rate_hz = 1000.0, counts = [{counts}] }}\n"
    )


def twin_round(
    seconds: float,
    radius_deg: float,
    warmup_s: float = 8.0,
    tree: str | None = None,
    tracking: bool = True,
) -> dict[str, Any]:
    """``daq run`` (a fake six-joint grating box at 1 kHz, in the daemon's process) → the
    live twin (``twin run --from``, a client of the daemon, ``--effects-radius-deg``) →
    one subscriber process on the daemon's endpoint (``_twin_sub_main``): the daemon's
    latency and the twin's, in the same seconds, plus the twin's CPU and the host's
    steal. ``radius_deg = 0``: the full effect predictor per batch. ``tree``: run the
    twin of another checkout of this repository (e.g. a worktree of an older commit;
    ``radius_deg`` is then not passed: the twin as that commit had it). ``tracking``
    False: ``--no-tracking`` (the calibration carries ``[tracking]``, so the twin follows
    the robot by default: the tracker stream subscribed, the grating samples kept and
    searched for dwells; the fake box moves steadily and has no tracker, so no dwell
    updates the model here: what is measured is the per-batch cost of following)."""
    port = _free_port()
    span = warmup_s + seconds
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "cell.toml"
        cfg.write_text(_twin_cell_config(port))
        procs: list[subprocess.Popen] = []
        try:
            d = subprocess.Popen(
                [PY, "-m", "daq.cli", "run", "--config", str(cfg), "--duration", str(span + 20)],
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            )  # fmt: skip
            procs.append(d)
            assert d.stdout is not None
            json.loads(d.stdout.readline())
            cmd = [PY, "-m", "calibration.cli", "run", "--from", str(TWIN_CALIBRATED),
                   "--out", str(Path(tmp) / "twin"), "--connect", f"tcp/127.0.0.1:{port}",
                   "--publish-s", str(span + 10), "--quiet"]  # fmt: skip
            if tree is None:
                cmd += ["--effects-radius-deg", str(radius_deg)]
                cmd += [] if tracking else ["--no-tracking"]
            env = dict(os.environ)
            if tree is not None:
                env["PYTHONPATH"] = str(Path(tree).resolve())
            tw = subprocess.Popen(
                cmd,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                cwd=tree,
                env=env,
            )
            procs.append(tw)
            assert tw.stdout is not None
            line = tw.stdout.readline()  # {"twin": "live", ...} once it publishes
            if not line.startswith('{"twin"'):
                raise RuntimeError(f"twin run did not start: {tw.stderr.read()[-2000:]}")
            sub = _start_main(f"_twin_sub_main({port}, {warmup_s}, {seconds})")
            procs.append(sub)
            time.sleep(warmup_s)
            c0, s0, t0 = _cpu_s(tw.pid), _host_steal_s(), time.monotonic()
            probe = _probe_host(max(0.0, seconds - 0.5))
            c1, s1, t1 = _cpu_s(tw.pid), _host_steal_s(), time.monotonic()
            out, _ = sub.communicate(timeout=seconds + 60)
            res = json.loads(out.strip().splitlines()[-1])
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
    res.update(
        radius_deg=radius_deg,
        tree=tree,
        tracking=tracking,
        twin_cpu_fraction=(c1 - c0) / (t1 - t0),
        host_steal_cores=(s1 - s0) / (t1 - t0),
        host_wakeup_late_ms=probe.summary(t1 - t0),
    )
    return res


def twin_hop(seconds: float, rounds: int = 2, ref_tree: str | None = None) -> dict[str, Any]:
    """Alternating rounds: the twin as it is (``--effects-radius-deg 0.25``, tracking on),
    the same twin with ``--no-tracking``, and the reference, the same twin with the full
    effect predictor per batch (radius 0: the twin's work per batch before), and with
    ``ref_tree`` the twin of that checkout; each beside the daemon's own latency of that
    round."""
    out: dict[str, Any] = {"rounds": []}
    kinds = [
        ("twin", 0.25, None, True),
        ("twin_no_tracking", 0.25, None, False),
        ("reference_full_predictor", 0.0, None, True),
    ]
    if ref_tree is not None:
        kinds.append(("reference_tree", -1.0, ref_tree, True))
    for _ in range(rounds):
        for name, radius, tree, tracking in kinds:
            res = twin_round(seconds, radius, tree=tree, tracking=tracking)
            out["rounds"].append({**res, "kind": name})
    for name, *_ in kinds:
        rs = [r for r in out["rounds"] if r["kind"] == name and r["twin_out"]]
        if not rs:
            continue
        out[name] = {
            "device_to_twin_p50_ms": float(np.median([r["twin_out"]["p50"] for r in rs])),
            "device_to_twin_p99_ms": float(np.median([r["twin_out"]["p99"] for r in rs])),
            "daemon_p50_ms": float(np.median([r["daemon"]["p50"] for r in rs])),
            "daemon_p99_ms": float(np.median([r["daemon"]["p99"] for r in rs])),
            "twin_hop_p50_ms": float(
                np.median([r["twin_out"]["p50"] - r["daemon"]["p50"] for r in rs])
            ),
            "twin_cpu": float(np.median([r["twin_cpu_fraction"] for r in rs])),
        }
    return out


#: steal bins (cores) the soak's windows are grouped by
STEAL_BINS = (("<0.01", 0.0, 0.01), ("0.01-0.05", 0.01, 0.05), ("0.05-0.2", 0.05, 0.2),
              (">=0.2", 0.2, float("inf")))  # fmt: skip


def _windows_by_host_state(keys: dict[str, Any], probe: HostProbe) -> dict[str, Any]:
    """The latency per ``WINDOW_S`` window (worst device) beside what the host probe saw
    in it; the windows grouped by whether the probe was ever stalled beyond 5 ms, and by
    the hypervisor's steal in them (``STEAL_BINS``): a diagnosis of the run's p99, which
    stays the figure of record."""
    host = probe.windows(WINDOW_S)
    by_t: dict[int, list[dict[str, float]]] = {}
    for v in keys.values():
        for w in v.get("latency_mapped_ms_windows", []):
            by_t.setdefault(int(w["t_s"]), []).append(w)
    rows = []
    for t0, h in sorted(host.items()):
        if t0 not in by_t:
            continue
        lat = by_t[t0]
        rows.append({"t_utc_s": t0, "latency_p99_ms": max(w["p99"] for w in lat),
                     "latency_max_ms": max(w["max"] for w in lat), **h})  # fmt: skip

    def group(members: list[dict[str, Any]]) -> dict[str, Any]:
        p99 = [r["latency_p99_ms"] for r in members]
        if not p99:
            return {"windows": 0}
        return {"windows": len(p99), "p99_under_5ms": sum(p < 5.0 for p in p99),
                "latency_p99_ms_median": float(np.median(p99)),
                "latency_p99_ms_max": max(p99)}  # fmt: skip

    steal_known = [r for r in rows if r["steal_cores"] is not None]
    return {
        "windows": rows,
        "windows_host_quiet": group([r for r in rows if r["stalled_fraction_over_5ms"] == 0]),
        "windows_host_stalled": group([r for r in rows if r["stalled_fraction_over_5ms"] > 0]),
        "windows_by_steal_cores": {
            name: group([r for r in steal_known if lo <= r["steal_cores"] < hi])
            for name, lo, hi in STEAL_BINS
        },
    }


def run(
    quick: bool = True,
    emulated: bool = False,
    tx_queue: int | None = None,
    threads: bool = False,
) -> list[dict[str, Any]]:
    """Flat rows for ``python -m benchmarks`` (quick: a smoke run of a few seconds)."""
    from daq.config import ZenohConfig

    queue = ZenohConfig().tx_queue_batches if tx_queue is None else tx_queue
    rows: list[dict[str, Any]] = []
    for batch in (100,) if quick else (100, 500, 1000):
        t = throughput(
            1.5 if quick else 5.0,
            batch,
            rounds=1 if quick else 3,
            tx_queue=tx_queue,
            threads=threads,
        )
        rows.append(
            {
                "benchmark": f"throughput vs raw zenoh, {batch}-sample batches",
                "payload_bytes": t["payload_bytes"],
                "daemon_msg_per_s": t["daemon_msg_per_s"],
                "raw_msg_per_s": t["raw_msg_per_s"],
                "daemon_samples_per_s": t["daemon_samples_per_s"],
                "raw_samples_per_s": t["raw_samples_per_s"],
                "ratio_vs_raw": t["ratio"],
                "ratio_per_round": t["ratio_per_round"],
                "daemon_cpu": t["daemon_cpu_fraction"],
                "tx_queue_batches": queue,
                "note": "same messages, same subscriber process on the exact key, BLOCK",
            }
        )
    c = cell(3.0 if quick else 60.0, emulated=emulated, reference=not quick, threads=threads)
    rows.append(
        {
            "benchmark": "cell 3 devices at 1 kHz, "
            + ("emulated (sim-cell)" if emulated else "fake devices"),
            "seconds": c["seconds"],
            "samples": c["samples_received"],
            "loss_samples": c["loss_samples"],
            "lost_messages": c["lost_messages"],
            "undecodable": c["undecodable"],
            "latency_p50_ms": c["latency_p50_ms"],
            "latency_p99_ms": c["latency_p99_ms"],
            "rx_to_sub_p50_ms": c["latency_rx_p50_ms"],
            "rx_to_sub_p99_ms": c["latency_rx_p99_ms"],
            "daemon_cpu": c["daemon_cpu_fraction"],
            "host_wakeup_late_p99_ms": c["host_wakeup_late_ms"]["p99"],
            "host_steal_cores": c["host_steal_cores"],
            "raw_zenoh_p99_ms": (c["raw_reference_latency_ms"] or {}).get("p99"),
            "note": "latency: subscriber receive - mapped device latch time (worst device)",
        }
    )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_daq", description=__doc__)
    ap.add_argument("--full", action="store_true", help="longer windows")
    ap.add_argument("--soak", type=float, metavar="S", help="only the cell benchmark, S seconds")
    ap.add_argument("--emulated", action="store_true", help="the emulated cell (sim-cell)")
    ap.add_argument("--record", action="store_true", help="--soak: the daemon also records MCAP")
    ap.add_argument(
        "--devices", type=int, default=3, help="--soak: fake devices at 1 kHz (default 3)"
    )
    ap.add_argument(
        "--reference",
        action="store_true",
        help="--soak: run a raw zenoh latency reference alongside (one 1 kHz stream per "
        "device between two other processes; adds ~0.3 core of load)",
    )
    ap.add_argument(
        "--threads",
        action="store_true",
        help="the daemon's devices in threads of one process ([publish] process_per_device "
        "= false) instead of a worker process each",
    )
    ap.add_argument(
        "--realtime",
        type=int,
        default=0,
        metavar="N",
        help="--soak: the daemon ([publish] realtime_priority) and the echo "
        "(--realtime-priority) under SCHED_FIFO priority N (needs root or CAP_SYS_NICE)",
    )
    ap.add_argument(
        "--windows",
        metavar="FILE",
        help=f"--soak: write the latency and host figures per {WINDOW_S} s window to FILE "
        "(JSON lines)",
    )
    ap.add_argument(
        "--wildcard",
        action="store_true",
        help="only raw zenoh: subscriber on cell/** vs on the exact key (3 rounds of 5 s)",
    )
    ap.add_argument(
        "--tx-queue",
        type=int,
        metavar="N",
        help="throughput: [zenoh] tx_queue_batches of both sides (default: the daemon's)",
    )
    ap.add_argument(
        "--twin",
        type=float,
        metavar="S",
        help="only the live twin's hop: alternating S-second rounds of the twin, of the twin "
        "with --no-tracking and of the twin with the full effect predictor per batch, each "
        "beside the daemon's latency",
    )
    ap.add_argument("--rounds", type=int, default=2, help="--twin: rounds of each (2)")
    ap.add_argument(
        "--twin-ref-tree",
        metavar="DIR",
        help="--twin: also rounds of the twin of this checkout (a worktree of an older commit)",
    )
    args = ap.parse_args(argv)
    if args.twin:
        res = twin_hop(args.twin, args.rounds, args.twin_ref_tree)
        print(json.dumps({"twin_hop": res}, indent=1))
        return 0
    if args.wildcard:
        print(json.dumps({"wildcard_subscription": wildcard_cost(5.0)}))
        return 0
    if args.soak:
        res = cell(
            args.soak,
            emulated=args.emulated,
            record=args.record,
            devices=args.devices,
            reference=args.reference,
            threads=args.threads,
            realtime=args.realtime,
        )
        res["per_key"] = {
            k.rsplit("/", 2)[-2]: {
                f: v.get(f) for f in ("samples", "seq_gaps", "lost_batches", "unsettled")
            }
            | {"latency_p99_ms": v.get("latency_mapped_ms", {}).get("p99")}
            for k, v in res["per_key"].items()
        }
        rows = res.pop("windows")
        if args.windows:
            with open(args.windows, "w", encoding="utf-8") as fh:
                fh.writelines(json.dumps(r) + "\n" for r in rows)
        print(json.dumps({"soak": res}, indent=1))
        lost = res["loss_samples"] + res["lost_messages"] + res["undecodable"]
        return 0 if lost == 0 else 1
    rows = run(
        quick=not args.full, emulated=args.emulated, tx_queue=args.tx_queue, threads=args.threads
    )
    for r in rows:
        print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
