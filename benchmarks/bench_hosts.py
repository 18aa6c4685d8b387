"""What the router costs: the cell through ``daq router`` (TLS, client certificates, access
control: deploy/router.json5) against the same cell with the subscriber connected to the
daemon directly, in alternating rounds of the same run (docs/deployment.md).

Each round: ``daq run`` on 3 fake devices at 1 kHz (``daq.testing.FakeDriver``, worker
processes) and ``daq echo 'cell/**' --stats``; "direct": the echo connects to the
daemon's loopback endpoint (peers, TCP, no TLS); "router": the daemon and the echo are
TLS clients of a ``daq router`` on 127.0.0.1 with certificates from
scripts/make-test-pki.sh. Latency = subscriber receive − mapped device latch time (worst
device's p50 and p99); CPU of the daemon with its workers and of the router, from /proc.
Loopback only: what the router adds in hops, TLS and access control, not a network.

    python -m benchmarks.bench_hosts                      # 2 rounds of each, 15 s
    python -m benchmarks.bench_hosts --seconds 30 --rounds 3
    python -m benchmarks.bench_hosts --cells 4            # 4 cells x 3 devices, one router

``--cells N``: the plant of N cells through one router instead (benchmarks.bench_cells).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_daq import CELL, PY, _cell_config, _cpu_s, _free_port, _tree_cpu_s

ROOT = Path(__file__).resolve().parent.parent
WARMUP_S = 3.0


def client_zenoh(port: int, who: str) -> str:
    """cell.toml's [zenoh] of a TLS client of the router on 127.0.0.1:``port``, as ``who``."""
    return (
        f'[zenoh]\nmode = "client"\nconnect = ["tls/127.0.0.1:{port}"]\n'
        f'tls_ca = "pki/ca.pem"\ntls_certificate = "pki/{who}.pem"\n'
        f'tls_private_key = "pki/{who}.key"\n'
    )


def stop_all(procs: list[subprocess.Popen[str]]) -> None:
    """Terminate the processes still running (killed after 10 s)."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def _worst(stats: dict[str, Any]) -> dict[str, float]:
    """Worst device's latency p50/p99 (ms) and the loss of all keys."""
    data = [v for k, v in stats["keys"].items() if "latency_mapped_ms" in v]
    return {
        "p50_ms": max(v["latency_mapped_ms"]["p50"] for v in data),
        "p99_ms": max(v["latency_mapped_ms"]["p99"] for v in data),
        "samples": sum(v["samples"] for v in data),
        "lost": sum(v["seq_gaps"] + v["lost_batches"] for v in stats["keys"].values()),
    }


def one_round(work: Path, via_router: bool, seconds: float) -> dict[str, Any]:
    """One cell run of ``seconds`` (after a warm-up), direct or through the router."""
    port = _free_port()
    cell = _cell_config(port, devices=3, rate_hz=1000.0, batch=500, age_s=0.0)
    procs: list[subprocess.Popen[str]] = []
    router = None
    try:
        if via_router:
            rport = _free_port()
            text = (ROOT / "deploy/router.json5").read_text(encoding="utf-8")
            text = text.replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{rport}")
            (work / "router.json5").write_text(text.replace("cell/cell1/", f"cell/{CELL}/"))
            router = subprocess.Popen(
                [PY, "-m", "daq.cli", "router", "--config", "router.json5"],
                cwd=work, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            )  # fmt: skip
            procs.append(router)
            assert router.stdout is not None
            json.loads(router.stdout.readline())  # up
            old = f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
            cell = cell.replace(old, client_zenoh(rport, "daemon"))
            (work / "viewer.toml").write_text(client_zenoh(rport, "viewer"))
            where = ["--config", "viewer.toml"]
        else:
            where = ["--connect", f"tcp/127.0.0.1:{port}"]
        # a configured cell says "no recording" in its file (--no-record: the emulated one)
        (work / "cell.toml").write_text(cell + "\n[recording]\nenabled = false\n")
        d = subprocess.Popen(
            [PY, "-m", "daq.cli", "run", "--config", "cell.toml",
             "--duration", str(seconds + WARMUP_S)],
            cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        procs.append(d)
        assert d.stdout is not None
        json.loads(d.stdout.readline())  # running
        e = subprocess.Popen(
            [PY, "-m", "daq.cli", "echo", "cell/**", "--stats", "--idle", "3",
             "--duration", str(seconds + WARMUP_S + 30), *where],
            cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        procs.append(e)
        time.sleep(WARMUP_S)
        t0, c0 = time.monotonic(), _tree_cpu_s(d.pid)
        r0 = _cpu_s(router.pid) if router is not None else 0.0
        time.sleep(max(0.0, seconds - 0.5))
        t1, c1 = time.monotonic(), _tree_cpu_s(d.pid)
        r1 = _cpu_s(router.pid) if router is not None else 0.0
        d.communicate(timeout=seconds + 60)
        out, err = e.communicate(timeout=60)
        if not out.strip():
            raise RuntimeError(f"daq echo failed: {err[-2000:]}")
        stats = json.loads(out.strip().splitlines()[-1])
    finally:
        stop_all(procs)
    return {
        "mode": "router" if via_router else "direct",
        **_worst(stats),
        "daemon_cpu": (c1 - c0) / (t1 - t0),
        "router_cpu": (r1 - r0) / (t1 - t0) if via_router else None,
    }


def compare(seconds: float, rounds: int) -> dict[str, Any]:
    """Alternating direct and router rounds; medians, and the router's p50 cost."""
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        subprocess.run(
            [str(ROOT / "scripts/make-test-pki.sh"), str(work / "pki")],
            check=True, capture_output=True, timeout=60,
        )  # fmt: skip
        for _ in range(rounds):
            for via_router in (False, True):
                runs.append(one_round(work, via_router, seconds))

    def med(mode: str, key: str) -> float:
        return float(np.median([r[key] for r in runs if r["mode"] == mode]))

    return {
        "seconds": seconds,
        "rounds": runs,
        "direct_p50_ms": med("direct", "p50_ms"),
        "router_p50_ms": med("router", "p50_ms"),
        "router_minus_direct_p50_ms": med("router", "p50_ms") - med("direct", "p50_ms"),
        "direct_p99_ms": med("direct", "p99_ms"),
        "router_p99_ms": med("router", "p99_ms"),
        "lost": sum(r["lost"] for r in runs),
        "router_cpu": med("router", "router_cpu"),
        "daemon_cpu_direct": med("direct", "daemon_cpu"),
        "daemon_cpu_router": med("router", "daemon_cpu"),
    }


def run(quick: bool = True) -> list[dict[str, Any]]:
    """Flat rows for ``python -m benchmarks``."""
    c = compare(3.0 if quick else 15.0, 1 if quick else 2)
    row = {k: v for k, v in c.items() if k != "rounds"}
    row["benchmark"] = "cell 3 x 1 kHz through daq router (TLS, ACL) vs direct"
    row["note"] = "alternating rounds, medians; latency of the worst device"
    return [row]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_hosts", description=__doc__)
    ap.add_argument("--seconds", type=float, default=15.0, help="measured seconds a round")
    ap.add_argument("--rounds", type=int, default=2, help="rounds of each mode")
    ap.add_argument(
        "--cells", type=int, help="N cells x 3 devices through one router (bench_cells)"
    )
    args = ap.parse_args(argv)
    if args.cells is not None:
        from benchmarks.bench_cells import main as cells_main

        return cells_main(["--cells", str(args.cells), "--seconds", str(args.seconds)])
    print(json.dumps(compare(args.seconds, args.rounds), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
