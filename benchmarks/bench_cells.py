"""A plant of several cells through one router: every cell's daemon, one ``daq router``
with TLS and access control, a subscriber per cell (docs/deployment.md, "Several cells").

Each cell ``cell1`` … ``cellN``: ``daq run`` on 3 fake devices at 1 kHz
(``daq.testing.FakeDriver`` in worker processes, the devices of benchmarks.bench_hosts),
a TLS client of the router with its own certificate (``daemon``, ``daemon-cell2`` …),
and ``daq echo --cell cellK --stats`` with the cell's twin certificate (``twin``,
``twin-cell2`` …). The router's configuration is deploy/router-cells.json5, its cell2
entries copied for cell3 … (the file's "add a cell"), listening on 127.0.0.1. Reported:
samples lost (by sequence numbers: what a daemon acquired from its subscriber's first
sample on and the subscriber did not receive, holes and tail alike), latency subscriber
receive − mapped device latch time (p50 and p99: the median and the worst over the
devices), CPU per process from /proc (each device's worker, each daemon's own process,
the router, the subscribers) over the measured window, and the host's load. Before the
N cells, a one-cell run through the same router (``reference_1_cell``): on a shared host,
the N-cell figures read against it, measured minutes apart in the same run.

    python -m benchmarks.bench_hosts --cells 4             # 4 cells x 3 devices, 15 s
    python -m benchmarks.bench_cells --cells 4 --seconds 30
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from benchmarks.bench_daq import PY, _cell_config, _cpu_s, _free_port
from benchmarks.bench_hosts import client_zenoh, stop_all
from daq.testing import child_pids

ROOT = Path(__file__).resolve().parent.parent
WARMUP_S = 3.0
DEVICES = 3
RATE_HZ = 1000.0


def _no_nulls(value: Any) -> Any:
    """``value`` without the null entries zenoh fills in for unset keys."""
    if isinstance(value, dict):
        return {k: _no_nulls(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [_no_nulls(v) for v in value]
    return value


def router_config(cells: int, listen: str) -> dict[str, Any]:
    """deploy/router-cells.json5 listening on ``listen``, for cells ``cell1`` …
    ``cell<cells>``: cell2's rules, subjects and policies copied per further cell (its
    identities ``daemon-cellK``, ``twin-cellK``)."""
    conf = zenoh.Config.from_file(str(ROOT / "deploy/router-cells.json5"))

    def get(key: str) -> Any:
        return _no_nulls(json.loads(conf.get_json(key)))

    acl = get("access_control")

    def copies(items: list[dict[str, Any]]) -> list[dict[str, Any]]:
        out = []
        for k in range(3, cells + 1):
            for item in items:
                if "cell2" in item["id"]:
                    out.append(json.loads(json.dumps(item).replace("cell2", f"cell{k}")))
        return out

    new_subjects = copies(acl["subjects"])
    for policy in acl["policies"]:
        if any("cell2" in s for s in policy["subjects"]) and not any(
            "cell2" in r for r in policy["rules"]
        ):  # the policy of every identity (read): the new subjects too
            policy["subjects"] += [s["id"] for s in new_subjects]
    extra_policies = []
    for k in range(3, cells + 1):
        for policy in acl["policies"]:
            if all("cell2" in r for r in policy["rules"]):
                extra_policies.append(json.loads(json.dumps(policy).replace("cell2", f"cell{k}")))
    acl["rules"] += copies(acl["rules"])
    acl["subjects"] += new_subjects
    acl["policies"] += extra_policies
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": get("scouting"),
        "transport": {"link": {"tls": get("transport/link/tls")}},
        "access_control": acl,
    }


def identity(role: str, k: int) -> str:
    """The certificate of cell ``k``'s daemon or twin (cell1 keeps the plain names)."""
    return role if k == 1 else f"{role}-cell{k}"


def _cpu(pid: int) -> float:
    try:
        return _cpu_s(pid)
    except OSError:  # ended meanwhile
        return float("nan")


def _host_busy() -> tuple[float, float]:
    """(busy, total) CPU seconds of the host so far, all CPUs (/proc/stat)."""
    with open("/proc/stat", encoding="ascii") as fh:
        f = [int(x) for x in fh.readline().split()[1:]]
    tck = os.sysconf("SC_CLK_TCK")
    idle = f[3] + f[4]
    return (sum(f[:8]) - idle) / tck, sum(f[:8]) / tck


def _pids(cells: dict[int, subprocess.Popen[str]]) -> dict[str, int]:
    """Each daemon's own pid and its device workers' (``cellK``, ``cellK/worker1`` …)."""
    out = {}
    for k, d in cells.items():
        out[f"cell{k}"] = d.pid
        for j, w in enumerate(sorted(child_pids(d.pid))):
            out[f"cell{k}/worker{j + 1}"] = w
    return out


