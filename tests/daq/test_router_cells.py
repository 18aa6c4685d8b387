"""Several cells on one router (deploy/router-cells.json5, docs/deployment.md): each
cell's daemon and twin may publish their own cell's keys only; a reader sees both cells.

``daq router`` on a free 127.0.0.1 port (loopback only), certificates from
scripts/make-test-pki.sh with the second cell's identities; the clients are zenoh
sessions of this process (TLS, client certificates), each putting on its own cell's keys
and on the other cell's.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import zenoh

ROOT = Path(__file__).resolve().parents[2]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _session(work: Path, port: int, who: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    tls = {
        "root_ca_certificate": str(work / "pki/ca.pem"),
        "connect_certificate": str(work / f"pki/{who}.pem"),
        "connect_private_key": str(work / f"pki/{who}.key"),
        "enable_mtls": True,
    }
    for k, v in tls.items():
        conf.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    return zenoh.open(conf)


def test_each_cell_publishes_its_own_keys_only(tmp_path: Path) -> None:
    subprocess.run(
        [str(ROOT / "scripts/make-test-pki.sh"), str(tmp_path / "pki"),
         "DNS:localhost,IP:127.0.0.1", "daemon-cell2", "twin-cell2"],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    port = _free_port()
    text = (ROOT / "deploy/router-cells.json5").read_text(encoding="utf-8")
    (tmp_path / "router.json5").write_text(text.replace("0.0.0.0:7447", f"127.0.0.1:{port}"))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    router = subprocess.Popen(
        [sys.executable, "-m", "daq.cli", "router", "--config", "router.json5"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    sessions: list[zenoh.Session] = []
    try:
        assert router.stdout is not None
        assert json.loads(router.stdout.readline())["daq"] == "router"
        got: list[str] = []
        viewer = _session(tmp_path, port, "viewer")
        sessions.append(viewer)
        viewer.declare_subscriber("**", lambda s: got.append(str(s.key_expr)))
        time.sleep(0.5)
        tries = {  # who: (cell it belongs to, key prefix it publishes under)
            "daemon": ("cell1", "cell"),
            "twin": ("cell1", "twin"),
            "daemon-cell2": ("cell2", "cell"),
            "twin-cell2": ("cell2", "twin"),
        }
        publishers = {}
        for who in tries:
            publishers[who] = _session(tmp_path, port, who)
            sessions.append(publishers[who])
        expected = {f"{p}/{c}/robot/robot1/from-{w}" for w, (c, p) in tries.items()}
        # again until every allowed key arrived (the viewer's subscription reaches the
        # router in its own time); bounded by count and time
        deadline = time.monotonic() + 10.0
        for _ in range(100):
            for who, (_, prefix) in tries.items():
                for cell in ("cell1", "cell2"):
                    publishers[who].put(f"{prefix}/{cell}/robot/robot1/from-{who}", b"{}")
            time.sleep(0.1)
            if expected <= set(got) or time.monotonic() > deadline:
                break
        time.sleep(0.3)  # anything refused would have come by now too
    finally:
        for s in sessions:
            s.close()
        router.terminate()
        _, err = router.communicate(timeout=15)
    assert set(got) == expected, sorted(set(got))
    assert router.returncode == 0, err
    for who, (cell, prefix) in tries.items():
        other = "cell2" if cell == "cell1" else "cell1"
        line = f"CertCommonName({who})+"
        key = f"Put (ingress) on {prefix}/{other}/robot/robot1/from-{who}"
        assert any(line in x and key in x for x in err.splitlines()), (who, err[-2000:])
