"""``daq``: the acquisition daemon's command line.

Commands (docs/daq.md)::

    daq run [--config cell.toml] [--duration S] [--record [PATH]]   the daemon
    daq record KEYEXPR -o FILE.mcap [--duration S]                   zenoh -> MCAP
    daq replay FILE.mcap [--speed X | --fast] [--loop] [--start S] [--topic EXPR]
    daq recover FILE.mcap [-o OUT.mcap | --in-place]                 a damaged file's readable part
    daq info FILE.mcap                                               channels, counts, damage
    daq echo KEYEXPR [--stats [--stats-window S]] [--jsonl FILE] [--duration S]   look at a key
    daq schema KEY                                                   the JSON schema of a key

``echo`` and ``record`` take ``--realtime-priority N`` (SCHED_FIFO, as ``[publish]
realtime_priority`` for ``run``).

zenoh settings: ``--config`` file's ``[zenoh]`` table, ``DAQ_ZENOH_*`` variables and
``--mode/--listen/--connect`` arguments, in rising precedence. Sources (``run``,
``replay``) listen on ``tcp/127.0.0.1:7447`` by default; sinks (``echo``, ``record``,
``schema``) connect there and listen nowhere.

Options are checked as they are parsed: a mistake is one line on stderr naming the
option, exit 2 (``--speed 0``, ``--start -5``, ``--count 0``, ``--duration nan``, a key
expression zenoh refuses).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import sys
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from daq.config import ENDPOINT_RE, DaqConfig, ZenohConfig, load
from daq.errors import DaqError
from edges.command import one_line, run_command, take_debug_flag

COMMANDS: dict[str, str] = {
    "run": "the acquisition daemon (no --config: the emulated default cell, recorded)",
    "record": "record zenoh keys to an MCAP file",
    "replay": "republish an MCAP recording over zenoh",
    "recover": "write the readable part of a damaged MCAP recording as a whole file",
    "info": "channels, message counts and damage of an MCAP file (streaming)",
    "echo": "subscribe to a key expression and print or summarise batches",
    "schema": "print the JSON schema of a key (zenoh query <key>/@schema)",
}


class OptionParser(argparse.ArgumentParser):
    """``argparse`` whose usage errors are one line, ``PROG: error: MESSAGE (see PROG
    --help)``, exit 2, like every other user mistake (its subcommands' parsers too)."""

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


def number(
    lo: float | None = None, *, above: bool = False, hi: float | None = None
) -> Callable[[str], float]:
    """An ``argparse`` ``type=``: a finite float >= ``lo`` (> ``lo`` when ``above``), <=
    ``hi``; ``nan``, ``inf`` and values outside are refused naming the bound."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if lo is not None and (v <= lo if above else v < lo):
            raise argparse.ArgumentTypeError(
                f"must be {'>' if above else '>='} {lo:g}, got {text!r}"
            )
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi:g}, got {text!r}")
        return v

    parse.__name__ = "number"
    return parse


def integer(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An ``argparse`` ``type=``: an integer in ``lo..hi``."""

    def parse(text: str) -> int:
        if not re.fullmatch(r"\s*[+-]?[0-9]+\s*", text):
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}")
        v = int(text)
        if v < lo or (hi is not None and v > hi):
            rng = f">= {lo}" if hi is None else f"{lo}-{hi}"
            raise argparse.ArgumentTypeError(f"must be {rng}, got {text!r}")
        return v

    parse.__name__ = "integer"
    return parse


def key_expr(text: str) -> str:
    """An ``argparse`` ``type=``: a key expression zenoh accepts (``cell/**``)."""
    import zenoh

    try:
        zenoh.KeyExpr(text)
    except Exception as exc:
        why = re.sub(r" at \S+:\d+\.?$", "", str(exc).strip())  # zenoh's source location
        raise argparse.ArgumentTypeError(f"not a valid key expression: {why}") from None
    return text


def endpoint(text: str) -> str:
    """An ``argparse`` ``type=``: a zenoh endpoint ``<protocol>/<address>`` (``none``:
    an empty list)."""
    if text != "none" and not ENDPOINT_RE.fullmatch(text):
        raise argparse.ArgumentTypeError(
            f"expected <protocol>/<address> (tcp/127.0.0.1:7447) or none, got {text!r}"
        )
    return text


