"""Two cells on one router, on loopback: ``daq echo --cell`` and ``twin view --cell`` take
their cell's keys only; without ``--cell`` the view refuses a bus with several cells and
follows the only one up (docs/deployment.md "Several cells", docs/view.md).

One ``daq router`` (plain TCP on a free 127.0.0.1 port: the keys, not TLS, are what is
tested here; tests/daq/test_router_cells.py has the router's TLS and access control), two
daemons (``daq run``, one fake device each at 200 Hz, cells ``cellA`` and ``cellB``),
both clients of the router, and a live twin's health per cell put from this process.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from daq.testing import daq_cli, free_port

ROOT = Path(__file__).resolve().parents[2]
CELLS = ("cellA", "cellB")
#: the rate each cell's live twin says in its health: tells the cells apart at the view
TWIN_RATE = {"cellA": 111.0, "cellB": 222.0}


def _cell_toml(cell: str, router: int) -> str:
    return (
        f'[cell]\nname = "{cell}"\n'
        f'[zenoh]\nmode = "client"\nconnect = ["tcp/127.0.0.1:{router}"]\n'
        '[[device]]\nname = "dev1"\ndriver = "daq.testing:FakeDriver"\nurl = "fake://1"\n'
        "rate_hz = 200.0\noptions = { rate_hz = 200.0 }\n[recording]\nenabled = false\n"
    )


def _client(router: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{router}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


@dataclass
class Plant:
    router: int  # the router's port
    daemons: dict[str, subprocess.Popen[str]]
    twin: zenoh.Session  # puts each cell's twin health, twice a second

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.router}"


def _stop(p: subprocess.Popen[str]) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()


@pytest.fixture(scope="module")
def plant(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Plant]:
    work = tmp_path_factory.mktemp("cells")
    port = free_port()
    conf = {
        "mode": "router",
        "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    (work / "router.json5").write_text(json.dumps(conf), encoding="utf-8")
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    procs = [daq_cli("router", "--config", "router.json5", cwd=work, env=env)]
    stop = threading.Event()
    twin = None
    thread = None
    try:
        assert procs[0].stdout is not None
        assert json.loads(procs[0].stdout.readline())["daq"] == "router"
        daemons = {}
        for cell in CELLS:  # both starting at once
            (work / f"{cell}.toml").write_text(_cell_toml(cell, port), encoding="utf-8")
            daemons[cell] = daq_cli("run", "--config", f"{cell}.toml", cwd=work, env=env)
            procs.append(daemons[cell])
        for d in daemons.values():
            assert d.stdout is not None
            assert json.loads(d.stdout.readline())["daq"] == "running", d.stderr
        twin = _client(port)

        def put_health(session: zenoh.Session) -> None:
            while not stop.wait(0.5):
                for cell, rate in TWIN_RATE.items():
                    doc = {"rate_hz": rate, "latency_ms": {"p50": 1.0, "p99": 2.0}}
                    session.put(f"twin/{cell}/robot/robot1/health", json.dumps(doc))

        thread = threading.Thread(target=put_health, args=(twin,), daemon=True)
        thread.start()
        yield Plant(port, daemons, twin)
    finally:
        stop.set()
        if thread is not None:
            thread.join(5)
        if twin is not None:
            twin.close()
        for p in reversed(procs):
            _stop(p)


def _echoes(plant: Plant, *runs: tuple[str, ...]) -> list[dict]:
    """``daq echo ARGS --stats`` of each of ``runs`` through the router, at once."""
    procs = [
        daq_cli("echo", *args, "--stats", "--duration", "2.5", "--connect", plant.endpoint,
                env={"PYTHONPATH": str(ROOT)})
        for args in runs
    ]  # fmt: skip
    out = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=60)
        assert p.returncode == 0, stderr[-2000:]
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def test_daq_echo_cell_takes_its_cells_keys_only(plant: Plant) -> None:
    # the control: without --cell, both cells' keys
    every, *picked = _echoes(plant, (), *(("--cell", cell) for cell in CELLS))
    assert {k.split("/")[1] for k in every["keys"]} == set(CELLS), sorted(every["keys"])
    for cell, got in zip(CELLS, picked, strict=True):
        keys = [*got["keys"], *got["health"]]
        assert f"cell/{cell}/robot/robot1/dev1/samples" in got["keys"], sorted(keys)
        assert all(k.startswith(f"cell/{cell}/") for k in keys), sorted(keys)
        st = got["keys"][f"cell/{cell}/robot/robot1/dev1/samples"]
        assert st["seq_breaks"] == 0 and st["samples"] > 100, st


def test_twin_view_picks_a_cell(plant: Plant) -> None:
    from view.cli import pick_cell
    from view.errors import ViewError
    from view.model import nominal_twin
    from view.sources import LiveSource

    # the command line: several cells up and no --cell is one line naming them, exit 2
    done = subprocess.run(
        [sys.executable, "-m", "calibration.cli", "view", "--connect", plant.endpoint,
         "--port", "0", "--duration", "1", "--quiet"],
        capture_output=True, text=True, timeout=60, env={"PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "cells cellA, cellB" in lines[0] and "--cell" in lines[0], lines
    said: list[str] = []
    session = _client(plant.router)
    sources: list[LiveSource] = []
    try:
        with pytest.raises(ViewError, match="cells cellA, cellB"):
            pick_cell(session, None, plant.endpoint, said.append)
        for cell in CELLS:
            assert pick_cell(session, cell, plant.endpoint, said.append) == cell
            sources.append(LiveSource(session, nominal_twin("kr500"), cell=cell))
        deadline = time.monotonic() + 20
        while any(s.latest().rate_hz is None or s.batches < 50 for s in sources):
            assert time.monotonic() < deadline, [s.batches for s in sources]
            time.sleep(0.1)
        for _ in range(10):  # a while: the other cell's messages keep coming meanwhile
            for cell, source in zip(CELLS, sources, strict=True):
                # the twin's health of its own cell, never the other's
                assert source.latest().rate_hz == TWIN_RATE[cell]
                assert all(k.startswith(f"cell/{cell}/") for k in source._kinds), source._kinds
            time.sleep(0.1)
        # one cell left: the view follows it without --cell, and says so
        _stop(plant.daemons["cellA"])
        deadline = time.monotonic() + 20
        while (picked := pick_cell(session, None, plant.endpoint, said.append)) != "cellB":
            assert time.monotonic() < deadline, picked
        assert said[-1].startswith("cell cellB: the only cell up"), said
    finally:
        for s in sources:
            s.close()
        session.close()