def plant(work: Path, cells: int, seconds: float) -> dict[str, Any]:
    """One run of ``cells`` cells through one router: ``seconds`` measured after a
    warm-up. Long as the plant's start, the measured window and the summary in order."""
    rport = _free_port()
    conf = router_config(cells, f"tls/127.0.0.1:{rport}")
    (work / "router.json5").write_text(json.dumps(conf, indent=1), encoding="utf-8")
    procs: list[subprocess.Popen[str]] = []
    try:
        router = subprocess.Popen(
            [PY, "-m", "daq.cli", "router", "--config", "router.json5"],
            cwd=work, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        procs.append(router)
        assert router.stdout is not None
        json.loads(router.stdout.readline())  # up
        daemons: dict[int, subprocess.Popen[str]] = {}
        echoes: dict[int, subprocess.Popen[str]] = {}
        for k in range(1, cells + 1):
            cell = _cell_config(0, devices=DEVICES, rate_hz=RATE_HZ, batch=500, age_s=0.0)
            cell = cell.replace('name = "bench"', f'name = "cell{k}"')
            cell = cell.replace('[zenoh]\nlisten = ["tcp/127.0.0.1:0"]\n', "")
            cell += "\n" + client_zenoh(rport, identity("daemon", k))
            cell += "\n[recording]\nenabled = false\n"
            (work / f"cell{k}.toml").write_text(cell, encoding="utf-8")
            d = subprocess.Popen(  # stopped by SIGTERM after the measured window
                [PY, "-m", "daq.cli", "run", "--config", f"cell{k}.toml"],
                cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            procs.append(d)
            daemons[k] = d
        for k, d in daemons.items():
            assert d.stdout is not None
            line = d.stdout.readline()
            if not line:
                raise RuntimeError(f"cell{k}'s daemon: {d.communicate()[1][-2000:]}")
            (work / f"sub{k}.toml").write_text(client_zenoh(rport, identity("twin", k)))
            e = subprocess.Popen(
                [PY, "-m", "daq.cli", "echo", "--cell", f"cell{k}", "--config", f"sub{k}.toml",
                 "--stats", "--ready", "--idle", "3", "--duration", str(seconds + 600)],
                cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            procs.append(e)
            echoes[k] = e
        for k, e in echoes.items():  # subscribed (a loaded host starts them slowly)
            assert e.stderr is not None
            if not e.stderr.readline().startswith('{"ready"'):
                raise RuntimeError(f"cell{k}'s subscriber: {e.communicate()[1][-2000:]}")
        time.sleep(WARMUP_S)
        watched = {"router": router.pid, **_pids(daemons)}
        watched |= {f"sub{k}": e.pid for k, e in echoes.items()}
        t0, h0 = time.monotonic(), _host_busy()
        c0 = {name: _cpu(pid) for name, pid in watched.items()}
        time.sleep(seconds)
        t1, h1 = time.monotonic(), _host_busy()
        c1 = {name: _cpu(pid) for name, pid in watched.items()}
        stopped = {}
        for d in daemons.values():
            d.terminate()
        for k, d in daemons.items():
            out, _ = d.communicate(timeout=120)
            stopped[k] = json.loads(out.strip().splitlines()[-1])
        stats = {}
        for k, e in echoes.items():
            out, err = e.communicate(timeout=120)
            if not out.strip():
                raise RuntimeError(f"cell{k}'s subscriber: {err[-2000:]}")
            stats[k] = json.loads(out.strip().splitlines()[-1])
    finally:
        stop_all(procs)
    cpu = {name: (c1[name] - c0[name]) / (t1 - t0) for name in watched}
    return _summary(cells, seconds, cpu, stats, stopped, (h1[0] - h0[0]) / (h1[1] - h0[1]))


def _summary(
    cells: int,
    seconds: float,
    cpu: dict[str, float],
    stats: dict[int, dict[str, Any]],
    stopped: dict[int, dict[str, Any]],
    host_busy: float,
) -> dict[str, Any]:
    """The run's figures: loss, latency, CPU per process kind (cores)."""
    per_cell = {}
    p50s, p99s = [], []
    lost = received = acquired = messages = 0
    for k in range(1, cells + 1):
        data = {key: v for key, v in stats[k]["keys"].items() if key.endswith("/samples")}
        foreign = [key for key in stats[k]["keys"] if not key.startswith(f"cell/cell{k}/")]
        lat = [v["latency_mapped_ms"] for v in data.values() if "latency_mapped_ms" in v]
        p50s += [x["p50"] for x in lat]
        p99s += [x["p99"] for x in lat]
        devices = stopped[k].get("devices", {})
        # what the daemon acquired from the subscriber's first sample on, and did not
        # arrive (holes and the tail alike: the daemon's seq runs 0 .. samples - 1)
        cell_lost = 0
        for key, v in data.items():
            done = int(devices.get(key.split("/")[-2], {}).get("samples", 0))
            cell_lost += max(0, done - int(v["first_seq"]) - v["samples"])
        lost += cell_lost
        received += sum(v["samples"] for v in data.values())
        messages += sum(v["batches"] for v in data.values())
        acquired += sum(int(v.get("samples", 0)) for v in devices.values())
        per_cell[f"cell{k}"] = {
            "keys": len(data),
            "foreign_keys": foreign,
            "lost": cell_lost,
            "seq_gaps": sum(v["seq_gaps"] + v["lost_batches"] for v in data.values()),
            "seq_breaks": sum(v["seq_breaks"] for v in data.values()),
            "p50_ms_worst": max((x["p50"] for x in lat), default=None),
            "p99_ms_worst": max((x["p99"] for x in lat), default=None),
            "daemon_cpu": cpu[f"cell{k}"],
            "workers_cpu": [v for n, v in cpu.items() if n.startswith(f"cell{k}/worker")],
            "subscriber_cpu": cpu[f"sub{k}"],
        }
    workers = [v for n, v in cpu.items() if "/worker" in n]
    daemons = [cpu[f"cell{k}"] for k in range(1, cells + 1)]
    return {
        "cells": cells,
        "devices": cells * DEVICES,
        "rate_hz": RATE_HZ,
        "seconds": seconds,
        "lost": lost,
        "samples_received": received,
        "samples_acquired": acquired,
        # 1 at 1 kHz when the daemon keeps up (a read holds one sample); more when it
        # runs behind and a read takes the backlog
        "samples_per_message": received / messages if messages else None,
        "p50_ms_median": float(np.median(p50s)) if p50s else None,
        "p50_ms_worst": max(p50s, default=None),
        "p99_ms_median": float(np.median(p99s)) if p99s else None,
        "p99_ms_worst": max(p99s, default=None),
        "worker_cpu_per_device": float(np.mean(workers)) if workers else None,
        "daemon_cpu_per_cell": float(np.mean(daemons)),
        "cpu_per_device_all_in": (sum(workers) + sum(daemons)) / (cells * DEVICES),
        "router_cpu": cpu["router"],
        "subscribers_cpu": sum(cpu[f"sub{k}"] for k in range(1, cells + 1)),
        "host_busy_cores": host_busy * (os.cpu_count() or 1),
        "load_avg": os.getloadavg(),
        "per_cell": per_cell,
    }


def run_plant(cells: int, seconds: float, reference: bool = False) -> dict[str, Any]:
    """The PKI (a CA, a daemon and a twin certificate per cell) and one plant run; with
    ``reference``, a one-cell run first, through the same router (same run, same host)."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        names = [identity(r, k) for k in range(2, cells + 1) for r in ("daemon", "twin")]
        subprocess.run(
            [str(ROOT / "scripts/make-test-pki.sh"), str(work / "pki"),
             "DNS:localhost,IP:127.0.0.1", *names],
            check=True, capture_output=True, timeout=120,
        )  # fmt: skip
        ref = None
        if reference:
            ref = {"load_avg_before": os.getloadavg(), **plant(work, 1, seconds)}
        load0 = os.getloadavg()
        out = {"load_avg_before": load0, **plant(work, cells, seconds)}
    if ref is not None:
        out["reference_1_cell"] = {k: v for k, v in ref.items() if k != "per_cell"}
    return out


def run(quick: bool = True) -> list[dict[str, Any]]:
    """Flat rows for ``python -m benchmarks``: 2 cells for 3 s quick, else 4 for 15 s."""
    out = run_plant(2 if quick else 4, 3.0 if quick else 15.0)
    row = {k: v for k, v in out.items() if k not in ("per_cell", "load_avg", "load_avg_before")}
    row["benchmark"] = f"{out['cells']} cells x 3 fake devices at 1 kHz, one daq router (TLS, ACL)"
    row["note"] = "one run; lost by sequence numbers; CPU in cores from /proc"
    return [row]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_cells", description=__doc__)
    ap.add_argument("--cells", type=int, default=4, help="cells, 3 fake devices each (4)")
    ap.add_argument("--seconds", type=float, default=15.0, help="measured seconds (15)")
    ap.add_argument("--no-reference", action="store_true", help="no one-cell reference run before")
    args = ap.parse_args(argv)
    if not 1 <= args.cells <= 50:
        ap.error("--cells: 1 to 50")
    reference = args.cells > 1 and not args.no_reference
    print(json.dumps(run_plant(args.cells, args.seconds, reference), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
