"""Speed benchmarks, run with ``python -m benchmarks [--quick] [--json PATH] [--only NAME]``.

Every module ``benchmarks/bench_*.py`` is a benchmark module. It exposes

    def run(quick: bool) -> list[dict]

returning one row per measurement: a flat dict of str keys to numbers or strings. The
runner adds ``module`` to each row, prints one table per module with the union of the row
keys as columns, and writes everything as JSON on request. Suggested keys (not enforced):
``benchmark``, ``n`` (work items), ``ours_s`` (seconds for all n), ``<baseline>_s`` for each
reference measured in the same run (scaled to n when measured on a subset, with
``<baseline>_measured_n`` saying on how many), ``speedup_vs_<baseline>`` (baseline time /
ours) and a short ``note``. ``quick=True`` is a smoke mode on tiny sizes: it must finish
in seconds and is what ``tests/test_benchmarks_smoke.py`` runs; its numbers mean nothing.
"""

from __future__ import annotations

import importlib
import pkgutil
import time
from collections.abc import Callable, Iterable, Sequence
from types import ModuleType
from typing import Any

Row = dict[str, Any]

MODULE_PREFIX = "bench_"


def module_names() -> list[str]:
    """Fully qualified names of the benchmark modules in this package, sorted."""
    return sorted(
        f"{__name__}.{info.name}"
        for info in pkgutil.iter_modules(__path__)
        if info.name.startswith(MODULE_PREFIX)
    )


def load(name: str) -> ModuleType:
    module = importlib.import_module(name)
    if not callable(getattr(module, "run", None)):
        raise TypeError(f"{name} has no run(quick: bool) -> list[dict]")
    return module


def best_time(fn: Callable[[], object], repeat: int = 1) -> float:
    """Shortest wall time of ``repeat`` calls of ``fn`` (s): the least disturbed run."""
    best = float("inf")
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def format_table(rows: Sequence[Row]) -> str:
    """A plain-text table: the union of the rows' keys in first-seen order, ``note`` last."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    columns.sort(key=lambda c: c == "note")  # stable: only moves the free text to the end
    cells = [[_cell(row.get(c)) for c in columns] for row in rows]
    widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join(lines)


def _cell(value: object) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        if value == 0 or 1e-3 <= abs(value) < 1e6:
            return f"{value:.4g}"
        return f"{value:.3e}"
    return str(value)


def run_modules(names: Iterable[str], quick: bool) -> tuple[list[Row], list[str]]:
    """Run each module; returns all rows (with ``module``) and the error messages."""
    rows: list[Row] = []
    errors: list[str] = []
    for name in names:
        short = name.rsplit(".", 1)[-1]
        try:
            module_rows = load(name).run(quick=quick)
        except Exception as exc:  # one broken module must not hide the others' numbers
            errors.append(f"{short}: {type(exc).__name__}: {exc}")
            continue
        rows += [{"module": short, **row} for row in module_rows]
    return rows, errors
