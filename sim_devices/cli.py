"""``sim-cell``: run the emulated cell.

* ``sim-cell serve [--config cell.toml] [--duration S] [--truth PATH]`` starts the devices
  and prints one JSON object per device on stdout (kind, protocol, path or URL, ids), then
  serves until the duration ends or SIGINT/SIGTERM; ptys and sockets are closed on exit.
* ``sim-cell truth [--config cell.toml] --out truth.toml`` writes the truth file.
* ``sim-cell default-config`` prints the default cell's configuration (all keys).

Everything listens on 127.0.0.1 only; no broadcast, no multicast.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import tomli_w

from calibration.errors import CalibrationError
from edges.command import run_command, take_debug_flag
from sim_devices.config import CellConfig
from sim_devices.errors import SimError
from sim_devices.plant import Plant, SimClock

log = logging.getLogger("sim_devices")


class Cell:
    """All devices of one emulated cell, started and stopped together."""

    def __init__(
        self, config: CellConfig, run_dir: Path, t0_monotonic: float | None = None
    ) -> None:
        self.config = config
        self.run_dir = run_dir
        self.plant = Plant.from_config(config, SimClock(config.cell.speed, t0_monotonic))
        self.records: list[dict[str, Any]] = []
        self._closers: list[Any] = []

    def start(self) -> list[dict[str, Any]]:
        cfg = self.config
        if cfg.grating.enabled:
            from sim_devices.grating_reader import GratingReaderDevice, ModbusRtuSlave
            from sim_devices.pty_link import PtyLink

            link = PtyLink(self.run_dir / "grating0")
            self.grating = GratingReaderDevice(self.plant, cfg.grating)
            slave = ModbusRtuSlave(self.grating, link).start()
            self._closers += [slave.stop, link.close]
            self.records.append(
                {
                    "kind": "grating_reader",
                    "protocol": "modbus-rtu",
                    "path": link.path,
                    "tty": link.tty_path,
                    "unit_id": cfg.grating.unit_id,
                    "rate_hz": cfg.grating.rate_hz,
                    "driver": "grating_modbus",
                }
            )
        if cfg.tracker.enabled:
            from sim_devices.pty_link import PtyLink
            from sim_devices.tracker import TrackerInstrument, TrackerServer

            inst = TrackerInstrument(self.plant, cfg.tracker, cfg.effects)
            pty = PtyLink(self.run_dir / "tracker0") if cfg.tracker.serial else None
            server = TrackerServer(inst, tcp_port=cfg.tracker.tcp_port, pty=pty).start()
            self.tracker = inst
            self._closers.append(server.stop)
            if pty is not None:
                self._closers.append(pty.close)
            self.records.append(
                {
                    "kind": "laser_tracker",
                    "protocol": "ascii-tcp",
                    "url": server.url,
                    "host": "127.0.0.1",
                    "port": server.port,
                    "driver": "tracker_ascii",
                }
            )
            if pty is not None:
                self.records.append(
                    {
                        "kind": "laser_tracker",
                        "protocol": "ascii-serial",
                        "path": pty.path,
                        "tty": pty.tty_path,
                        "driver": "tracker_ascii",
                    }
                )
        if cfg.encoders.enabled:
            from sim_devices.encoders import EncoderNodes
            from sim_devices.socketcand import SocketcandServer

            channel = f"simcell-{os.getpid()}-{id(self)}"
            nodes = EncoderNodes(self.plant, cfg.encoders, channel=channel)
            nodes.start_fault_schedule()
            server = SocketcandServer(
                channel,
                bus_name=cfg.encoders.channel,
                port=cfg.encoders.socketcand_port,
                clock=nodes.clock,
                sim_clock=self.plant.clock,
                sync_responder=nodes.sync_frames,
            ).start()
            self.encoders = nodes
            self._closers += [server.stop, nodes.close]
            self.records.append(
                {
                    "kind": "motor_encoders",
                    "protocol": "canopen-socketcand",
                    "url": server.url,
                    "host": "127.0.0.1",
                    "port": server.port,
                    "channel": cfg.encoders.channel,
                    "node_ids": list(nodes.node_ids),
                    "profile": "CiA 406",
                    "driver": "encoder_canopen",
                }
            )
        return self.records

    def stop(self) -> None:
        closers, self._closers = self._closers, []
        for close in closers:
            try:
                close()
            except Exception:
                log.exception("error while stopping a device")


def _load(path: str | None) -> CellConfig:
    return CellConfig.load(path) if path else CellConfig()


KINDS = ("grating", "tracker", "encoders")


def _only(config: CellConfig, kind: str) -> CellConfig:
    """``config`` with every device section but ``kind`` disabled."""
    from dataclasses import replace

    return replace(
        config,
        **{k: replace(getattr(config, k), enabled=(k == kind)) for k in KINDS},
    )


def _child(config: CellConfig, run_dir: Path, t0: float, conn: Any) -> None:
    """One device kind in its own process (its own GIL); stops on SIGTERM."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides
    cell = Cell(config, run_dir, t0)
    try:
        conn.send(cell.start())
        stop.wait()
    finally:
        cell.stop()
        stats = {}
        for name in KINDS:
            dev = getattr(cell, name, None)
            if dev is not None:
                stats[name] = dict(dev.stats)
        stats["cpu_s"] = time.process_time()
        conn.send(stats)
        conn.close()


