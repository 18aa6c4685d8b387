"""``sim-cell``: run the emulated cell.

* ``sim-cell serve [--config cell.toml] [--duration S] [--truth PATH]`` starts the devices
  and prints one JSON object per device on stdout (kind, protocol, path or URL, ids), then
  serves until the duration ends or SIGINT/SIGTERM; ptys and sockets are closed on exit.
* ``sim-cell truth [--config cell.toml] --out truth.toml`` writes the truth file.
* ``sim-cell default-config`` prints the default cell's configuration (all keys).

A mistake in the options or the config is one line on stderr and exit 2, before any device
starts; a truth file is written atomically and never over an input (``--truth`` onto the
``--config`` file is refused). ``--debug`` anywhere shows tracebacks.

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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import tomli_w

from calibration.errors import CalibrationError
from edges.command import one_line, os_error_text, run_command, take_debug_flag
from edges.options import OptionParser
from edges.outputs import OutputSet
from edges.stop_signals import on_stop_signals
from sim_devices.config import CellConfig, load_cell, number_option
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
        """Start the enabled devices; one record per device (what ``serve`` prints)."""
        cfg = self.config
        if cfg.grating.enabled:
            self._start_grating()
        if cfg.tracker.enabled:
            self._start_tracker()
        if cfg.encoders.enabled:
            self._start_encoders()
        return self.records

    def _start_grating(self) -> None:
        """The grating reader: Modbus RTU on a pty."""
        from sim_devices.grating_reader import GratingReaderDevice, ModbusRtuSlave
        from sim_devices.pty_link import PtyLink

        cfg = self.config
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

    def _start_tracker(self) -> None:
        """The laser tracker: ASCII over TCP, and over a pty when ``serial``."""
        from sim_devices.pty_link import PtyLink
        from sim_devices.tracker import TrackerInstrument, TrackerServer

        cfg = self.config
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

    def _start_encoders(self) -> None:
        """The motor encoders: CANopen nodes behind a socketcand server."""
        from sim_devices.encoders import EncoderNodes
        from sim_devices.socketcand import SocketcandServer

        cfg = self.config
        channel = f"simcell-{os.getpid()}-{id(self)}"
        nodes = EncoderNodes(self.plant, cfg.encoders, channel=channel)
        nodes.start_fault_schedule()
        can_server = SocketcandServer(
            channel,
            bus_name=cfg.encoders.channel,
            port=cfg.encoders.socketcand_port,
            clock=nodes.clock,
            sim_clock=self.plant.clock,
            sync_responder=nodes.sync_frames,
        ).start()
        self.encoders = nodes
        self._closers += [can_server.stop, nodes.close]
        self.records.append(
            {
                "kind": "motor_encoders",
                "protocol": "canopen-socketcand",
                "url": can_server.url,
                "host": "127.0.0.1",
                "port": can_server.port,
                "channel": cfg.encoders.channel,
                "node_ids": list(nodes.node_ids),
                "profile": "CiA 406",
                "driver": "encoder_canopen",
            }
        )

    def stop(self) -> None:
        closers, self._closers = self._closers, []
        for close in closers:
            try:
                close()
            except Exception:
                log.exception("error while stopping a device")


def _load(path: str | None) -> CellConfig:
    """The cell configuration of ``--config`` (None: the default cell), checked against
    its robot."""
    if path is not None and not path.strip():
        raise SimError("--config: empty path; give a cell.toml or leave the option out")
    return load_cell(path)


def _inputs(args: argparse.Namespace, config: CellConfig) -> list[str | None]:
    """The files a run reads (an output may be none of them)."""
    robot = config.cell.robot
    return [args.config, robot if Path(robot).exists() else None, config.cell.plan or None]


KINDS = ("grating", "tracker", "encoders")
#: the configuration key of each device kind's listening port, for a bind error's hint
PORT_KEYS = {"tracker": ("tracker", "tcp_port"), "encoders": ("encoders", "socketcand_port")}


def _only(config: CellConfig, kind: str) -> CellConfig:
    """``config`` with every device section but ``kind`` disabled."""
    from dataclasses import replace

    return replace(
        config,
        **{k: replace(getattr(config, k), enabled=(k == kind)) for k in KINDS},
    )


def _child(config: CellConfig, run_dir: Path, t0: float, conn: Any) -> None:
    """One device kind in its own process (its own GIL); stops on SIGTERM.

    Sends ``("ok", records)`` once the devices listen, or ``("user", text)`` /
    ``("bug", text)`` when they could not start (a port in use, a pty refused: the user's
    to fix; anything else a bug), then the device statistics when stopped."""
    stop = threading.Event()
    on_stop_signals(stop.set, (signal.SIGTERM,))  # not in the handler: edges/stop_signals.py
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides
    cell: Cell | None = None
    try:
        cell = Cell(config, run_dir, t0)
        records = cell.start()
    except Exception as exc:
        if cell is not None:
            cell.stop()
        if isinstance(exc, OSError):
            conn.send(("user", os_error_text(exc)))
        elif isinstance(exc, SimError | CalibrationError):
            conn.send(("user", one_line(str(exc))))
        else:
            conn.send(("bug", f"{type(exc).__name__}: {one_line(str(exc))}"))
        conn.close()
        return
    try:
        conn.send(("ok", records))
        stop.wait()
    finally:
        cell.stop()
        stats: dict[str, Any] = {}
        for name in KINDS:
            dev = getattr(cell, name, None)
            if dev is not None:
                stats[name] = dict(dev.stats)
        stats["cpu_s"] = time.process_time()
        conn.send(stats)
        conn.close()


def _started(kind: str, conn: Any, config: CellConfig, source: str) -> list[dict[str, Any]]:
    """The records of device process ``kind`` once it listens; its start error otherwise
    (:class:`SimError` for the user's: a port in use, a pty refused)."""
    if not conn.poll(60):
        raise RuntimeError(f"device process {kind} did not start within 60 s")
    try:
        status, payload = conn.recv()
    except EOFError:
        raise RuntimeError(f"device process {kind} ended before it started") from None
    if status == "ok":
        return list(payload)
    if status == "user":
        hint = ""
        if kind in PORT_KEYS:
            table, key = PORT_KEYS[kind]
            hint = f" ([{table}] {key} = {getattr(getattr(config, table), key)})"
        raise SimError(f"{source}: the {kind} device could not start: {payload}{hint}")
    raise RuntimeError(f"device process {kind}: {payload}")


def _run_dir(config: CellConfig, source: str) -> Path:
    run_dir = Path(config.cell.run_dir)
    where = f"{source}: [cell]: key 'run_dir'"
    if run_dir.exists() and not run_dir.is_dir():
        raise SimError(f"{where}: {run_dir} exists and is not a directory")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimError(f"{where}: cannot create {run_dir}: {exc.strerror or exc}") from None
    return run_dir


def _stage_truth(outputs: OutputSet, plant_config: CellConfig, path: str, option: str) -> None:
    """The truth document staged for ``path`` (it appears when ``outputs`` commits)."""
    staged = outputs.file(path, option)  # refused (an input, a directory) before any work
    staged.write_text(
        tomli_w.dumps(Plant.from_config(plant_config).truth_document()), encoding="utf-8"
    )


def cmd_serve(args: argparse.Namespace) -> int:
    """Start the devices; the truth file (``--truth`` or ``[cell] truth_file``) appears
    once every device listens, before they are announced on stdout, and not at all when
    one could not start."""
    import multiprocessing

    config = _load(args.config)
    source = args.config or "default cell config"
    if args.truth is not None and not args.truth.strip():
        raise SimError("--truth: empty path; give a file to write")
    truth_path = args.truth or config.cell.truth_file
    truth_option = "--truth" if args.truth else f"{source}: [cell]: key 'truth_file':"
    with OutputSet(inputs=_inputs(args, config), error=SimError) as outputs:
        if truth_path:
            _stage_truth(outputs, config, truth_path, truth_option)
        tmp = None
        made = False
        if config.cell.run_dir:
            made = not Path(config.cell.run_dir).exists()
            run_dir = _run_dir(config, source)
        else:
            tmp = tempfile.TemporaryDirectory(prefix="sim-cell-")
            run_dir = Path(tmp.name)
        try:
            ctx = multiprocessing.get_context("fork")
            return _serve(config, run_dir, args.duration, source, ctx, outputs.commit)
        except BaseException:
            if made:  # a run that failed leaves no directory it made (only if empty)
                with contextlib.suppress(OSError):
                    run_dir.rmdir()
            raise
        finally:
            if tmp is not None:
                tmp.cleanup()


def _serve(
    config: CellConfig,
    run_dir: Path,
    duration: float,
    source: str,
    ctx: Any,
    on_started: Callable[[], object],
) -> int:
    """Run the device processes until ``duration`` (0: a signal); ``on_started`` runs once
    all of them listen, before they are announced."""
    stop = threading.Event()
    on_stop_signals(stop.set)  # not stop.set() in the handler: edges/stop_signals.py
    t0 = time.monotonic()
    children: list[tuple[str, Any, Any]] = []  # kind, process, its end of the pipe
    summary: dict[str, Any] = {"kind": "summary"}
    started = False
    try:
        _spawn_devices(children, config, run_dir, t0, ctx)
        # every device listens before any is announced: a reader never sees half a cell
        records = [
            rec for kind, _p, conn in children for rec in _started(kind, conn, config, source)
        ]
        on_started()
        started = True
        for rec in records:
            # the truth clock's origin on the host's CLOCK_MONOTONIC: device time
            # t_us of a sample latched at wall second w is clock.device_us(w), and w is
            # seconds since this instant (what a test compares mapped timestamps with)
            print(json.dumps({**rec, "t0_monotonic_ns": round(t0 * 1e9)}), flush=True)
        _wait_devices(stop, children, duration)
    finally:
        _stop_devices(children, summary if started else None)
        summary["cpu_s_parent"] = time.process_time()
        if started:
            print(json.dumps(summary), file=sys.stderr, flush=True)
    return 0


def _spawn_devices(
    children: list[tuple[str, Any, Any]], config: CellConfig, run_dir: Path, t0: float, ctx: Any
) -> None:
    """A process per enabled device kind, appended to ``children`` as it starts (so a
    failure part way stops those already running)."""
    for kind in KINDS:
        if not getattr(config, kind).enabled:
            continue
        parent_conn, child_conn = ctx.Pipe()
        proc = ctx.Process(
            target=_child, args=(_only(config, kind), run_dir, t0, child_conn), daemon=True
        )
        proc.start()
        children.append((kind, proc, parent_conn))


def _wait_devices(
    stop: threading.Event, children: list[tuple[str, Any, Any]], duration: float
) -> None:
    """Until ``stop``, ``duration`` seconds (0: no limit) or a device process dies."""
    end = time.monotonic() + duration if duration else None
    while not stop.is_set():
        if end is not None and time.monotonic() >= end:
            break
        if any(not p.is_alive() for _, p, _ in children):
            log.error("a device process died")
            break
        stop.wait(0.1 if end is None else max(0.0, min(0.1, end - time.monotonic())))


def _stop_devices(children: list[tuple[str, Any, Any]], summary: dict[str, Any] | None) -> None:
    """SIGTERM to every device process, then each one's last counters into ``summary``
    (None: the cell never started, nothing is waited for), killed if it lingers."""
    for _kind, proc, _conn in children:
        if proc.is_alive():
            os.kill(proc.pid, signal.SIGTERM)
    for kind, proc, conn in children:
        if summary is not None and conn.poll(10):
            with contextlib.suppress(EOFError):
                summary[kind] = conn.recv()
        proc.join(5)
        if proc.is_alive():
            proc.kill()


def cmd_truth(args: argparse.Namespace) -> int:
    if not args.out.strip():
        raise SimError("--out: empty path; give the truth file to write")
    config = _load(args.config)
    with OutputSet(inputs=_inputs(args, config), error=SimError) as outputs:
        _stage_truth(outputs, config, args.out, "--out")
    return 0


def cmd_default_config(_args: argparse.Namespace) -> int:
    sys.stdout.write(CellConfig().dumps())
    return 0


LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def build_parser() -> argparse.ArgumentParser:
    parser = OptionParser(prog="sim-cell", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("serve", help="start the emulated devices")
    p.add_argument("--config", help="cell.toml (default: the built-in default cell)")
    p.add_argument(
        "--duration",
        type=number_option(0.0, what="s; 0: until SIGINT/SIGTERM"),
        default=0.0,
        help="stop after S seconds (0: never)",
    )
    p.add_argument("--truth", help="also write the truth file here")
    p.add_argument("--log-level", default="WARNING", type=str.upper, choices=LOG_LEVELS)
    p.set_defaults(func=cmd_serve)
    t = sub.add_parser("truth", help="write the truth file")
    t.add_argument("--config")
    t.add_argument("--out", required=True)
    t.set_defaults(func=cmd_truth)
    d = sub.add_parser("default-config", help="print the default cell.toml")
    d.set_defaults(func=cmd_default_config)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
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
