"""The import graph of the project's packages: no cycles (function-level imports
included: a lazy import is still a dependency), the layers between packages and between
calibration's subpackages, and no module imports a command module of the twin
(``calibration.cli.*``) except the command line itself."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calibration", "daq", "drivers", "sim_devices", "edges", "view")

#: What each package may import of the others (docs/architecture.md): the one place the
#: layering is written down, and a test holds the code to it.
MAY_IMPORT: dict[str, set[str]] = {
    "edges": set(),
    "drivers": {"edges"},
    "daq": {"drivers", "edges"},
    "calibration": {"edges", "daq"},
    "sim_devices": {"calibration", "drivers", "edges"},
    "view": {"calibration", "daq", "edges"},
}
#: What each of calibration's subpackages may import of the others (docs/architecture.md).
#: ``errors`` is the package's exception tree, open to all; ``calibration`` itself (its
#: ``__init__``, the public API) re-exports from the layers and is imported by none.
CALIBRATION_MAY_IMPORT: dict[str, set[str]] = {
    "errors": set(),
    "presets": set(),  # the preset description files (data: its __init__ imports nothing)
    "model": {"errors"},
    "scales": {"errors", "model"},
    "identify": {"errors", "model"},
    "effects": {"errors", "model", "identify"},
    "twin": {"errors", "model", "scales", "identify", "effects"},
    "plan": {"errors", "model", "identify", "effects"},
    "cli": {"errors", "model", "scales", "identify", "effects", "twin", "plan"},
}

#: Modules above their package's layer, each with the reason it may reach higher.
APPLICATIONS: dict[str, str] = {
    "daq.demo": "the main job: runs the emulated cell, the daemon and the twin together",
}


def modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def imports_of(path: Path, known: set[str]) -> set[str]:
    """Every project module ``path`` imports, at any depth of its code."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found |= {f"{node.module}.{a.name}" for a in node.names}
    return found & known


def graph() -> dict[str, set[str]]:
    mods = modules()
    names = set(mods)
    return {name: imports_of(path, names) - {name} for name, path in mods.items()}


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per back edge found by a depth-first walk (empty: acyclic)."""
    found: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(v: str) -> None:
        state[v] = 1
        stack.append(v)
        for w in sorted(g[v]):
            if state.get(w) == 1:
                found.append([*stack[stack.index(w) :], w])
            elif w not in state:
                visit(w)
        stack.pop()
        state[v] = 2

    for v in sorted(g):
        if v not in state:
            visit(v)
    return found


def test_the_walk_finds_a_cycle_when_there_is_one():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c", "a"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_covers_every_package():
    g = graph()
    assert {"daq.cli", "calibration.cli", "drivers.base", "edges.outputs"} <= set(g)
    assert "daq.config" in g["daq.daemon"]  # edges are found


def test_no_import_cycle():
    assert cycles(graph()) == []


def test_packages_import_only_what_their_layer_allows():
    offenders = sorted(
        f"{name} -> {dep}"
        for name, deps in graph().items()
        for dep in deps
        if name not in APPLICATIONS
        and dep.split(".")[0] != name.split(".")[0]
        and dep.split(".")[0] not in MAY_IMPORT[name.split(".")[0]]
    )
    assert offenders == []


def test_calibration_reads_daq_formats_only():
    """The twin reads the daemon's formats (columnar batches, MCAP recordings, the bus and
    its config, their errors); it never runs the daemon or its drivers."""
    formats = {"daq.bus", "daq.columnar", "daq.config", "daq.recording_reader", "daq.errors"}
    reached = {d for n, deps in graph().items() if n.startswith("calibration.") for d in deps}
    assert {d for d in reached if d.startswith("daq.")} <= formats


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "(the public API)"


def test_calibration_subpackages_import_only_their_lower_layers():
    g = graph()
    layers = {_layer(n) for n in g if n.startswith("calibration.")}
    assert layers <= set(CALIBRATION_MAY_IMPORT), layers - set(CALIBRATION_MAY_IMPORT)
    offenders = sorted(
        f"{name} -> {dep}"
        for name, deps in g.items()
        if name.startswith("calibration.")
        for dep in deps
        if dep.startswith("calibration")
        and _layer(dep) != _layer(name)
        and _layer(dep) not in CALIBRATION_MAY_IMPORT[_layer(name)]
    )
    assert offenders == []


def test_the_subpackage_check_sees_a_wrong_arrow():
    assert "identify" not in CALIBRATION_MAY_IMPORT["model"]
    assert _layer("calibration.model.kinematics") == "model"


def test_only_the_command_line_imports_command_modules():
    offenders = {
        (name, dep)
        for name, deps in graph().items()
        for dep in deps
        if dep.startswith("calibration.cli.") and not name.startswith("calibration.cli")
    }
    assert offenders == set()


def test_only_the_command_line_writes_the_twins_run_files():
    """``calibration.cli.run_files`` writes what ``twin export`` and ``twin run`` computed in
    memory: only command modules import it (files at the edges)."""
    importers = {name for name, deps in graph().items() if "calibration.cli.run_files" in deps}
    assert importers == {"calibration.cli.export", "calibration.cli.run"}
