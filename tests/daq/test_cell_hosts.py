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
import re
import selectors
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PY = sys.executable
CELL = "cell1"
ROUTER_DEV, ROUTER_APP = "10.231.1.2", "10.231.2.2"
PORT = 7447


DOC = ROOT / "docs/deployment.md"


def doc_command(prefix: str) -> tuple[dict[str, str], list[str]]:
    """The command line of docs/deployment.md that starts with ``prefix``: its leading
    ``VAR=value`` words and the rest, ``daq`` run as ``python -m daq.cli``."""
    lines = [x for x in DOC.read_text(encoding="utf-8").splitlines() if x.startswith(prefix)]
    assert len(lines) == 1, (prefix, lines)
    words = shlex.split(lines[0].split("  #")[0])
    env = {}
    while "=" in words[0] and not words[0].startswith("-"):
        k, _, v = words.pop(0).partition("=")
        env[k] = v
    if words[0] == "daq":
        words = [PY, "-m", "daq.cli", *words[1:]]
    elif words[0].startswith("scripts/"):
        words[0] = str(ROOT / words[0])
    return env, words


def doc_file(name: str) -> str:
    """The text of the ```toml block of docs/deployment.md that begins ``# file: name``."""
    m = re.search(rf"```toml\n# file: {re.escape(name)}\n(.*?)```", DOC.read_text("utf-8"), re.S)
    assert m is not None, name
    return m.group(1)


def _sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, timeout=20)


@dataclass
class Cell:
    """Three namespaces, the PKI, and the processes started in them (stopped at the end)."""

    token: str
    dir: Path
    procs: list[subprocess.Popen[str]] = field(default_factory=list)

    def ns(self, role: str) -> str:
        return f"gt{self.token}{role}"

    def env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("DAQ_")}
        env["PYTHONPATH"] = str(ROOT)
        return env

    def start(
        self, role: str, *args: str, env: dict[str, str] | None = None
    ) -> subprocess.Popen[str]:
        """``args`` run in namespace ``role``, working directory the cell's (pki/ there)."""
        log = self.dir / f"{role}-{len(self.procs)}.stderr"
        with open(log, "w", encoding="utf-8") as err:  # a file: never a full pipe
            p = subprocess.Popen(
                ["ip", "netns", "exec", self.ns(role), *args],
                cwd=self.dir,
                env={**self.env(), **(env or {})},
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
            )
        p.stderr_path = log  # type: ignore[attr-defined]
        self.procs.append(p)
        return p

    def daq(
        self, role: str, *args: str, env: dict[str, str] | None = None
    ) -> subprocess.Popen[str]:
        return self.start(role, PY, "-m", "daq.cli", *args, env=env)

    def run(
        self, role: str, *args: str, timeout_s: float = 30.0
    ) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            ["ip", "netns", "exec", self.ns(role), *args],
            cwd=self.dir,
            env=self.env(),
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )


def _stderr(p: subprocess.Popen[str]) -> str:
    return Path(p.stderr_path).read_text(encoding="utf-8")  # type: ignore[attr-defined]


def _stop(p: subprocess.Popen[str], sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> int:
    if p.poll() is None:
        p.send_signal(sig)
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)
    return p.returncode