def cmd_serve(args: argparse.Namespace) -> int:
    import multiprocessing

    config = _load(args.config)
    tmp = None
    if config.cell.run_dir:
        run_dir = Path(config.cell.run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="sim-cell-")
        run_dir = Path(tmp.name)
    truth_path = args.truth or config.cell.truth_file
    if truth_path:
        plant = Plant.from_config(config)
        Path(truth_path).write_text(tomli_w.dumps(plant.truth_document()), encoding="utf-8")
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    t0 = time.monotonic()
    ctx = multiprocessing.get_context("fork")
    children = []
    summary: dict[str, Any] = {"kind": "summary"}
    try:
        for kind in KINDS:
            if not getattr(config, kind).enabled:
                continue
            parent_conn, child_conn = ctx.Pipe()
            proc = ctx.Process(
                target=_child, args=(_only(config, kind), run_dir, t0, child_conn), daemon=True
            )
            proc.start()
            children.append((kind, proc, parent_conn))
        for kind, _proc, conn in children:
            if not conn.poll(60):
                raise SimError(f"device process {kind} did not start")
            for rec in conn.recv():
                # the truth clock's origin on the host's CLOCK_MONOTONIC: device time
                # t_us of a sample latched at wall second w is clock.device_us(w), and w is
                # seconds since this instant (what a test compares mapped timestamps with)
                print(json.dumps({**rec, "t0_monotonic_ns": round(t0 * 1e9)}), flush=True)
        end = time.monotonic() + args.duration if args.duration else None
        while not stop.is_set():
            if end is not None and time.monotonic() >= end:
                break
            if any(not p.is_alive() for _, p, _ in children):
                log.error("a device process died")
                break
            stop.wait(0.1 if end is None else max(0.0, min(0.1, end - time.monotonic())))
    finally:
        for _kind, proc, _conn in children:
            if proc.is_alive():
                os.kill(proc.pid, signal.SIGTERM)
        for kind, proc, conn in children:
            if conn.poll(10):
                with contextlib.suppress(EOFError):
                    summary[kind] = conn.recv()
            proc.join(5)
            if proc.is_alive():
                proc.kill()
        summary["cpu_s_parent"] = time.process_time()
        print(json.dumps(summary), file=sys.stderr, flush=True)
        if tmp is not None:
            tmp.cleanup()
    return 0


def cmd_truth(args: argparse.Namespace) -> int:
    config = _load(args.config)
    plant = Plant.from_config(config)
    Path(args.out).write_text(tomli_w.dumps(plant.truth_document()), encoding="utf-8")
    return 0


def cmd_default_config(_args: argparse.Namespace) -> int:
    sys.stdout.write(CellConfig().dumps())
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="sim-cell", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("serve", help="start the emulated devices")
    p.add_argument("--config", help="cell.toml (default: the built-in default cell)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after S seconds (0: never)")
    p.add_argument("--truth", help="also write the truth file here")
    p.add_argument("--log-level", default="WARNING")
    p.set_defaults(func=cmd_serve)
    t = sub.add_parser("truth", help="write the truth file")
    t.add_argument("--config")
    t.add_argument("--out", required=True)
    t.set_defaults(func=cmd_truth)
    d = sub.add_parser("default-config", help="print the default cell.toml")
    d.set_defaults(func=cmd_default_config)
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(args, "log_level", "WARNING"), stream=sys.stderr, format="%(message)s"
    )
    return run_command(
        f"sim-cell {args.command}",
        lambda: args.func(args),
        user_errors=(SimError, CalibrationError),
        debug=debug,
    )


if __name__ == "__main__":
    sys.exit(main())
