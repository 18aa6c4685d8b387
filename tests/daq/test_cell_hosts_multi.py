"""Two cells on one router over hosts emulated with network namespaces (docs/deployment.md,
"Several cells on one router"): each cell's samples reach its own subscriber in order,
and no identity can inject into the other cell's keys.

Five namespaces (tests/daq/netns.py): ``dev1`` and ``dev2`` (each an emulated cell:
sim-cell and ``daq run --cell``), ``rtr`` (``daq router`` from deploy/router-cells.json5)
and ``app`` (a subscriber per cell with that cell's twin certificate, ``twin view``, and
clients with one cell's certificates trying the other cell's keys). Subnets 10.231.3/4/5
(tests/daq/test_cell_hosts.py uses 10.231.1/2). The commands are the ones
docs/deployment.md gives. Needs root (CAP_NET_ADMIN).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator

import pytest

from tests.daq.netns import (
    PY,
    ROOT,
    Hosts,
    doc_command,
    doc_file,
    json_line,
    require_root,
    stderr_of,
    stop,
)

ROUTER_APP = "10.231.5.2"
CELLS = ("cell1", "cell2")
PROBE = ROOT / "tests/daq/hosts_probe.py"


def twin_identity(cell: str) -> str:
    return "twin" if cell == "cell1" else f"twin-{cell}"


def _ready(p: subprocess.Popen[str], timeout_s: float) -> bool:
    """``daq echo --ready`` said it subscribed (its stderr file) within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and p.poll() is None:
        if '{"ready"' in stderr_of(p):
            return True
        time.sleep(0.1)
    return False


@pytest.fixture(scope="module")
def plant(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Hosts]:
    require_root("test_cell_hosts_multi")
    links = {"dev1": "10.231.3", "dev2": "10.231.4", "app": "10.231.5"}
    h = Hosts("gc", f"{os.getpid() % 100000:05d}", tmp_path_factory.mktemp("cells"), links)
    try:
        h.make()
        _, pki = doc_command('scripts/make-test-pki.sh pki "DNS:router.plant,')
        subprocess.run(pki, cwd=h.dir, check=True, capture_output=True, timeout=60)
        shutil.copy(ROOT / "deploy/router-cells.json5", h.dir / "router-cells.json5")
        sub = doc_file("twin-cell2.toml")
        for cell in CELLS:
            text = sub.replace("twin-cell2", twin_identity(cell))
            (h.dir / f"{twin_identity(cell)}.toml").write_text(text, encoding="utf-8")
        yield h
    finally:
        h.remove()