def _line(p: subprocess.Popen[str], prefix: str, timeout_s: float) -> dict | None:
    """The first stdout line of ``p`` starting with ``prefix``, as JSON (None: not within
    ``timeout_s``, or ``p`` ended); bounded by lines read and time."""
    assert p.stdout is not None
    sel = selectors.DefaultSelector()
    sel.register(p.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout_s
    try:
        for _ in range(10_000):
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            if not sel.select(timeout=min(1.0, left)):
                if p.poll() is not None:
                    return None
                continue
            line = p.stdout.readline()
            if not line:
                return None
            if line.startswith(prefix):
                return json.loads(line)
    finally:
        sel.close()
    return None


def _make_namespaces(cell: Cell) -> None:
    for role in ("dev", "rtr", "app"):
        _sh("ip", "netns", "add", cell.ns(role))
        _sh("ip", "-n", cell.ns(role), "link", "set", "lo", "up")
    for side, net in (("dev", 1), ("app", 2)):
        a, b = f"gt{cell.token}{side[0]}0", f"gt{cell.token}{side[0]}1"
        _sh("ip", "link", "add", a, "type", "veth", "peer", "name", b)
        _sh("ip", "link", "set", a, "netns", cell.ns(side))
        _sh("ip", "link", "set", b, "netns", cell.ns("rtr"))
        _sh("ip", "-n", cell.ns(side), "addr", "add", f"10.231.{net}.1/24", "dev", a)
        _sh("ip", "-n", cell.ns("rtr"), "addr", "add", f"10.231.{net}.2/24", "dev", b)
        _sh("ip", "-n", cell.ns(side), "link", "set", a, "up")
        _sh("ip", "-n", cell.ns("rtr"), "link", "set", b, "up")


def _remove_namespaces(cell: Cell) -> None:
    for role in ("dev", "rtr", "app"):  # deleting a namespace deletes its veth ends
        subprocess.run(["ip", "netns", "del", cell.ns(role)], capture_output=True, timeout=20)


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    if os.geteuid() != 0:
        pytest.fail(
            "test_cell_hosts needs root (CAP_NET_ADMIN) to make network namespaces and veth "
            "pairs; run it as root, as CI does"
        )
    if shutil.which("ip") is None or shutil.which("openssl") is None:
        pytest.fail("test_cell_hosts needs iproute2 (ip) and openssl on PATH")
    c = Cell(token=f"{os.getpid() % 100000:05d}", dir=tmp_path_factory.mktemp("cell"))
    try:
        _make_namespaces(c)
        _, pki = doc_command('scripts/make-test-pki.sh pki "DNS:localhost,')
        subprocess.run(pki, cwd=c.dir, check=True, capture_output=True, timeout=60)
        shutil.copy(ROOT / "deploy/router.json5", c.dir / "router.json5")
        (c.dir / "viewer.toml").write_text(doc_file("viewer.toml"), encoding="utf-8")
        yield c
    finally:
        for p in c.procs:
            _stop(p, signal.SIGKILL if p.poll() is None else signal.SIGTERM, 5.0)
        _remove_namespaces(c)


def _probe(cell: Cell, role: str, cert: str | None, ca: str = "pki/ca.pem", **kw: object) -> dict:
    spec = {"role": role, "endpoint": f"tls/{ROUTER_APP}:{PORT}", "ca": ca, "cell": CELL, **kw}
    if cert is not None:
        spec |= {"cert": f"pki/{cert}.pem", "key": f"pki/{cert}.key"}
    done = cell.run("app", PY, str(ROOT / "tests/daq/hosts_probe.py"), json.dumps(spec))
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


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


def test_cell_over_three_hosts_in_order_refusals_and_router_restart(cell: Cell) -> None:
    """The daemon (emulated cell) publishes through the TLS router to an independent
    subscriber in another namespace: every sample in order; a twin's certificate cannot
    inject into the cell's keys (its own twin keys pass); the router restarts mid-run and
    the daemon's recording still holds every acquired sample, the unsent ones counted."""
    _, router_cmd = doc_command("daq router ")
    router = cell.start("rtr", *router_cmd)
    up = _line(router, '{"daq": "router"', 15.0)
    assert up is not None, _stderr(router)
    rec = cell.dir / "dev.mcap"
    env, daemon_cmd = doc_command("DAQ_ZENOH_MODE=client DAQ_ZENOH_CONNECT=tls/10.231.1.2")
    # the device PC's clock 0.5 s ahead of the router's (the test hook: docs/deployment.md)
    daemon = cell.start("dev", *daemon_cmd, env={**env, "DAQ_TEST_CLOCK_SHIFT_S": "0.5"})
    running = _line(daemon, '{"daq": "running"', 40.0)
    assert running is not None, _stop(daemon) or _stderr(daemon)[-3000:]
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
        assert _stop(router) == 0
        first_life = _stderr(router)
        time.sleep(1.0)
        router = cell.start("rtr", *router_cmd)
        assert _line(router, '{"daq": "router"', 15.0) is not None
        time.sleep(4.0)  # clients reconnect by themselves; data flows again
        # the device PC's link drops for 5 s (shorter than zenoh's 10 s lease: the
        # session holds, TCP and zenoh's queue keep what is sent meanwhile)
        veth = f"gt{cell.token}d0"
        _sh("ip", "-n", cell.ns("dev"), "link", "set", veth, "down")
        try:
            time.sleep(5.0)
        finally:
            _sh("ip", "-n", cell.ns("dev"), "link", "set", veth, "up")
        time.sleep(4.0)
    finally:
        assert _stop(daemon) == 0
        stopped = _line(daemon, '{"daq": "stopped"', 20.0)
        assert _stop(echo) == 0
        stats = _line(echo, '{"keys"', 10.0)
        assert _stop(recorder) == 0
        rec_line = _line(recorder, '{"recorded"', 10.0)
        _stop(router)
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
    assert _stderr(daemon).count("ms ahead of the router's") == 1, _stderr(daemon)[-2000:]
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


def test_clients_without_a_valid_certificate_neither_read_nor_publish(cell: Cell) -> None:
    """Another CA's certificate, an expired one, none: the router's TLS refuses the link
    (zenoh's own session, no local check in the way) and logs why."""
    router = cell.start("rtr", *doc_command("daq router ")[1])
    try:
        assert _line(router, '{"daq": "router"', 15.0) is not None
        wrong = _probe(cell, "connect", "wrong-ca")
        expired = _probe(cell, "connect", "expired")
        none = _probe(cell, "connect", None)
        valid = _probe(cell, "connect", "viewer")  # the control: the same call works
    finally:
        _stop(router)
    log = _stderr(router)
    assert valid["opened"], valid
    for name, got in (("wrong-ca", wrong), ("expired", expired), ("none", none)):
        assert not got["opened"], (name, got)
    assert "refused a TLS client: UnknownIssuer" in log, log
    assert "refused a TLS client: certificate expired" in log, log
    assert "refused a TLS client: no client certificate" in log, log
