"""A cell over three hosts, emulated with network namespaces (docs/deployment.md).

The test makes three namespaces and tears them down itself: ``dev`` (the daemon on the
emulated cell: sim-cell and ``daq run``), ``rtr`` (``daq router`` from deploy/router.json5)
and ``app`` (a twin-like client and an independent ``daq echo``), joined by two veth
pairs, 10.231.1.0/24 (dev-rtr) and 10.231.2.0/24 (app-rtr). The router's namespace does
not forward IP, so dev and app reach each other only through zenoh's router. Every link
is TLS with client certificates from scripts/make-test-pki.sh; access control is
deploy/router.json5's. The commands are the ones docs/deployment.md gives.

Needs root (CAP_NET_ADMIN, as CI runs): without it the tests fail saying so.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.daq.netns import (
    ROOT,
    Hosts,
    doc_command,
    doc_file,
    json_line,
    require_root,
    sh,
    stderr_of,
    stop,
)

CELL = "cell1"
ROUTER_DEV, ROUTER_APP = "10.231.1.2", "10.231.2.2"
PORT = 7447


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Hosts]:
    require_root("test_cell_hosts")
    links = {"dev": "10.231.1", "app": "10.231.2"}
    c = Hosts("gt", f"{os.getpid() % 100000:05d}", tmp_path_factory.mktemp("cell"), links)
    try:
        c.make()
        _, pki = doc_command('scripts/make-test-pki.sh pki "DNS:localhost,')
        subprocess.run(pki, cwd=c.dir, check=True, capture_output=True, timeout=60)
        shutil.copy(ROOT / "deploy/router.json5", c.dir / "router.json5")
        (c.dir / "viewer.toml").write_text(doc_file("viewer.toml"), encoding="utf-8")
        yield c
    finally:
        c.remove()


def _probe(cell: Hosts, role: str, cert: str | None, ca: str = "pki/ca.pem", **kw: object) -> dict:
    spec = {"role": role, "endpoint": f"tls/{ROUTER_APP}:{PORT}", "ca": ca, "cell": CELL, **kw}
    if cert is not None:
        spec |= {"cert": f"pki/{cert}.pem", "key": f"pki/{cert}.key"}
    return cell.probe("app", spec)


def _recorded_seq(path: Path, keys: list[str]) -> dict[str, np.ndarray]:
    """``seq`` of each data key in ``keys`` in a recording, in file order."""
    from daq.testing import recorded_columns

    return {k: recorded_columns(path, k)["seq"].astype(np.int64) for k in keys}


def _holes(path: Path, keys: list[str]) -> dict[str, tuple[list[dict], int]]:
    """Per data key of a subscriber's recording: its hole records, and the messages it
    lacks by its ``batch_seq``."""
    from daq.columnar import read_header
    from daq.recording_holes import HOLES_TOPIC
    from daq.recording_reader import read_recording

    holes = [json.loads(m.data) for m in read_recording(path).messages_iter({HOLES_TOPIC})]
    out = {}
    for key in keys:
        seq = [read_header(m.data).batch_seq for m in read_recording(path).messages_iter({key})]
        lacking = int(np.sum(np.diff(np.array(seq, dtype=np.int64)) - 1))
        out[key] = ([h for h in holes if h["key"] == key], lacking)
    return out


def twin_docs(path: Path) -> int:
    """Messages of the twin's health key in a recording."""
    from daq.recording_reader import read_recording

    key = f"twin/{CELL}/robot/robot1/health"
    return sum(1 for _ in read_recording(path).messages_iter({key}))


