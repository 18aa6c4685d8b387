"""Driver throughput with the emulator in the loop: samples/s and CPU per 1000 samples.

Starts ``sim-cell serve`` (one process per device kind), then reads each device through
its driver alone, then all three at once (three threads in this process, as a daemon
would). Each run opens its drivers, lets them settle (connect, catch up with what the
device buffered) and only then measures a window of ``seconds``: the drivers' threads
start and end the window together (barriers). CPU is process CPU time (user + system) in
that window: this process for the drivers (``time.process_time``: the reading threads and
the drivers' own threads) and each emulator process (``/proc/PID/stat``). Lost samples
are counted in the window and since connect.

Rows: one per device alone; for all three together one row per device (its rate, its
losses, its emulator process's CPU) and a summary row with the CPU fraction of every
process and what is left of the machine's cores.

Run standalone: ``.venv/bin/python -m benchmarks.bench_drivers [--quick] [--json]``.
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


class _Window:
    """Start and end of the measuring window shared by the reading threads.

    Every thread keeps reading (uncounted) while it waits for the others, so no device
    piles up a backlog that the window would then count.
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self.lock = threading.Lock()
        self.ready = 0
        self.done = 0
        self.go = threading.Event()
        self.stop = threading.Event()

    def mark(self, what: str) -> None:
        with self.lock:
            setattr(self, what, getattr(self, what) + 1)

    def wait_all(self, what: str, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self.lock:
                if getattr(self, what) >= self.n:
                    return True
            time.sleep(0.01)
        return False


def _worker(
    name: str,
    url: str,
    opts: dict[str, Any],
    settle_s: float,
    seconds: float,
    win: _Window,
    out: dict[str, Any],
) -> None:
    from drivers.registry import open_driver

    driver_name = "tracker_ascii" if name.startswith("tracker") else name
    drv = None
    marked = {"ready": False, "done": False}
    try:
        drv = open_driver(driver_name, url, **opts)
        # settle: connected and caught up with what the device buffered before
        t_settle = time.monotonic()
        while time.monotonic() - t_settle < 10.0:
            b = drv.read(0.05)
            if time.monotonic() - t_settle >= settle_s and len(b) < 200:
                break
        win.mark("ready")
        marked["ready"] = True
        while not win.go.is_set():
            drv.read(0.02)
        lost0 = drv.health().counters.get("lost_samples", 0)
        n = 0
        t0 = time.monotonic()
        c0 = time.thread_time()
        while time.monotonic() - t0 < seconds:
            n += len(drv.read(0.05))
        elapsed = time.monotonic() - t0
        thread_cpu = time.thread_time() - c0
        counters = drv.health().counters
        out[name] = {
            "samples": n,
            "elapsed_s": elapsed,
            "read_thread_cpu_s": thread_cpu,
            "lost_in_window": counters.get("lost_samples", 0) - lost0,
            "lost_since_connect": counters.get("lost_samples", 0),
            "counters": {
                k: v for k, v in counters.items() if v and k not in ("samples", "batches")
            },
        }
        win.mark("done")
        marked["done"] = True
        while not win.stop.is_set():
            drv.read(0.02)
    except Exception as exc:  # report, never leave the others waiting
        out[name] = {"error": f"{type(exc).__name__}: {exc}"}
        for what, done in marked.items():
            if not done:
                win.mark(what)
    finally:
        if drv is not None:
            drv.close()


def _measure(
    names: list[str],
    recs: dict[str, dict[str, Any]],
    pids: dict[str, int],
    seconds: float,
    settle_s: float,
) -> tuple[dict[str, Any], float, float, dict[str, float]]:
    """Run ``names`` together; (per-driver results, window s, driver CPU s, emulator CPU s)."""
    win = _Window(len(names))
    out: dict[str, Any] = {}
    threads = [
        threading.Thread(
            target=_worker,
            args=(nm, recs[SPECS[nm][0]][SPECS[nm][1]], SPECS[nm][2], settle_s, seconds, win, out),
        )
        for nm in names
    ]
    for t in threads:
        t.start()
    win.wait_all("ready", 120)
    w0 = time.monotonic()
    c0 = time.process_time()
    e0 = {k: _proc_cpu_s(p) for k, p in pids.items()}
    win.go.set()
    win.wait_all("done", seconds + 60)
    window = time.monotonic() - w0
    drv_cpu = time.process_time() - c0
    emu_cpu = {k: _proc_cpu_s(p) - e0[k] for k, p in pids.items()}
    win.stop.set()
    for t in threads:
        t.join(30)
    return out, window, drv_cpu, emu_cpu


def _device_row(name: str, r: dict[str, Any], emu_cpu_s: float, drv_cpu_s: float | None) -> dict:
    if "error" in r:
        return {"benchmark": name, "note": r["error"]}
    n = max(r["samples"], 1)
    row: dict[str, Any] = {
        "benchmark": name,
        "samples_per_s": r["samples"] / r["elapsed_s"],
        "driver_cpu_ms_per_1000": None if drv_cpu_s is None else 1e6 * drv_cpu_s / n,
        "read_thread_cpu_ms_per_1000": 1e6 * r["read_thread_cpu_s"] / n,
        "emulator_cpu_ms_per_1000": 1e6 * emu_cpu_s / n,
        "emulator_cpu_fraction": emu_cpu_s / r["elapsed_s"],
        "lost_in_window": r["lost_in_window"],
        "lost_since_connect": r["lost_since_connect"],
        "seconds": r["elapsed_s"],
        "note": " ".join(f"{k}={v}" for k, v in sorted(r["counters"].items())),
    }
    return row


def run(quick: bool = True) -> list[dict[str, Any]]:
    """Per device alone, then all three together; flat rows (see the module docstring)."""
    seconds = 3.0 if quick else 10.0
    settle_s = 1.0
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        proc, recs, pids = _start_cell(Path(tmp))
        try:
            time.sleep(1.0)
            for name in SPECS:
                kind = SPECS[name][3]
                load0 = os.getloadavg()[0]
                out, window, drv_cpu, emu_cpu = _measure([name], recs, pids, seconds, settle_s)
                row = _device_row(f"{name} alone", out[name], emu_cpu.get(kind, 0.0), drv_cpu)
                row["driver_cpu_fraction"] = drv_cpu / window
                row["loadavg_1min"] = load0
                rows.append(row)
            together = ["grating_modbus", "tracker_ascii", "encoder_canopen"]
            load0 = os.getloadavg()[0]
            out, window, drv_cpu, emu_cpu = _measure(together, recs, pids, seconds, settle_s)
            total = 0
            for name in together:
                r = out[name]
                rows.append(
                    _device_row(f"{name} together", r, emu_cpu.get(SPECS[name][3], 0.0), None)
                )
                total += r.get("samples", 0)
            emu_total = sum(emu_cpu.values())
            summary: dict[str, Any] = {
                "benchmark": "all three together",
                "samples_per_s": total / window,
                "driver_cpu_ms_per_1000": 1e6 * drv_cpu / max(total, 1),
                "emulator_cpu_ms_per_1000": 1e6 * emu_total / max(total, 1),
                "driver_cpu_fraction": drv_cpu / window,
                "emulator_cpu_fraction": emu_total / window,
                "cores_used": (drv_cpu + emu_total) / window,
                "cores_spare_of_2": 2.0 - (drv_cpu + emu_total) / window,
                "lost_in_window": sum(out[n].get("lost_in_window", 0) for n in together),
                "lost_since_connect": sum(out[n].get("lost_since_connect", 0) for n in together),
                "min_device_samples_per_s": min(
                    out[n].get("samples", 0) / out[n].get("elapsed_s", 1.0) for n in together
                ),
                "loadavg_1min": load0,
                "seconds": window,
                "note": "cpu fractions: "
                + " ".join(f"{k}={v / window:.3f}" for k, v in emu_cpu.items())
                + f" drivers={drv_cpu / window:.3f}",
            }
            rows.append(summary)
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="3 s windows (default 10 s)")
    p.add_argument("--json", action="store_true", help="one JSON object per row")
    args = p.parse_args(argv)
    rows = run(args.quick)
    if args.json:
        for r in rows:
            print(json.dumps(r))
    else:
        from benchmarks import format_table

        print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
