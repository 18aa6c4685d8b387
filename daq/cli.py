"""``daq``: the acquisition daemon's command line.

Commands (docs/daq.md)::

    daq run [--config cell.toml] [--duration S] [--record [PATH]]   the daemon
    daq record KEYEXPR -o FILE.mcap [--duration S]                   zenoh -> MCAP
    daq replay FILE.mcap [--speed X | --fast] [--loop] [--start S] [--topic EXPR]
    daq recover FILE.mcap [-o OUT.mcap | --in-place]                 a damaged file's readable part
    daq info FILE.mcap                                               channels, counts, damage
    daq echo KEYEXPR [--stats [--stats-window S]] [--jsonl FILE] [--duration S]   look at a key
    daq echo --cell NAME ...                                         one cell's keys (cell/NAME/**)
    daq schema KEY                                                   the JSON schema of a key
    daq router --config router.json5                                 a zenoh router (zenohd's file)

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
import os
import re
import sys

from daq.cells import cell_name
from daq.config import ENDPOINT_RE, RATE_HZ, resolve, sink_zenoh
from daq.errors import DaqError
from edges.command import run_command, take_debug_flag
from edges.options import OptionParser, integer, number, path_text

COMMANDS: dict[str, str] = {
    "run": "the acquisition daemon (no --config: the emulated default cell, recorded)",
    "record": "record zenoh keys to an MCAP file",
    "replay": "republish an MCAP recording over zenoh",
    "recover": "write the readable part of a damaged MCAP recording as a whole file",
    "info": "channels, message counts and damage of an MCAP file (streaming)",
    "echo": "subscribe to a key expression and print or summarise batches",
    "schema": "print the JSON schema of a key (zenoh query <key>/@schema)",
    "router": "a zenoh router from zenoh's own JSON5 configuration (as zenohd -c FILE)",
}


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


def record_path(text: str) -> str:
    """An ``argparse`` ``type=``: a recording path, ``{cell}`` and ``{start}`` allowed."""
    from daq.config import template_refusal

    if not text:
        return text  # --record with no path: the configured one
    refusal = template_refusal(text)
    if refusal is not None:
        raise argparse.ArgumentTypeError(refusal)
    return text


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


def build_parser() -> argparse.ArgumentParser:
    parser = OptionParser(
        prog="daq",
        description="Acquisition daemon: timestamped samples over zenoh, MCAP recording, replay.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _run_options(sub.add_parser("run", help=COMMANDS["run"]))
    _record_options(sub.add_parser("record", help=COMMANDS["record"]))
    _replay_options(sub.add_parser("replay", help=COMMANDS["replay"]))
    _recover_options(sub.add_parser("recover", help=COMMANDS["recover"]))
    p = sub.add_parser("info", help=COMMANDS["info"])
    p.add_argument("file", type=path_text)
    _echo_options(sub.add_parser("echo", help=COMMANDS["echo"]))
    _schema_options(sub.add_parser("schema", help=COMMANDS["schema"]))
    p = sub.add_parser("router", help=COMMANDS["router"])
    p.add_argument(
        "--config", type=path_text, required=True, help="zenoh JSON5 configuration (zenohd's)"
    )
    return parser


def _run_options(p: argparse.ArgumentParser) -> None:
    """The options of ``daq run``."""
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
        type=number(RATE_HZ.lo, above=RATE_HZ.lo_open, hi=RATE_HZ.hi),
        default=None,
        help="emulated tracker/encoder rate, Hz (1000; no --config only: a configured "
        "cell states rate_hz per [[device]])",
    )
    p.add_argument("--cell", help="cell name (key chunk)")
    _zenoh_args(p)


def _record_options(p: argparse.ArgumentParser) -> None:
    """The options of ``daq record``."""
    p.add_argument(
        "key", nargs="?", type=key_expr, default="cell/**", help="key expression (cell/**)"
    )
    p.add_argument("-o", "--output", type=path_text, required=True, help="MCAP file to write")
    p.add_argument("--config", type=path_text, help="take zenoh settings from this cell TOML")
    p.add_argument("--duration", type=POSITIVE_S, help="stop after S seconds")
    _realtime_arg(p)
    _zenoh_args(p)


def _replay_options(p: argparse.ArgumentParser) -> None:
    """The options of ``daq replay``."""
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
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="replay the readable part of a damaged recording (said on stderr and in the "
        "result line); keys whose schema is lost are never republished",
    )
    p.add_argument("--config", type=path_text, help="take zenoh settings from this cell TOML")
    _zenoh_args(p)


def _recover_options(p: argparse.ArgumentParser) -> None:
    """The options of ``daq recover``."""
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


def _echo_options(p: argparse.ArgumentParser) -> None:
    """The options of ``daq echo``."""
    # default cell/** (every cell), with --cell that cell's keys (daq.cells.echo_key)
    p.add_argument("key", nargs="?", type=key_expr, default=None)
    p.add_argument(
        "--cell",
        type=cell_name,
        metavar="NAME",
        help="that cell's keys only (cell/NAME/**; a KEYEXPR must lie within its keys)",
    )
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


def _schema_options(p: argparse.ArgumentParser) -> None:
    """The options of ``daq schema``."""
    p.add_argument("key", type=key_expr, help="a data key or a key expression (cell/**)")
    p.add_argument("--config", type=path_text, help="take zenoh settings from this cell TOML")
    p.add_argument("--timeout", type=POSITIVE_S, default=2.0, help="seconds to wait (2)")
    _zenoh_args(p)


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
        from daq.daemon import check_run_options, main_run

        check_run_options(args)

        if args.record and "{" not in args.record:
            # a recording is written as it runs, not staged: its place is checked first
            from daq.recording_writer import check_stream_output

            inputs = [args.config, args.sim_config, os.environ.get("DAQ_CONFIG")]
            check_stream_output(args.record, "--record", inputs, create_dirs=True)
        return main_run(args)
    if getattr(args, "realtime_priority", 0):
        from daq.scheduling import set_realtime

        set_realtime(args.realtime_priority, "--realtime-priority")
    if args.command == "record":
        from daq.cli_recording import main_record

        return main_record(args, sink_zenoh(args))
    if args.command == "replay":
        from daq.replay import main_replay

        return main_replay(args, resolve(args).zenoh)
    if args.command == "recover":
        from daq.cli_recording import main_recover

        return main_recover(args)
    if args.command == "info":
        from daq.cli_recording import main_info

        return main_info(args)
    if args.command == "router":
        from daq.router import main_router

        return main_router(args)
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
