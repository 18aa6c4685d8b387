"""``twin view`` while the twin runs at 1 kHz: frames per second, and how far behind it is.

A publisher process stands in for the live twin and the daemon: on a zenoh peer on
loopback it publishes, every millisecond, one sample each of ``twin/<cell>/robot/<robot>/
state`` (the live twin's columns: joint angles moving through the arm's range, the TCP,
``t_publish_ns``), the grating counts and the tracker point, each as one
``daq.columnar.v1`` batch, as the live twin does at the grating rate. In this process the
view (:class:`view.sources.LiveSource` + :class:`view.server.TwinView`, what ``twin
view --connect`` runs) subscribes as a zenoh client and draws at ``fps``, with headless
Chromium showing the page when it is installed (the scene messages then really go to a
browser). Measured over ``seconds`` after a warm-up:

* ``frames_per_s``: scene updates sent to the page per second;
* ``update_ms_p50/p99``: computing and sending one update (geometry, ghost, markers);
* ``drawn_age_ms_p50/p99``: when the frame was sent minus when the twin published the
  sample it draws: the view's lag behind the twin (zenoh delivery plus up to one frame);
* ``twin_samples_per_s``: the twin's samples the view received (all of them: each only
  replaces the latest, none waits for a frame).

Run standalone: ``.venv/bin/python -m benchmarks.bench_view [--seconds S] [--fps F]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

CELL, ROBOT = "bench", "robot1"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def publish(endpoint: str, seconds: float, rate_hz: float = 1000.0) -> None:
    """The stand-in twin and daemon (a process of its own): one sample per key per
    period, for ``seconds``."""
    from calibration.model.description import load_robot
    from calibration.model.kinematics import KinematicModel, tcp_positions
    from daq.bus import ChannelPublisher, SchemaServer, open_session
    from daq.columnar import Column, StreamSchema
    from daq.config import ZenohConfig

    robot = load_robot("kr500")
    n = robot.n_joints
    model = KinematicModel.from_description(robot)
    # one period of motion, precomputed: every joint swings within its limits
    steps = int(rate_hz * 10)
    phase = np.linspace(0.0, 2 * np.pi, steps, endpoint=False)[:, None]
    lo = np.array([j.lower_deg for j in robot.joints])
    hi = np.array([j.upper_deg for j in robot.joints])
    q = (lo + hi) / 2 + 0.3 * (hi - lo) / 2 * np.sin(phase * np.arange(1, n + 1))
    tcp = tcp_positions(model, np.radians(q))
    counts = np.rint(q * 10000.0).astype(np.int64) % (1 << 32)
    session = open_session(ZenohConfig(mode="peer", listen=(endpoint,), connect=()))
    base = f"{CELL}/robot/{ROBOT}"
    common = (
        Column("seq", "uint64", (), "", None, ""),
        Column("epoch", "int32", (), "", None, ""),
        Column("t_device_us", "int64", (), "us", None, ""),
        Column("t_host_rx_ns", "int64", (), "ns", "host_utc", ""),
        Column("t_mapped_ns", "int64", (), "ns", "host_utc", ""),
        Column("t_mapped_ok", "uint8", (), "", None, ""),
    )
    strips = tuple(Column(f"grating{k}_counts", "int64", (), "", None, "") for k in range(1, n + 1))
    grating = StreamSchema(
        f"cell/{base}/grating/samples", (*common, *strips), {"cell": CELL, "robot": ROBOT}
    )
    tracker = StreamSchema(
        f"cell/{base}/tracker/samples",
        (*common, *(Column(c, "float64", (), "mm", None, "") for c in ("x_mm", "y_mm", "z_mm"))),
        {"cell": CELL, "robot": ROBOT, "device": "tracker"},
    )  # fmt: skip
    twin = StreamSchema(
        f"twin/{base}/state",
        (
            Column("seq", "uint64", (), "", None, ""),
            Column("t_mapped_ns", "int64", (), "ns", "host_utc", ""),
            Column("t_publish_ns", "int64", (), "ns", "host_utc", ""),
            Column("q_deg", "float64", (n,), "deg", None, ""),
            Column("tcp_mm", "float64", (3,), "mm", None, ""),
        ),
        {"cell": CELL, "robot": ROBOT},
    )
    cell_schemas = SchemaServer(session, "cell")
    twin_schemas = SchemaServer(session, "twin")
    pubs = [
        ChannelPublisher(session, grating, schemas=cell_schemas),
        ChannelPublisher(session, tracker, schemas=cell_schemas),
        ChannelPublisher(session, twin, schemas=twin_schemas),
    ]
    print(json.dumps({"publishing": endpoint}), flush=True)
    period = 1.0 / rate_hz
    start = time.monotonic()
    i = 0
    while time.monotonic() - start < seconds:
        k = i % steps
        now = time.time_ns()
        one = {"seq": np.array([i], np.uint64), "t_mapped_ns": np.array([now], np.int64)}
        dev = {
            **one,
            "epoch": np.zeros(1, np.int32),
            "t_device_us": np.array([i * 1000], np.int64),
            "t_host_rx_ns": np.array([now], np.int64),
            "t_mapped_ok": np.ones(1, np.uint8),
        }
        pubs[0].publish(
            {**dev, **{f"grating{j + 1}_counts": counts[k : k + 1, j] for j in range(n)}}
        )
        pubs[1].publish({**dev, "x_mm": tcp[k : k + 1, 0], "y_mm": tcp[k : k + 1, 1],
                         "z_mm": tcp[k : k + 1, 2]})  # fmt: skip
        pubs[2].publish(
            {**one, "t_publish_ns": np.array([time.time_ns()], np.int64),
             "q_deg": q[k : k + 1], "tcp_mm": tcp[k : k + 1]}
        )  # fmt: skip
        i += 1
        # paced on the clock: a late period is made up at once, never drifts
        wait = start + i * period - time.monotonic()
        if wait > 0:
            time.sleep(wait)
    for p in pubs:
        p.close()
    cell_schemas.close()
    twin_schemas.close()
    session.close()


def _browser(url: str, profile: str) -> subprocess.Popen | None:
    chromium = shutil.which("chromium")
    if chromium is None:
        return None
    return subprocess.Popen(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
         "--no-first-run", f"--user-data-dir={profile}", "--window-size=1280,800",
         "--remote-debugging-port=0", url],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip


def _stop(proc: subprocess.Popen | None) -> None:
    if proc is not None and proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


def measure(seconds: float, fps: float, warmup_s: float = 3.0) -> dict[str, Any]:
    from daq.bus import open_session
    from daq.config import ZenohConfig
    from view.model import nominal_twin
    from view.server import TwinView
    from view.sources import LiveSource

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    root = Path(__file__).resolve().parents[1]
    pub = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.bench_view", "--publish", endpoint,
         "--seconds", str(seconds + warmup_s + 10)],
        cwd=root, stdout=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    session = source = view = browser = None
    profile = tempfile.mkdtemp(prefix="bench-view-")
    try:
        line = pub.stdout.readline() if pub.stdout else ""
        if "publishing" not in line:
            raise RuntimeError(f"the publisher did not start (exit {pub.poll()})")
        session = open_session(ZenohConfig(mode="client", listen=(), connect=(endpoint,)))
        twin = nominal_twin("kr500")
        source = LiveSource(session, twin)
        view = TwinView(source, twin, title="bench", port=0, fps=fps)
        url = view.start()
        browser = _browser(url, profile)
        view.run(warmup_s)
        frames0, batches0 = view.stats.frames, source.batches
        view._age_ms.clear()
        view._update_ms.clear()
        t0 = time.monotonic()
        stats = view.run(seconds)
        span = time.monotonic() - t0
        age = np.array(view._age_ms)
        upd = np.array(view._update_ms)
        return {
            "benchmark": f"twin view at {fps:g} fps, twin at 1 kHz",
            "seconds": round(span, 2),
            "frames_per_s": (stats.frames - frames0) / span,
            "update_ms_p50": float(np.percentile(upd, 50)),
            "update_ms_p99": float(np.percentile(upd, 99)),
            "drawn_age_ms_p50": float(np.percentile(age, 50)) if age.size else float("nan"),
            "drawn_age_ms_p99": float(np.percentile(age, 99)) if age.size else float("nan"),
            # three keys per period (grating, tracker, twin): a third of the batches
            "twin_samples_per_s": (source.batches - batches0) / 3 / span,
            "browser": "chromium headless" if browser is not None else "none",
        }
    finally:
        if view is not None:
            view.close()
        if source is not None:
            source.close()
        if session is not None:
            session.close()
        _stop(browser)
        _stop(pub)
        shutil.rmtree(profile, ignore_errors=True)


def run(quick: bool) -> list[dict[str, Any]]:
    seconds = 2.0 if quick else 20.0
    return [measure(seconds, fps, warmup_s=1.0 if quick else 3.0) for fps in (40.0, 60.0)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_view", description=__doc__)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--fps", type=float, action="append")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--publish", metavar="EP", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.publish:
        publish(args.publish, args.seconds)
        return 0
    from benchmarks import format_table

    if args.quick:
        rows = run(quick=True)
    else:
        rows = [measure(args.seconds, fps) for fps in (args.fps or [40.0, 60.0])]
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
