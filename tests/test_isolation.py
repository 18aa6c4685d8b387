"""The twin never sees the emulator's truth: ``calibration`` does not import ``sim_devices``.

Two checks: a static one over the source of every module file in the package (any
``import``/``from ... import`` form; import strings passed to importlib are out of scope),
and a dynamic one that imports every module in a fresh interpreter.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

FORBIDDEN = "sim_devices"
# From the repository layout, not ``calibration.__file__``: a stale editable install can
# expose the package as a namespace package (``__file__`` None) when pytest runs.
REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIR = REPO_ROOT / "calibration"
MODULE_FILES = sorted(PACKAGE_DIR.rglob("*.py"))


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO_ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_forbidden(name: str | None) -> bool:
    return name is not None and (name == FORBIDDEN or name.startswith(FORBIDDEN + "."))


def forbidden_imports(source: str, filename: str) -> list[str]:
    """``file:line`` of every statement importing ``sim_devices`` in ``source``."""
    hits = []
    for node in ast.walk(ast.parse(source, filename=filename)):
        if isinstance(node, ast.Import):
            bad = any(_is_forbidden(alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            # `from sim_devices[.x] import y`, or `from <anything> import sim_devices`
            bad = (node.level == 0 and _is_forbidden(node.module)) or any(
                alias.name == FORBIDDEN for alias in node.names
            )
        else:
            continue
        if bad:
            hits.append(f"{filename}:{node.lineno}")
    return hits


def test_the_package_has_modules_to_check():
    names = {module_name(p) for p in MODULE_FILES}
    assert {"calibration", "calibration.model.kinematics", "calibration.model.description"} <= names


@pytest.mark.parametrize("path", MODULE_FILES, ids=module_name)
def test_module_source_never_imports_sim_devices(path):
    assert forbidden_imports(path.read_text(encoding="utf-8"), str(path)) == []


@pytest.mark.parametrize(
    "source",
    [
        "import sim_devices",
        "import sim_devices.truth as t",
        "import os, sim_devices",
        "from sim_devices import truth",
        "from sim_devices.truth import Robot",
        "from . import sim_devices",
        "def f():\n    import sim_devices\n",
        "try:\n    from sim_devices import x\nexcept ImportError:\n    pass\n",
    ],
)
def test_the_checker_catches_every_import_form(source):
    line = source[: source.index(FORBIDDEN)].count("\n") + 1
    assert forbidden_imports(source, "probe.py") == [f"probe.py:{line}"]


@pytest.mark.parametrize(
    "source", ["import sim_devices_extra", "from simulation import devices", "x = 'sim_devices'"]
)
def test_the_checker_ignores_lookalikes(source):
    assert forbidden_imports(source, "probe.py") == []


def test_importing_every_module_leaves_sim_devices_unloaded():
    names = [module_name(p) for p in MODULE_FILES]
    script = (
        "import importlib, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        f"loaded = sorted(m for m in sys.modules if m == {FORBIDDEN!r} "
        f"or m.startswith({FORBIDDEN + '.'!r}))\n"
        "print(len(sys.modules), loaded)\n"
        "sys.exit(1 if loaded else 0)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO_ROOT,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