def test_cell_over_three_hosts_in_order_refusals_and_router_restart(cell: Hosts) -> None:
    """The daemon (emulated cell) publishes through the TLS router to an independent
    subscriber in another namespace: every sample in order; a twin's certificate cannot
    inject into the cell's keys (its own twin keys pass); the router restarts mid-run and
    the daemon's recording still holds every acquired sample, the unsent ones counted."""
    _, router_cmd = doc_command("daq router --config router.json5")
    router = cell.start("rtr", *router_cmd)
    up = json_line(router, '{"daq": "router"', 15.0)
    assert up is not None, stderr_of(router)
    rec = cell.dir / "dev.mcap"
    env, daemon_cmd = doc_command("DAQ_ZENOH_MODE=client DAQ_ZENOH_CONNECT=tls/10.231.1.2")
    # the device PC's clock 0.5 s ahead of the router's (the test hook: docs/deployment.md)
    daemon = cell.start("dev", *daemon_cmd, env={**env, "DAQ_TEST_CLOCK_SHIFT_S": "0.5"})
    running = json_line(daemon, '{"daq": "running"', 40.0)
    assert running is not None, stop(daemon) or stderr_of(daemon)[-3000:]
    _, echo_cmd = doc_command("daq echo 'cell/cell1/**' --config viewer.toml")
    echo = cell.start("app", *echo_cmd)
    _, record_cmd = doc_command("daq record 'cell/cell1/**' --config viewer.toml")
    recorder = cell.start("app", *record_cmd)
    try:
        time.sleep(3.0)  # the echo subscribed and receiving
        twin = _probe(cell, "twin", "twin", seconds=2.0)
        assert twin["received"] > 0 and twin["puts"] > 0  # it reads the cell
        time.sleep(1.0)
        # the router restarts: SIGTERM, down for a second, up again from the same file
        assert stop(router) == 0
        first_life = stderr_of(router)
        time.sleep(1.0)
        router = cell.start("rtr", *router_cmd)
        assert json_line(router, '{"daq": "router"', 15.0) is not None
        time.sleep(4.0)  # clients reconnect by themselves; data flows again
        # the device PC's link drops for 5 s (shorter than zenoh's 10 s lease: the
        # session holds, TCP and zenoh's queue keep what is sent meanwhile)
        veth = cell.veth("dev")
        sh("ip", "-n", cell.ns("dev"), "link", "set", veth, "down")
        try:
            time.sleep(5.0)
        finally:
            sh("ip", "-n", cell.ns("dev"), "link", "set", veth, "up")
        time.sleep(4.0)
    finally:
        assert stop(daemon) == 0
        stopped = json_line(daemon, '{"daq": "stopped"', 20.0)
        assert stop(echo) == 0
        stats = json_line(echo, '{"keys"', 10.0)
        assert stop(recorder) == 0
        rec_line = json_line(recorder, '{"recorded"', 10.0)
        stop(router)
    assert stopped is not None and stats is not None and rec_line is not None
    keys = stats["keys"]
    data = {k: v for k, v in keys.items() if k.endswith("/samples")}
    assert set(data) == {k for k in running["keys"]}, (sorted(data), running["keys"])
    assert stats["undecodable"] == 0  # the injected batch never arrived
    assert not any("intruder" in k for k in (*keys, *stats["health"]))
    assert f"twin/{CELL}/robot/robot1/health" not in stats["health"]  # not subscribed there
    recorded = _recorded_seq(rec, running["keys"])
    for key, st in data.items():
        # in order by sequence number: none went back or repeated (the mapped time's
        # order, ``out_of_order``, is the clock fit's, not the transport's: not asserted)
        assert st["seq_breaks"] == 0, (key, st)
        # every sample the daemon acquired is in its recording, none missing
        seq = recorded[key]
        assert np.all(np.diff(seq) == 1), (key, np.flatnonzero(np.diff(seq) != 1)[:5])
        assert st["first_seq"] >= seq[0] and st["last_seq"] <= seq[-1]
        # and publishing resumed after the restart and the link drop: the subscriber got
        # the stream to its end (the echo stops after the daemon)
        assert st["last_seq"] >= seq[-1] - 20, (key, st["last_seq"], seq[-1])
        # the subscriber's hole is the restart's, and the daemon counted what it could not send
        device = key.split("/")[-2]
        summary = stopped["devices"][device]
        assert summary["gaps"] == 0 and summary["samples_missing"] == 0, summary
        assert summary["samples"] == len(seq), (key, summary, len(seq))
        assert st["seq_gaps"] > 0 and summary["messages_unrouted"] > 0, (key, st, summary)
        # what the subscriber lost is what the daemon could not hand to a router (within
        # the router watch's 10 ms look either side: 2 messages a side at 200 Hz)
        assert abs(st["lost_batches"] - summary["messages_unrouted"]) <= 10, (key, st, summary)
    # the subscriber's recording marks its holes: the router's restart, as many
    # messages as it lacks, near what the daemon counted unrouted
    holes = _holes(cell.dir / "app.mcap", running["keys"])
    assert rec_line["holes"] == sum(len(h) for h, _ in holes.values()) > 0, rec_line
    for key, (marked, lacking) in holes.items():
        assert sum(h["count"] for h in marked) == lacking, (key, marked, lacking)
        assert {h["reason"] for h in marked} <= {"router_down"}, marked
        unrouted = stopped["devices"][key.split("/")[-2]]["messages_unrouted"]
        assert abs(lacking - unrouted) <= 10, (key, lacking, unrouted)
    # ... which the twin's reader says (twin run --replay prints it as a warning)
    from calibration.twin.streams import read_recording_streams

    note = read_recording_streams(cell.dir / "app.mcap").note
    assert f"the recorder marked {rec_line['holes']} hole(s)" in note, note
    # the clock 0.5 s off: measured against the router's through TLS and its access
    # control, said once on stderr
    clock = stopped["host_clock"]
    assert clock is not None and not clock["within_tolerance"], clock
    assert abs(clock["offset_ms"] - 500.0) <= clock["uncertainty_ms"] + 5.0, clock
    assert stderr_of(daemon).count("ms ahead of the router's") == 1, stderr_of(daemon)[-2000:]
    # the twin's own keys passed: the daemon recorded them (from the router)
    assert twin_docs(rec) > 0
    # the refusals were logged by the router, naming the identity and the key
    for key in ("tracker/samples", "intruder/health"):
        line = "CertCommonName(twin)+Transport(Tls)"
        refused = [
            x
            for x in first_life.splitlines()
            if line in x and f"Put (ingress) on cell/{CELL}/robot/robot1/{key}" in x
        ]
        assert refused, first_life[-3000:]


def test_clients_without_a_valid_certificate_neither_read_nor_publish(cell: Hosts) -> None:
    """Another CA's certificate, an expired one, none: the router's TLS refuses the link
    (zenoh's own session, no local check in the way) and logs why."""
    router = cell.start("rtr", *doc_command("daq router --config router.json5")[1])
    try:
        assert json_line(router, '{"daq": "router"', 15.0) is not None
        wrong = _probe(cell, "connect", "wrong-ca")
        expired = _probe(cell, "connect", "expired")
        none = _probe(cell, "connect", None)
        valid = _probe(cell, "connect", "viewer")  # the control: the same call works
    finally:
        stop(router)
    log = stderr_of(router)
    assert valid["opened"], valid
    for name, got in (("wrong-ca", wrong), ("expired", expired), ("none", none)):
        assert not got["opened"], (name, got)
    assert "refused a TLS client: UnknownIssuer" in log, log
    assert "refused a TLS client: certificate expired" in log, log
    assert "refused a TLS client: no client certificate" in log, log
