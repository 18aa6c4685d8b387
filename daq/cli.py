"""``daq``: the acquisition daemon's command line.

Commands (docs/daq.md)::

    daq run [--config cell.toml] [--duration S] [--record [PATH]]   the daemon
    daq record KEYEXPR -o FILE.mcap [--duration S]                   zenoh -> MCAP
    daq replay FILE.mcap [--speed X | --fast] [--loop] [--start S] [--topic EXPR]
    daq recover FILE.mcap [-o OUT.mcap]                              rewrite a truncated file
    daq info FILE.mcap                                               channels and counts (streams)
    daq echo KEYEXPR [--stats [--stats-window S]] [--jsonl FILE] [--duration S]   look at a key
    daq schema KEY                                                   the JSON schema of a key

``echo`` and ``record`` take ``--realtime-priority N`` (SCHED_FIFO, as ``[publish]
realtime_priority`` for ``run``).

zenoh settings: ``--config`` file's ``[zenoh]`` table, ``DAQ_ZENOH_*`` variables and
``--mode/--listen/--connect`` arguments, in rising precedence. Sources (``run``,
``replay``) listen on ``tcp/127.0.0.1:7447`` by default; sinks (``echo``, ``record``,
``schema``) connect there and listen nowhere.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import replace
from typing import Any

from daq.config import DaqConfig, ZenohConfig, load
from daq.errors import DaqError
from edges.command import run_command, take_debug_flag

COMMANDS: dict[str, str] = {
    "run": "the acquisition daemon (no --config: the emulated default cell, recorded)",
    "record": "record zenoh keys to an MCAP file",
    "replay": "republish an MCAP recording over zenoh",
    "recover": "rewrite a truncated MCAP recording whole",
    "info": "list the channels and message counts of an MCAP file (streaming)",
    "echo": "subscribe to a key expression and print or summarise batches",
    "schema": "print the JSON schema of a key (zenoh query <key>/@schema)",
}


def _whole_seconds(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of seconds >= 1, got {text!r}")
    return value


def _zenoh_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--mode", choices=("peer", "client", "router"), help="zenoh mode")
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="listen endpoint")
    g.add_argument("--connect", action="append", metavar="ENDPOINT", help="connect endpoint")


def _zenoh_overrides(args: argparse.Namespace) -> dict[str, Any]:
    z: dict[str, Any] = {}
    if getattr(args, "mode", None):
        z["mode"] = args.mode
    if getattr(args, "listen", None):
        z["listen"] = [e for e in args.listen if e != "none"]
    if getattr(args, "connect", None):
        z["connect"] = [e for e in args.connect if e != "none"]
    return z


def resolve(args: argparse.Namespace, extra: dict[str, dict[str, Any]] | None = None) -> DaqConfig:
    overrides: dict[str, dict[str, Any]] = dict(extra or {})
    z = _zenoh_overrides(args)
    if z:
        overrides["zenoh"] = {**overrides.get("zenoh", {}), **z}
    return load(getattr(args, "config", None), overrides=overrides)


def sink_zenoh(args: argparse.Namespace) -> ZenohConfig:
    """zenoh settings of a sink: connect to where the source listens, listen nowhere."""
    user = _zenoh_overrides(args)
    zc = resolve(argparse.Namespace(config=getattr(args, "config", None))).zenoh
    connect = list(zc.connect) if zc.mode == "client" else [*zc.listen, *zc.connect]
    zc = replace(zc, listen=(), connect=tuple(dict.fromkeys(connect)))
    if "mode" in user:
        zc = replace(zc, mode=user["mode"])
    if "listen" in user:
        zc = replace(zc, listen=tuple(user["listen"]))
    if "connect" in user:
        zc = replace(zc, connect=tuple(user["connect"]))
    return zc


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="daq",
        description="Acquisition daemon: timestamped samples over zenoh, MCAP recording, replay.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help=COMMANDS["run"])
    p.add_argument("--config", help="cell TOML (default: $DAQ_CONFIG, else the emulated cell)")
    p.add_argument("--duration", type=float, help="stop by itself after S seconds")
    p.add_argument(
        "--record", nargs="?", const="", metavar="PATH", help="record to MCAP (PATH optional)"
    )
    p.add_argument("--no-record", action="store_true", help="do not record (emulated cell)")
    p.add_argument("--sim-config", help="emulated cell TOML for sim-cell (no --config only)")
    p.add_argument(
        "--rate", type=float, default=1000.0, help="emulated tracker/encoder rate, Hz (1000)"
    )
    p.add_argument("--cell", help="cell name (key chunk)")
    _zenoh_args(p)

    p = sub.add_parser("record", help=COMMANDS["record"])
    p.add_argument("key", nargs="?", default="cell/**", help="key expression (default cell/**)")
    p.add_argument("-o", "--output", required=True, help="MCAP file to write")
    p.add_argument("--config", help="take zenoh settings from this cell TOML")
    p.add_argument("--duration", type=float, help="stop after S seconds")
    _realtime_arg(p)
    _zenoh_args(p)

    p = sub.add_parser("replay", help=COMMANDS["replay"])
    p.add_argument("file", help="MCAP recording")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--speed", type=float, default=1.0, help="×N of real time (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--loop", action="store_true", help="start over at the end")
    p.add_argument("--start", type=float, default=0.0, help="skip the first S seconds")
    p.add_argument("--topic", action="append", help="key expression filter (repeatable)")
    p.add_argument("--duration", type=float, help="stop after S seconds of wall time")
    p.add_argument(
        "--wait-subscribers",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for a matching subscriber before starting",
    )
    p.add_argument("--config", help="take zenoh settings from this cell TOML")
    _zenoh_args(p)

    p = sub.add_parser("recover", help=COMMANDS["recover"])
    p.add_argument("file")
    p.add_argument("-o", "--output", help="output (default: rewrite FILE in place)")

    p = sub.add_parser("info", help=COMMANDS["info"])
    p.add_argument("file")

    p = sub.add_parser("echo", help=COMMANDS["echo"])
    p.add_argument("key", nargs="?", default="cell/**")
    p.add_argument("--config", help="take zenoh settings from this cell TOML")
    p.add_argument("--duration", type=float)
    p.add_argument("--count", type=int, help="stop after N batches")
    p.add_argument("--idle", type=float, help="stop after S seconds without data (once started)")
    p.add_argument("--jsonl", metavar="FILE", help="write every batch as JSON lines ('-': stdout)")
    p.add_argument("--stats", action="store_true", help="print a JSON summary at the end")
    p.add_argument(
        "--stats-window",
        type=_whole_seconds,
        metavar="S",
        help="with --stats: latency percentiles also per S-second window of receive time",
    )
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--ready", action="store_true", help="say when subscribed (stderr)")
    _realtime_arg(p)
    _zenoh_args(p)

    p = sub.add_parser("schema", help=COMMANDS["schema"])
    p.add_argument("key", help="a data key or a key expression (cell/**)")
    p.add_argument("--config", help="take zenoh settings from this cell TOML")
    p.add_argument("--timeout", type=float, default=2.0)
    _zenoh_args(p)
    return parser


def _realtime_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--realtime-priority",
        type=int,
        default=0,
        metavar="N",
        help="run under SCHED_FIFO priority N (1-99; 0: normal); a subscriber on the "
        "daemon's machine needs the daemon's priority to keep up when CPU is short",
    )


def _schema(args: argparse.Namespace) -> int:
    from daq.bus import open_session, schema_key

    session = open_session(sink_zenoh(args))
    found = 0
    try:
        key = args.key if args.key.endswith("@schema") else schema_key(args.key)
        for reply in session.get(key, timeout=args.timeout):
            if reply.ok is not None:
                found += 1
                print(json.dumps(json.loads(reply.ok.payload.to_bytes()), indent=1))
    finally:
        session.close()
    if not found:
        print(f"daq schema: no schema answered for {args.key}", file=sys.stderr)
        return 1
    return 0


def _run_command(args: argparse.Namespace) -> int:
    if args.command == "run":
        from daq.daemon import main_run

        return main_run(args)
    if getattr(args, "realtime_priority", 0):
        from daq.scheduling import set_realtime

        set_realtime(args.realtime_priority, "--realtime-priority")
    if args.command == "record":
        from daq.recording import main_record

        return main_record(args, sink_zenoh(args))
    if args.command == "replay":
        from daq.replay import main_replay

        return main_replay(args, resolve(args).zenoh)
    if args.command == "recover":
        from daq.recording import main_recover

        return main_recover(args)
    if args.command == "info":
        from daq.recording import main_info

        return main_info(args)
    if args.command == "echo":
        from daq.echo import main_echo

        return main_echo(args, sink_zenoh(args))
    return _schema(args)


def main(argv: list[str] | None = None) -> int:
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return run_command(
        f"daq {args.command}", lambda: _run_command(args), user_errors=(DaqError,), debug=debug
    )


if __name__ == "__main__":
    sys.exit(main())
