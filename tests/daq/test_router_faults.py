"""Faults of a cell over a router, on loopback (docs/deployment.md, "Faults"): the router
restarts under a daemon whose devices run in worker processes and a subscriber that
records (``daq record``), and the daemon's host clock is 0.5 s off (the test hook
``DAQ_TEST_CLOCK_SHIFT_S``).

* each device's published health says ``messages_unrouted`` (the daemon counts, its
  workers publish), the last one equal to the daemon's stop summary;
* the daemon measures its clock against the router's, says so in one line, in each
  device's health (``host_clock``) and in its summary;
* the subscriber's recording has a hole record per data key, its count what the
  recording lacks (``batch_seq``), its reason the router's restart; ``daq info`` and
  ``daq replay`` report them (the replay does not republish them).

``daq router`` on a free 127.0.0.1 port, plain TCP (the TLS and access-control side is
tests/daq/test_cell_hosts.py's, in network namespaces).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from daq.bus import open_session
from daq.columnar import read_header
from daq.host_clock import measure, serve_clock
from daq.recording_holes import HOLES_TOPIC, KIND_HOLES
from daq.recording_reader import read_recording
from daq.replay import replay
from daq.testing import free_port, loopback_source

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]
SHIFT_S = 0.5
DEVICES = ("d1", "d2")


def _router_json5(port: int) -> str:
    return (
        f'{{ mode: "router", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }},\n'
        "  scouting: { multicast: { enabled: false }, gossip: { enabled: false } } }\n"
    )


def _cell_toml(port: int) -> str:
    out = [
        '[cell]\nname = "w"\nrobot = "r1"\n'
        f'[zenoh]\nmode = "client"\nconnect = ["tcp/127.0.0.1:{port}"]\n'
        "[publish]\nhealth_period_s = 0.5\n"
    ]
    for i, name in enumerate(DEVICES):
        out.append(
            f'[[device]]\nname = "{name}"\ndriver = "daq.testing:FakeDriver"\n'
            f'url = "fake://{i}"\nrate_hz = 500\njoints = [1, 2, 3]\n'
        )
    return "\n".join(out)


class _Procs:
    def __init__(self, work: Path) -> None:
        self.work = work
        self.procs: list[subprocess.Popen[str]] = []

    def daq(
        self, name: str, *args: str, env: dict[str, str] | None = None
    ) -> subprocess.Popen[str]:
        """``daq ARGS`` in ``work``, stderr to ``<name>.stderr`` (never a full pipe)."""
        base = {k: v for k, v in os.environ.items() if not k.startswith("DAQ_")}
        with open(self.work / f"{name}.stderr", "w", encoding="utf-8") as err:
            p = subprocess.Popen(
                [sys.executable, "-m", "daq.cli", *args],
                cwd=self.work,
                env={**base, "PYTHONPATH": str(ROOT), **(env or {})},
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
            )
        self.procs.append(p)
        return p

    def stderr(self, name: str) -> str:
        return (self.work / f"{name}.stderr").read_text(encoding="utf-8")

    def kill_all(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
                p.wait(5)


def _first_line(p: subprocess.Popen[str]) -> dict:
    assert p.stdout is not None
    line = p.stdout.readline()
    assert line, "the process ended without its first line"
    return json.loads(line)


def _stop(p: subprocess.Popen[str]) -> list[dict]:
    """SIGTERM, then its remaining stdout lines as JSON."""
    p.send_signal(signal.SIGTERM)
    out, _ = p.communicate(timeout=30)
    assert p.returncode == 0
    return [json.loads(x) for x in out.splitlines() if x.startswith("{")]


def _health(path: Path, device: str) -> list[dict]:
    key = f"cell/w/robot/r1/{device}/health"
    return [json.loads(m.data) for m in read_recording(path).messages_iter({key})]


def test_router_restart_holes_unrouted_and_a_clock_off(tmp_path: Path) -> None:
    port = free_port()
    (tmp_path / "router.json5").write_text(_router_json5(port), encoding="utf-8")
    (tmp_path / "cell.toml").write_text(_cell_toml(port), encoding="utf-8")
    procs = _Procs(tmp_path)
    try:
        router = procs.daq("router1", "router", "--config", "router.json5")
        assert _first_line(router)["clock_key"] == "daq/clock"
        daemon = procs.daq(
            "daemon",
            *("run", "--config", "cell.toml", "--record", "dev.mcap"),
            env={"DAQ_TEST_CLOCK_SHIFT_S": str(SHIFT_S)},
        )
        keys = _first_line(daemon)["keys"]
        z = ("--mode", "client", "--connect", f"tcp/127.0.0.1:{port}")
        rec = procs.daq("record", "record", "cell/w/**", "-o", "sub.mcap", *z)
        _first_line(rec)
        time.sleep(3.0)  # the recorder receiving, the clock measured
        _stop(router)
        time.sleep(1.5)  # the router down
        router = procs.daq("router2", "router", "--config", "router.json5")
        _first_line(router)
        # clients reconnect by themselves; the recorder writes each hole once the
        # publisher's health after it came (bounded: a loaded host reconnects slowly)
        t_end = time.monotonic() + 30.0
        while procs.stderr("record").count("hole of") < len(keys) and time.monotonic() < t_end:
            time.sleep(0.2)
        summary = _stop(daemon)[-1]
        time.sleep(0.5)
        recorded = _stop(rec)[-1]
        _stop(router)
    finally:
        procs.kill_all()
    dev, sub = tmp_path / "dev.mcap", tmp_path / "sub.mcap"

    # messages_unrouted: in the published health of each worker's device, its last
    # value the daemon's summary; the subscriber saw it after the restart
    for name in DEVICES:
        unrouted = summary["devices"][name]["messages_unrouted"]
        assert unrouted > 0, summary
        own = [d for d in _health(dev, name) if "messages_unrouted" in d]
        assert own and own[-1]["messages_unrouted"] == unrouted, (name, own[-1:], unrouted)
        seen = [d.get("messages_unrouted", 0) for d in _health(sub, name)]
        assert max(seen) > 0, (name, seen)

    # the clock: measured against the router's, 0.5 s ahead, said once, in health
    clock = summary["host_clock"]
    assert clock is not None and not clock["within_tolerance"], clock
    assert abs(clock["offset_ms"] - SHIFT_S * 1e3) <= clock["uncertainty_ms"] + 5.0, clock
    said = [x for x in procs.stderr("daemon").splitlines() if "clock is" in x]
    assert len(said) == 1 and "ms ahead of the router's" in said[0], said
    docs = [d for d in _health(dev, "d1") if d.get("host_clock")]
    assert docs and abs(docs[-1]["host_clock"]["offset_ms"] - 500.0) < 50.0, docs[-1:]

    # the holes: one per data key, its count what the recording lacks, the reason the
    # router's restart (both ends lost it)
    sub_rec = read_recording(sub)
    holes = [json.loads(m.data) for m in sub_rec.messages_iter({HOLES_TOPIC})]
    channels = {c.topic: c for c in sub_rec.channels.values()}  # filled by the pass
    assert {h["key"] for h in holes} == set(keys), (holes, keys)
    assert recorded["holes"] == len(holes)
    for key in keys:
        seq = np.array(
            [read_header(m.data).batch_seq for m in read_recording(sub).messages_iter({key})]
        )
        lacking = int(np.sum(np.diff(seq) - 1))
        mine = [h for h in holes if h["key"] == key]
        assert lacking > 0 and sum(h["count"] for h in mine) == lacking, (key, mine, lacking)
        for h in mine:
            assert h["reason"] == "router_down", h
            assert h["recorder_lost_router"] and h["publisher_unrouted"] > 0, h
            assert h["last_missing"] - h["first_missing"] + 1 == h["count"]
        # what it lacks is what the daemon could not hand to a router (one key a device),
        # within the router watch's 10 ms look either side and the recorder reconnecting
        # a few ms after the daemon (≈ 1 000 messages a second here): 2 %
        unrouted = summary["devices"][key.split("/")[-2]]["messages_unrouted"]
        assert abs(lacking - unrouted) <= max(10, 0.02 * unrouted), (key, lacking, unrouted)
    assert channels[HOLES_TOPIC].metadata["daq.kind"] == KIND_HOLES

    # daq info lists them; the daemon's own recording has none (nothing lost there)
    info = subprocess.run(
        [sys.executable, "-m", "daq.cli", "info", str(sub)],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["holes"] == holes
    # a replay reports them and does not republish them
    got = replay(str(sub), loopback_source(free_port()), fast=True)
    assert got["holes"] == holes and HOLES_TOPIC not in got["topics"], got
    assert set(keys) <= set(got["topics"])
    dev_rec = read_recording(dev)
    assert not any(m.topic == HOLES_TOPIC for m in dev_rec.messages_iter())
    assert dev_rec.channels and HOLES_TOPIC not in {c.topic for c in dev_rec.channels.values()}


def test_a_clock_is_measured_by_round_trips_to_the_reference() -> None:
    """daq.host_clock on one session: the offset of a clock 250 ms ahead, within its
    uncertainty (half the shortest round trip); no reference: no estimate."""
    session = open_session(loopback_source(free_port()))
    try:
        assert measure(session, time.time_ns, 0.01, rounds=2) is None  # nobody answers
        served = serve_clock(session, "test")
        ahead = measure(session, lambda: time.time_ns() + 250_000_000, 0.01)
        same = measure(session, time.time_ns, 0.01)
        served.undeclare()
    finally:
        session.close()
    assert ahead is not None and same is not None
    assert abs(ahead.offset_ms - 250.0) <= ahead.uncertainty_ms + 1.0, ahead
    assert not ahead.within_tolerance and ahead.reference == "test"
    assert abs(same.offset_ms) <= same.uncertainty_ms + 1.0 and same.within_tolerance, same
    assert ahead.rtt_ms > 0 and abs(ahead.rtt_ms - 2 * ahead.uncertainty_ms) < 0.01
