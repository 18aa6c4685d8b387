"""No ``Any`` at a module boundary: the parameters and returns of every public function and
method of the project's packages say what they take and give (a Protocol, a dataclass, a
type alias), read from the annotations as written (``ast``: nothing is imported).

Allowed by their form, because there ``Any`` is the truth:

* a JSON document, ``dict[str, Any]`` / ``Mapping[str, Any]`` / ``list[dict[str, Any]]``:
  a JSON object's values are any JSON value (reports, health, schema metadata);
* ``NDArray[Any]``: an array of any dtype (a batch's columns carry the dtypes their schema
  names);
* ``*args: Any`` / ``**kwargs: Any``: options passed through to what checks them (a
  driver's ``Option`` table, ``subprocess.Popen``, a dataclass's ``replace``);
* a package's ``__getattr__`` (PEP 562): its lazily loaded public names, each typed where
  it is defined.

Every other ``Any`` is named in :data:`EXCEPTIONS` with its reason.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calibration", "daq", "drivers", "sim_devices", "edges", "view")

#: The forms in which ``Any`` is the truth (the module docstring says why).
JSON_AND_ARRAYS = (
    "list[dict[str, Any]]",
    "dict[str, Any]",
    "Mapping[str, Any]",
    "NDArray[Any]",
)

_OTHER_BRANCH = "its module is being edited on another branch: typed after that merge"
_TOML_VALUE = (
    "a TOML value before it is checked, any of TOML's types (``object`` would say it); "
    + _OTHER_BRANCH
)

#: ``module:function(parameter)`` or ``module:function(return)`` -> why it is ``Any``.
EXCEPTIONS: dict[str, str] = {
    # the live twin: a module being split elsewhere
    "calibration.twin.live_twin:LiveSettings.zenoh_config(return)": _OTHER_BRANCH,
    "calibration.twin.live_twin:TwinPublication.__init__(session)": _OTHER_BRANCH,
    # the daemon's command handlers take argparse's namespace (argparse.Namespace)
    "daq.config:zenoh_overrides(args)": _OTHER_BRANCH,
    "daq.config:resolve(args)": _OTHER_BRANCH,
    "daq.config:sink_zenoh(args)": _OTHER_BRANCH,
    "daq.echo:KeyStats.add(header)": _OTHER_BRANCH,
    "daq.echo:main_echo(args)": _OTHER_BRANCH,
    "daq.cli_recording:main_recover(args)": _OTHER_BRANCH,
    "daq.cli_recording:main_info(args)": _OTHER_BRANCH,
    "daq.cli_recording:main_record(args)": _OTHER_BRANCH,
    "daq.cli_recording:main_record(zc)": _OTHER_BRANCH,
    "daq.replay:main_replay(args)": _OTHER_BRANCH,
    # argparse's error() never returns (typing.NoReturn)
    "edges.options:OptionParser.error(return)": _OTHER_BRANCH,
    # the one TOML reader's checks take what the file held
    "edges.toml_schema:key_spec(choices)": _TOML_VALUE,
    "edges.toml_schema:short(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.__init__(data)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.get(return)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.number(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.integer(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.string(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.boolean(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.choice(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.choice(choices)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.choice(return)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.strings(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.numbers(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.numbers(return)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.table(value)": _TOML_VALUE,
    "edges.toml_schema:TomlTable.mapping(value)": _TOML_VALUE,
    "edges.toml_schema:build(data)": _TOML_VALUE,
}


def _says_any(annotation: ast.expr) -> bool:
    """Whether ``annotation`` holds ``Any`` outside the forms allowed by their form."""
    text = ast.unparse(annotation)
    for allowed in JSON_AND_ARRAYS:
        text = text.replace(allowed, "")
    return re.search(r"\bAny\b", text) is not None


def any_in_signatures(source: str, module: str) -> list[str]:
    """``module:qualname(parameter|return)`` of every public signature of ``source`` that
    says ``Any`` (``*args``, ``**kwargs`` and ``__getattr__`` allowed by their form)."""
    found: list[str] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef) and not child.name.startswith("_"):
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = child.name
                if name == "__getattr__" or (name.startswith("_") and not name.endswith("__")):
                    continue
                a = child.args
                named = [*a.posonlyargs, *a.args, *a.kwonlyargs]
                where = f"{module}:{prefix}{name}"
                found.extend(
                    f"{where}({p.arg})"
                    for p in named
                    if p.annotation is not None and _says_any(p.annotation)
                )
                if child.returns is not None and _says_any(child.returns):
                    found.append(f"{where}(return)")

    visit(ast.parse(source), "")
    return found


def public_any() -> set[str]:
    found: set[str] = set()
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if any(p.startswith("_") and p != "__init__" for p in parts):
                continue
            module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found |= set(any_in_signatures(path.read_text(encoding="utf-8"), module))
    return found


def test_no_any_in_a_public_signature():
    """Every ``Any`` left is an exception named with its reason."""
    assert sorted(public_any() - set(EXCEPTIONS)) == []


def test_every_exception_is_still_there():
    """A signature typed since leaves the list (it only shrinks)."""
    assert sorted(set(EXCEPTIONS) - public_any()) == []


def test_the_walk_sees_any_and_lets_the_allowed_forms_pass():
    source = """
from typing import Any
def f(x: Any, y: int) -> int: ...
def g(x: int) -> list[Any]: ...
def h(doc: dict[str, Any], a: NDArray[Any], *args: Any, **kw: Any) -> Mapping[str, Any]: ...
def _private(x: Any) -> Any: ...
class C:
    def m(self, x: tuple[Any, ...] | None) -> None: ...
    def _p(self, x: Any) -> None: ...
class _Hidden:
    def m(self, x: Any) -> None: ...
def __getattr__(name: str) -> Any: ...
"""
    assert any_in_signatures(source, "m") == ["m:f(x)", "m:g(return)", "m:C.m(x)"]
