"""``twin``: the twin's command line. Each subcommand lives in its own module.

A subcommand module exposes ``register(subparsers) -> None`` that adds its parser and sets
``func`` (``args -> int`` exit code) as the parser default. Modules are imported lazily so a
broken optional piece fails only its own command.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from calibration.errors import CalibrationError

# subcommand name -> module providing register()
SUBCOMMANDS: dict[str, str] = {
    "robot": "calibration.cli_robot",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="twin", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_name in dict.fromkeys(SUBCOMMANDS.values()):
        importlib.import_module(module_name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except CalibrationError as exc:
        print(f"twin {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
