"""``python -m benchmarks``: run every ``benchmarks/bench_*.py`` module and print the table."""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import numpy as np

from benchmarks import format_table, module_names, run_modules


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run")
    parser.add_argument("--json", type=Path, metavar="PATH", help="also write rows as JSON")
    parser.add_argument(
        "--only", action="append", metavar="NAME", help="run modules whose name contains NAME"
    )
    args = parser.parse_args(argv)

    names = module_names()
    if args.only:
        names = [n for n in names if any(part in n for part in args.only)]
    if not names:
        print("no benchmark modules selected", file=sys.stderr)
        return 2
    rows, errors = run_modules(names, quick=args.quick)
    for module in dict.fromkeys(r["module"] for r in rows):
        print(f"\n== {module}{' (quick)' if args.quick else ''}")
        print(
            format_table(
                [
                    {k: v for k, v in r.items() if k != "module"}
                    for r in rows
                    if r["module"] == module
                ]
            )
        )
    for error in errors:
        print(f"\nFAILED {error}", file=sys.stderr)
    if args.json:
        doc = {
            "quick": args.quick,
            "python": platform.python_version(),
            "numpy": np.__version__,
            "machine": platform.machine(),
            "processor": platform.processor(),
            "rows": rows,
            "errors": errors,
        }
        args.json.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        print(f"\nwrote {args.json}")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