def path_text(text: str) -> str:
    """An ``argparse`` ``type=``: a path, not empty."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    return text


def record_path(text: str) -> str:
    """An ``argparse`` ``type=``: a recording path, ``{cell}`` and ``{start}`` allowed."""
    from daq.config import path_template

    if not text:
        return text  # --record with no path: the configured one
    try:
        return path_template(text, "path")
    except DaqError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("path: ")) from None


POSITIVE_S = number(0.0, above=True)
NONNEGATIVE_S = number(0.0)


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
    g.add_argument(
        "--listen", type=endpoint, action="append", metavar="ENDPOINT", help="listen endpoint"
    )
    g.add_argument(
        "--connect", type=endpoint, action="append", metavar="ENDPOINT", help="connect endpoint"
    )


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
    parser = OptionParser(
        prog="daq",
        description="Acquisition daemon: timestamped samples over zenoh, MCAP recording, replay.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help=COMMANDS["run"])
    p.add_argument(
        "--config", type=path_text, help="cell TOML (default: $DAQ_CONFIG, else the emulated cell)"
    )
    p.add_argument("--duration", type=POSITIVE_S, help="stop by itself after S seconds")
    p.add_argument(
        "--record",
        nargs="?",
        const="",
        type=record_path,
        metavar="PATH",
        help="record to MCAP (PATH optional; {cell} and {start} are filled in)",
    )
    p.add_argument("--no-record", action="store_true", help="do not record (emulated cell)")
    p.add_argument(
        "--sim-config", type=path_text, help="emulated cell TOML for sim-cell (no --config only)"
    )
    p.add_argument(
        "--rate",
        type=number(0.0, above=True, hi=100_000.0),
        default=1000.0,
        help="emulated tracker/encoder rate, Hz (1000)",
    )
    p.add_argument("--cell", help="cell name (key chunk)")
    _zenoh_args(p)

    p = sub.add_parser("record", help=COMMANDS["record"])
    p.add_argument(
        "key", nargs="?", type=key_expr, default="cell/**", help="key expression (cell/**)"
    )
    p.add_argument("-o", "--output", type=path_text, required=True, help="MCAP file to write")
    p.add_argument("--config", type=path_text, help="take zenoh settings from this cell TOML")
    p.add_argument("--duration", type=POSITIVE_S, help="stop after S seconds")
    _realtime_arg(p)
    _zenoh_args(p)

    p = sub.add_parser("replay", help=COMMANDS["replay"])
    p.add_argument("file", type=path_text, help="MCAP recording")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--speed", type=POSITIVE_S, default=1.0, help="×N of real time (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--loop", action="store_true", help="start over at the end")
    p.add_argument("--start", type=NONNEGATIVE_S, default=0.0, help="skip the first S seconds")
    p.add_argument(
        "--topic", type=key_expr, action="append", help="key expression filter (repeatable)"
    )
    p.add_argument("--duration", type=POSITIVE_S, help="stop after S seconds of wall time")
    p.add_argument(
        "--wait-subscribers",
        type=NONNEGATIVE_S,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for a matching subscriber before starting",
    )
    p.add_argument("--config", type=path_text, help="take zenoh settings from this cell TOML")
    _zenoh_args(p)

    p = sub.add_parser("recover", help=COMMANDS["recover"])
    p.add_argument("file", type=path_text)
    out = p.add_mutually_exclusive_group()
    out.add_argument(
        "-o", "--output", type=path_text, help="output (default: FILE.recovered.mcap beside FILE)"
    )
    out.add_argument(
        "--in-place",
        action="store_true",
        help="replace FILE, keeping the original as FILE.bak",
    )

    p = sub.add_parser("info", help=COMMANDS["info"])
    p.add_argument("file", type=path_text)

    p = sub.add_parser("echo", help=COMMANDS["echo"])
    p.add_argument("key", nargs="?", type=key_expr, default="cell/**")
    p.add_argument("--config", type=path_text, help="take zenoh settings from this cell TOML")
    p.add_argument("--duration", type=POSITIVE_S, help="stop after S seconds")
    p.add_argument("--count", type=integer(1), help="stop after N batches")
    p.add_argument(
        "--idle", type=POSITIVE_S, help="stop after S seconds without data (once started)"
    )
    p.add_argument(
        "--jsonl",
        type=path_text,
        metavar="FILE",
        help="write every batch as JSON lines ('-': stdout)",
    )
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
    p.add_argument("key", type=key_expr, help="a data key or a key expression (cell/**)")
    p.add_argument("--config", type=path_text, help="take zenoh settings from this cell TOML")
    p.add_argument("--timeout", type=POSITIVE_S, default=2.0, help="seconds to wait (2)")
    _zenoh_args(p)
    return parser


def _realtime_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--realtime-priority",
        type=integer(0, 99),
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

        if args.record and "{" not in args.record:
            # a recording is written as it runs, not staged: its place is checked first
            from daq.recording import check_stream_output

            inputs = [args.config, args.sim_config, os.environ.get("DAQ_CONFIG")]
            check_stream_output(args.record, "--record", inputs, create_dirs=True)
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
