"""Driver throughput with the emulator in the loop: samples/s and CPU per 1000 samples.

Starts ``sim-cell serve`` (one process per device kind), then reads each device through
its driver alone, then all three at once (three threads in this process, as a daemon
would). CPU is process CPU time (user + system): this process for the drivers
(``time.process_time``) and the device's emulator process (``/proc/PID/stat``).

Run standalone: ``.venv/bin/python -m benchmarks.bench_drivers [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

KIND_ORDER = ("grating_reader", "laser_tracker", "motor_encoders")  # spawn order of serve


def _proc_cpu_s(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
        return sorted(int(x) for x in text.split())
    except OSError:
        out = []
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                try:
                    ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                if ppid == pid:
                    out.append(int(d.name))
        return sorted(out)


def _start_cell(tmp: Path) -> tuple[subprocess.Popen, dict[str, dict[str, Any]], dict[str, int]]:
    cfg = tmp / "cell.toml"
    cfg.write_text('[cell]\nprogram = "random"\n')
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sim_devices.cli",
            "serve",
            "--config",
            str(cfg),
            "--duration",
            "600",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    recs: dict[str, dict[str, Any]] = {}
    end = time.monotonic() + 60
    while len(recs) < 4 and time.monotonic() < end:
        line = proc.stdout.readline() if proc.stdout else ""
        if not line:
            break
        r = json.loads(line)
        recs[f"{r['kind']}/{r['protocol']}"] = r
    kids = _children(proc.pid)
    pids = dict(zip(KIND_ORDER, kids, strict=False))
    return proc, recs, pids


SPECS = {
    "grating_modbus": ("grating_reader/modbus-rtu", "path", {}, "grating_reader"),
    "tracker_ascii": ("laser_tracker/ascii-serial", "path", {"rate_hz": 1000.0}, "laser_tracker"),
    "tracker_ascii_tcp": ("laser_tracker/ascii-tcp", "url", {"rate_hz": 1000.0}, "laser_tracker"),
    "encoder_canopen": (
        "motor_encoders/canopen-socketcand",
        "url",
        {"sync_hz": 1000.0},
        "motor_encoders",
    ),
}


def _read_for(name: str, url: str, opts: dict[str, Any], seconds: float, out: dict) -> None:
    from drivers.registry import open_driver

    driver_name = "tracker_ascii" if name.startswith("tracker") else name
    with open_driver(driver_name, url, **opts) as drv:
        drv.read(0.3)  # settle
        n = 0
        lost = 0
        t0 = time.monotonic()
        c0 = time.thread_time()
        while time.monotonic() - t0 < seconds:
            b = drv.read(0.05)
            n += len(b)
        elapsed = time.monotonic() - t0
        out[name] = {
            "samples": n,
            "elapsed_s": elapsed,
            "thread_cpu_s": time.thread_time() - c0,
            "counters": {k: v for k, v in drv.health().counters.items() if v},
        }
        lost = drv.health().counters.get("lost_samples", 0)
        out[name]["lost_samples"] = lost


def run(quick: bool = True) -> list[dict[str, Any]]:
    """Per device, then all together; one dict per measurement."""
    seconds = 3.0 if quick else 10.0
    results: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        proc, recs, pids = _start_cell(Path(tmp))
        try:
            time.sleep(1.0)
            for name, (key, field, opts, kind) in SPECS.items():
                out: dict[str, Any] = {}
                emu0 = _proc_cpu_s(pids.get(kind, -1))
                c0 = time.process_time()
                _read_for(name, recs[key][field], opts, seconds, out)
                drv_cpu = time.process_time() - c0
                emu_cpu = _proc_cpu_s(pids.get(kind, -1)) - emu0
                r = out[name]
                n = max(r["samples"], 1)
                results.append(
                    {
                        "name": f"drivers/{name}",
                        "samples_per_s": r["samples"] / r["elapsed_s"],
                        "driver_cpu_ms_per_1000": 1e3 * drv_cpu / n * 1000,
                        "emulator_cpu_ms_per_1000": 1e3 * emu_cpu / n * 1000,
                        "lost_samples": r["lost_samples"],
                        "counters": r["counters"],
                        "seconds": seconds,
                    }
                )
            # all three at once (tracker on its serial link)
            together = ("grating_modbus", "tracker_ascii", "encoder_canopen")
            out = {}
            emu0 = {k: _proc_cpu_s(p) for k, p in pids.items()}
            c0 = time.process_time()
            threads = [
                threading.Thread(
                    target=_read_for,
                    args=(nm, recs[SPECS[nm][0]][SPECS[nm][1]], SPECS[nm][2], seconds, out),
                )
                for nm in together
            ]
            for t in threads:
                t.start()
            for t in threads:
                t.join(seconds + 60)
            drv_cpu = time.process_time() - c0
            emu_cpu = sum(_proc_cpu_s(p) - emu0[k] for k, p in pids.items())
            total = sum(out[nm]["samples"] for nm in together if nm in out)
            results.append(
                {
                    "name": "drivers/all_three_together",
                    "samples_per_s": {
                        nm: out[nm]["samples"] / out[nm]["elapsed_s"]
                        for nm in together
                        if nm in out
                    },
                    "total_samples_per_s": total / seconds,
                    "driver_cpu_ms_per_1000": 1e3 * drv_cpu / max(total, 1) * 1000,
                    "emulator_cpu_ms_per_1000": 1e3 * emu_cpu / max(total, 1) * 1000,
                    "driver_process_cpu_fraction": drv_cpu / seconds,
                    "emulator_cpu_fraction": emu_cpu / seconds,
                    "lost_samples": {nm: out[nm]["lost_samples"] for nm in together if nm in out},
                    "seconds": seconds,
                }
            )
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args(argv)
    for r in run(args.quick):
        print(json.dumps(r, default=lambda o: float(o) if isinstance(o, np.floating) else str(o)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
