"""Hosts emulated with network namespaces, for the tests of a cell over several hosts
(tests/daq/test_cell_hosts.py, tests/daq/test_cell_hosts_multi.py; docs/deployment.md).

:class:`Hosts` makes a router namespace ``rtr`` and one namespace per other host, each
joined to ``rtr`` by a veth pair on a /24 of its own (the host ``.1``, the router ``.2``);
``rtr`` does not forward IP, so the hosts meet only through zenoh's router. It starts
processes in them (stderr to a file) and removes the namespaces (and their veth ends) at
the end. The commands come out of docs/deployment.md (:func:`doc_command`).

Needs root (CAP_NET_ADMIN); :func:`require_root` fails a test without it, saying so.
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
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PY = sys.executable
DOC = ROOT / "docs/deployment.md"


def doc_command(prefix: str) -> tuple[dict[str, str], list[str]]:
    """The command line of docs/deployment.md that starts with ``prefix``: its leading
    ``VAR=value`` words and the rest, ``daq`` run as ``python -m daq.cli`` (``twin`` as
    ``python -m calibration.cli``)."""
    lines = [x for x in DOC.read_text(encoding="utf-8").splitlines() if x.startswith(prefix)]
    assert len(lines) == 1, (prefix, lines)
    words = shlex.split(lines[0].split("  #")[0])
    env = {}
    while "=" in words[0] and not words[0].startswith("-"):
        k, _, v = words.pop(0).partition("=")
        env[k] = v
    if words[0] == "daq":
        words = [PY, "-m", "daq.cli", *words[1:]]
    elif words[0] == "twin":
        words = [PY, "-m", "calibration.cli", *words[1:]]
    elif words[0].startswith("scripts/"):
        words[0] = str(ROOT / words[0])
    return env, words


def doc_file(name: str) -> str:
    """The text of the ```toml block of docs/deployment.md that begins ``# file: name``."""
    m = re.search(rf"```toml\n# file: {re.escape(name)}\n(.*?)```", DOC.read_text("utf-8"), re.S)
    assert m is not None, name
    return m.group(1)


def sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, timeout=20)


def require_root(test: str) -> None:
    """Fail (not skip) ``test`` without root or without ``ip`` and ``openssl``."""
    if os.geteuid() != 0:
        pytest.fail(
            f"{test} needs root (CAP_NET_ADMIN) to make network namespaces and veth "
            "pairs; run it as root, as CI does"
        )
    if shutil.which("ip") is None or shutil.which("openssl") is None:
        pytest.fail(f"{test} needs iproute2 (ip) and openssl on PATH")


@dataclass
class Hosts:
    """Namespaces ``<prefix><token><role>``, the router's ``rtr`` and one per key of
    ``links`` (role -> its subnet's first three octets, ``10.231.1``), and the processes
    started in them (stopped at the end). Working directory ``dir`` (pki/ there)."""

    prefix: str
    token: str
    dir: Path
    links: dict[str, str]
    procs: list[subprocess.Popen[str]] = field(default_factory=list)

    def ns(self, role: str) -> str:
        return f"{self.prefix}{self.token}{role}"

    def veth(self, role: str) -> str:
        """The veth end in ``role``'s namespace (its peer in ``rtr`` ends in ``1``)."""
        return f"{self.prefix}{self.token}{list(self.links).index(role)}h"

    def make(self) -> None:
        for role in ("rtr", *self.links):
            sh("ip", "netns", "add", self.ns(role))
            sh("ip", "-n", self.ns(role), "link", "set", "lo", "up")
        for role, net in self.links.items():
            a, b = self.veth(role), self.veth(role)[:-1] + "r"
            sh("ip", "link", "add", a, "type", "veth", "peer", "name", b)
            sh("ip", "link", "set", a, "netns", self.ns(role))
            sh("ip", "link", "set", b, "netns", self.ns("rtr"))
            sh("ip", "-n", self.ns(role), "addr", "add", f"{net}.1/24", "dev", a)
            sh("ip", "-n", self.ns("rtr"), "addr", "add", f"{net}.2/24", "dev", b)
            sh("ip", "-n", self.ns(role), "link", "set", a, "up")
            sh("ip", "-n", self.ns("rtr"), "link", "set", b, "up")

    def remove(self) -> None:
        """Stop what still runs, delete the namespaces (and with them their veth ends)."""
        for p in self.procs:
            stop(p, signal.SIGKILL if p.poll() is None else signal.SIGTERM, 5.0)
        for role in ("rtr", *self.links):
            subprocess.run(["ip", "netns", "del", self.ns(role)], capture_output=True, timeout=20)

    def env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("DAQ_")}
        env["PYTHONPATH"] = str(ROOT)
        return env

    def start(
        self, role: str, *args: str, env: dict[str, str] | None = None
    ) -> subprocess.Popen[str]:
        """``args`` run in namespace ``role``, working directory ``dir``."""
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

    def probe(self, role: str, spec: dict[str, object]) -> dict[str, object]:
        """tests/daq/hosts_probe.py with ``spec`` in namespace ``role``: its JSON line."""
        done = self.run(role, PY, str(ROOT / "tests/daq/hosts_probe.py"), json.dumps(spec))
        assert done.returncode == 0, done.stderr[-2000:]
        out: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
        return out


def stderr_of(p: subprocess.Popen[str]) -> str:
    return Path(p.stderr_path).read_text(encoding="utf-8")  # type: ignore[attr-defined]


def stop(p: subprocess.Popen[str], sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> int:
    if p.poll() is None:
        p.send_signal(sig)
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)
    return p.returncode


def json_line(p: subprocess.Popen[str], prefix: str, timeout_s: float) -> dict | None:
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
