"""``twin``: the twin's command line. Each subcommand lives in its own module.

A subcommand module exposes ``register(subparsers) -> None`` that adds its parser and sets
``func`` (``args -> int`` exit code) as the parser default. Only the chosen command's module
is imported, so a broken or slow piece fails or slows only its own command.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from calibration.errors import CalibrationError
from edges.command import run_command, take_debug_flag
from edges.options import OptionParser

# subcommand name -> (module providing register(), one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "robot": ("calibration.cli.robot", "list presets or check a robot description file"),
    "scale": ("calibration.cli.scale", "grating-scale calibration from home.csv and sweep.csv"),
    "scale-apply": ("calibration.cli.scale", "turn grating counts into joint angles"),
    "identify": ("calibration.cli.identify", "identify kinematic parameters from a campaign"),
    "predict": ("calibration.cli.identify", "predict tracker points from joint angles"),
    "export": ("calibration.cli.export", "phases found in a recording as home/sweep/campaign.csv"),
    "run": ("calibration.cli.run", "the twin end to end: recording or live, reports, live twin"),
    "compensate": (
        "calibration.cli.compensate",
        "joint commands that put the calibrated robot's TCP on targets",
    ),
    "track": (
        "calibration.cli.track",
        "follow the robot's drift and steps through production tracker checks",
    ),
    "plan": (
        "calibration.cli.plan",
        "plan a campaign the tracker sees: joint list, KRL and RAPID programs, report",
    ),
    "stiffness": (
        "calibration.cli.stiffness",
        "Cartesian compliance at poses, or joint stiffness from a load test",
    ),
    # the view lives in its own package (view/), loaded only when this command runs
    "view": ("view.cli", "the twin in the browser: replay a recording or follow it live"),
}


def build_parser(command: str | None) -> argparse.ArgumentParser:
    parser = OptionParser(
        prog="twin",
        description="The robot's digital twin: calibration and identification.",
        epilog="commands:\n"
        + "\n".join(f"  {name:<12} {text}" for name, (_, text) in SUBCOMMANDS.items())
        + "\n\nexit status: 0 done, 1 done but failed a check, 2 bad input (one line says "
        "what), 70 a bug (--debug shows the traceback)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    if command in SUBCOMMANDS:
        importlib.import_module(SUBCOMMANDS[command][0]).register(sub)
    for name, (_, text) in SUBCOMMANDS.items():
        if name not in sub.choices:  # listed for usage messages, not imported
            sub.add_parser(name, help=text)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(command).parse_args(argv)
    return run_command(
        f"twin {args.command}",
        lambda: args.func(args),
        user_errors=(CalibrationError,),
        debug=debug,
    )


if __name__ == "__main__":
    sys.exit(main())
