"""Every third-party package the code imports is declared in pyproject.toml, in the part
that needs it: the daemon's core (``daq``, ``drivers``, ``edges``) only in the core
dependencies, the twin in ``[twin]``, the view in ``[view]``, the emulator in
``[emulator]``, tests and benchmarks in ``[test]`` (docs/install.md). And ``make test``'s
browser step says in one line how to get Chromium where it cannot install it."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROJECT = {"calibration", "daq", "drivers", "edges", "sim_devices", "view", "benchmarks", "tests"}
#: What each part may use: the core, plus its extras.
PARTS = {
    "edges": (),
    "drivers": (),
    "daq": (),
    "calibration": ("twin",),
    "view": ("twin", "view"),
    "sim_devices": ("twin", "emulator"),
    "tests": ("twin", "view", "emulator", "test"),
    "benchmarks": ("twin", "view", "emulator", "test"),
}
#: Imported but not installed by the project, each with its reason.
OUTSIDE = {
    "_typeshed": "type checking only",
    "pybotics": "benchmarks: a side venv of its own (it pins numpy<2), made on request",
}


def _name(requirement: str) -> str:
    return re.split(r"[\s<>=!~;\[]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def declared() -> dict[str, set[str]]:
    """Distribution names per group: ``""`` the core, else the extra (self-references
    expanded)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    groups = {"": project["dependencies"], **project["optional-dependencies"]}
    out: dict[str, set[str]] = {}
    for group, reqs in groups.items():
        names = set()
        for req in reqs:
            if _name(req) == project["name"]:
                extras = re.search(r"\[(.*)\]", req)
                names |= (
                    {f"extra:{e.strip()}" for e in extras.group(1).split(",")} if extras else set()
                )
            else:
                names.add(_name(req))
        out[group] = names
    for names in out.values():  # one level of "grating-twin[twin]" is all there is
        for ref in [n for n in names if n.startswith("extra:")]:
            names |= out[ref.removeprefix("extra:")]
            names.discard(ref)
    return out


def imported_modules(part: str) -> set[str]:
    """Top-level names of every module imported anywhere in ``part`` (any depth of code)."""
    found: set[str] = set()
    for path in (ROOT / part).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.add(node.module.split(".")[0])
    return found - PROJECT - set(sys.stdlib_module_names) - {"__future__"}


def test_every_imported_package_is_declared_where_its_part_gets_it():
    groups = declared()
    dists = packages_distributions()
    missing = {}
    for part, extras in PARTS.items():
        allowed = groups[""].union(*(groups[e] for e in extras))
        for module in sorted(imported_modules(part)):
            if module in OUTSIDE:
                continue
            provided = {_name(d) for d in dists.get(module, [])}
            if not provided & allowed:
                missing[f"{part}: {module}"] = sorted(provided) or "not installed"
    assert missing == {}


def test_the_core_leaves_the_twin_view_and_emulator_out():
    core = declared()[""]
    for heavy in ("scipy", "matplotlib", "viser", "pymodbus"):
        assert heavy not in core, heavy
    assert {"zstandard", "lz4"} <= core  # daq/recording_reader.py decompresses chunks itself


def test_make_test_says_in_one_line_how_to_get_chromium_where_it_cannot_install_it(tmp_path):
    # an empty PATH: no chromium, no apt-get
    proc = subprocess.run(
        ["/bin/sh", str(ROOT / "scripts" / "need-chromium")],
        env={"PATH": str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "apt-get install chromium" in lines[0], proc.stderr