def test_each_cell_reaches_its_own_subscriber_in_order_and_no_cell_injects(plant: Hosts) -> None:
    """Both emulated cells through one router: per cell a subscriber with the cell's twin
    certificate gets its cell's keys only, every sample in order; the other cell's twin
    and daemon certificates cannot put on the cell's keys (refused, logged); ``twin view``
    picks a cell through the router, and refuses to guess between two."""
    router = plant.start("rtr", *doc_command("daq router --config router-cells")[1])
    assert json_line(router, '{"daq": "router"', 15.0) is not None, stderr_of(router)
    daemons = {}
    for i, cell in enumerate(CELLS):
        env, cmd = doc_command(f"DAQ_ZENOH_MODE=client DAQ_ZENOH_CONNECT=tls/10.231.{3 + i}.2")
        assert cmd[cmd.index("--cell") + 1] == cell, cmd
        daemons[cell] = plant.start(f"dev{i + 1}", *cmd, env=env)
    running = {}
    for cell, d in daemons.items():
        running[cell] = json_line(d, '{"daq": "running"', 40.0)
        assert running[cell] is not None, stop(d) or stderr_of(d)[-3000:]
    _, echo_cmd = doc_command("daq echo --cell cell2 --config twin-cell2.toml")
    echoes = {}
    for cell in CELLS:
        cmd = [x.replace("cell2", cell) if "cell2" in x else x for x in echo_cmd]
        cmd = [x.replace("twin-cell1", twin_identity(cell)) for x in cmd]
        echoes[cell] = plant.start("app", *cmd, "--ready")
    view_env, view_cmd = doc_command(
        "DAQ_ZENOH_TLS_CA=pki/ca.pem DAQ_ZENOH_TLS_CERTIFICATE=pki/viewer"
    )
    # doc_command runs the doc's `twin` as `python -m calibration.cli`
    assert view_cmd[:4] == [PY, "-m", "calibration.cli", "view"], view_cmd
    view_cmd = [*view_cmd, "--port", "0", "--quiet"]
    at = view_cmd.index("--cell")
    try:
        for cell, e in echoes.items():
            assert _ready(e, 40.0), (cell, stderr_of(e)[-2000:])
        # clients with one cell's certificates put on the other cell's keys, at once
        probes = []
        for cell, other in (("cell1", "cell2"), ("cell2", "cell1")):
            for who in (twin_identity(cell), "daemon" if cell == "cell1" else "daemon-cell2"):
                spec = {"role": "twin", "endpoint": f"tls/{ROUTER_APP}:7447",
                        "ca": "pki/ca.pem", "cell": other, "seconds": 3.0,
                        "cert": f"pki/{who}.pem", "key": f"pki/{who}.key"}  # fmt: skip
                probe = plant.start("app", PY, str(PROBE), json.dumps(spec))
                probes.append((who, other, probe))
        picked = plant.start("app", *view_cmd, "--duration", "2", env=view_env)
        unpicked = plant.start("app", *view_cmd[:at], *view_cmd[at + 2 :], env=view_env)
        for who, _, p in probes:
            got = json_line(p, "{", 30.0)
            assert got is not None and got["puts"] > 0 and got["received"] > 0, (who, got)
        view_up = json_line(picked, '{"view"', 60.0)
        assert stop(picked, timeout_s=30.0) == 0, stderr_of(picked)[-2000:]
        assert view_up is not None and view_up["cell"] == "cell2", view_up
        assert unpicked.wait(60) == 2
        refusal = stderr_of(unpicked).strip().splitlines()
        assert len(refusal) == 1 and "cells cell1, cell2 are up" in refusal[0], refusal
    finally:
        exits = {cell: stop(d) for cell, d in daemons.items()}
        stopped = {cell: json_line(d, '{"daq": "stopped"', 20.0) for cell, d in daemons.items()}
        stats = {}
        for cell, e in echoes.items():
            stop(e)
            stats[cell] = json_line(e, '{"keys"', 10.0)
        stop(router)
    assert exits == {cell: 0 for cell in CELLS}, exits
    log = stderr_of(router)
    for cell in CELLS:
        st = stats[cell]
        assert st is not None, cell
        data = {k: v for k, v in st["keys"].items() if k.endswith("/samples")}
        assert set(data) == set(running[cell]["keys"]), (cell, sorted(data))
        keys = [*st["keys"], *st["health"]]
        assert all(k.startswith(f"cell/{cell}/") for k in keys), (cell, sorted(keys))
        assert st["undecodable"] == 0  # the injected batch never arrived
        assert not any("intruder" in k for k in keys)
        summary = stopped[cell]
        assert summary is not None, cell
        for key, v in data.items():
            # in order, and every message the daemon published arrived (batch numbers
            # contiguous); a hole in the sequence numbers is one the device had (an
            # emulated device on a loaded host can miss samples: the daemon counts them)
            assert v["seq_breaks"] == 0 and v["lost_batches"] == 0, (key, v)
            missing = summary["devices"][key.split("/")[-2]]["samples_missing"]
            assert v["seq_gaps"] <= missing and v["samples"] > 200, (key, v, missing)
    # every cross-cell put was refused at the router, naming the identity and the key
    for who, other, _ in probes:
        for key in (f"cell/{other}/robot/robot1/tracker/samples",
                    f"cell/{other}/robot/robot1/intruder/health",
                    f"twin/{other}/robot/robot1/health"):  # fmt: skip
            line = f"CertCommonName({who})+"
            assert any(line in x and f"Put (ingress) on {key}" in x for x in log.splitlines()), (
                who,
                key,
                log[-3000:],
            )
