"""One declarative way to read TOML files into typed values, errors naming file, table, key.

A table is a frozen dataclass: its fields are the keys, their type hints the value types
(``bool``, ``int``, ``float``, ``str``, ``tuple[float, ...]``, ``tuple[float, float,
float]``, ``tuple[str, ...]``, ``X | None``, ``Literal[...]``, ``Mapping[str, Any]`` for a
table taken as it is, a nested dataclass for a sub-table), a default makes a key optional
(unless the field's metadata is :data:`REQUIRED`), and the metadata :func:`key_spec` adds
a :class:`Range` (or a ``ranges`` map by dotted key) that bounds a number and says its
unit, the allowed values of a key, or a check of its own. :func:`build` turns a parsed
table into the dataclass; :class:`TomlTable` reads the few tables whose keys are data (an
effect's parameters, a scale map's terms) with the same checks and messages.
:func:`parse_toml_file` reads a file bounded, as UTF-8 (with or without a byte-order
mark), refusing NUL bytes.

Every mistake is one line: ``FILE: [table]: key 'k': must be in 1..20000 (Hz), got 0``.
A value set elsewhere than in the file (an environment variable, a command-line option)
is named by its origin instead of the file (``origins``, by dotted key). TOML allows
``nan`` and ``inf``: a number must be finite unless its range admits ``inf``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from edges.command import one_line
from edges.inputs import MAX_TOML_BYTES, read_input_bytes

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

T = TypeVar("T", bound="DataclassInstance")


@dataclass(frozen=True)
class Range:
    """Allowed values of a number (each element of a list): ``lo..hi`` (None: unbounded),
    ``lo`` itself excluded when ``lo_open``; ``inf``: +inf allowed (NaN never is);
    ``empty``: a list may be empty; ``what``: what the number is, for the message."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    inf: bool = False
    empty: bool = True
    what: str = ""

    def describe(self) -> str:
        """The allowed values in words (``in 0..1 (what)``; ``finite`` when unbounded)."""
        if self.lo is not None and self.hi is not None and not self.lo_open:
            text = f"in {_num(self.lo)}..{_num(self.hi)}"
        elif self.lo is not None and self.hi is not None:
            text = f"> {_num(self.lo)} and <= {_num(self.hi)}"
        elif self.lo is not None:
            text = f"{'>' if self.lo_open else '>='} {_num(self.lo)}"
        elif self.hi is not None:
            text = f"<= {_num(self.hi)}"
        else:
            text = "finite"
        return text + (f" ({self.what})" if self.what else "")

    def refusal(self, v: float) -> str:
        """Why ``v`` is refused, for a message (``must be ...``)."""
        text = self.describe()
        if isinstance(v, float) and not math.isfinite(v) and not self.inf:
            text = text.removeprefix("finite").lstrip()
            sep = " " if text.startswith("(") else ", "
            return "must be a finite number" + (f"{sep}{text}" if text else "")
        return f"must be {text}"

    def admits(self, v: float) -> bool:
        if isinstance(v, float) and (math.isnan(v) or (math.isinf(v) and not (self.inf and v > 0))):
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return self.hi is None or v <= self.hi or (self.inf and math.isinf(v))


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{v:g}"


FINITE = Range()
POSITIVE = Range(0.0, lo_open=True)
NON_NEGATIVE = Range(0.0)

#: Field metadata: the key must be in the file although the dataclass has a default.
REQUIRED: Mapping[str, Any] = types.MappingProxyType({"required": True})

#: A check of a value beyond its type and range: why it is refused, or None.
Check = Callable[[Any], str | None]


def key_spec(
    *,
    range: Range | None = None,
    choices: Sequence[Any] | None = None,
    check: Check | None = None,
) -> dict[str, Any]:
    """Field metadata for :func:`build` (``field(default=..., metadata=key_spec(...))``):
    a number's ``range``, the allowed values (``choices``, as a ``Literal`` hint says),
    a ``check`` of the value read."""
    return {"range": range, "choices": choices, "check": check}


def where(path: tuple[str, ...]) -> str:
    """A table's name in messages: ``[a.b]``, or ``top level``."""
    return f"[{'.'.join(path)}]" if path else "top level"


def origins_at(origins: Mapping[str, str] | None, path: tuple[str, ...]) -> dict[str, str]:
    """The origins of the keys of the table at ``path``, by key (``origins``: by dotted
    key, as :func:`build` takes them)."""
    table = ".".join(path)
    out = {}
    for dotted, origin in (origins or {}).items():
        parent, _, key = dotted.rpartition(".")
        if parent == table:
            out[key] = origin
    return out


def short(value: Any) -> str:
    """A value for a message: its type and a repr cut at 60 characters."""
    text = repr(value)
    text = text if len(text) <= 60 else text[:57] + "..."
    return f"{type(value).__name__} {text}" if not isinstance(value, dict | list) else text


# -- reading a file ------------------------------------------------------------------------
def parse_toml_text(text: str, source: str, error: type[Exception]) -> dict[str, Any]:
    """Parse TOML ``text``; a syntax error is ``error`` naming ``source``."""
    try:
        return tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{source}: not valid TOML: {one_line(str(exc))}") from None
    except RecursionError:
        raise error(f"{source}: not valid TOML: nested too deeply") from None


def parse_toml_file(path: str | Path, error: type[Exception], what: str) -> dict[str, Any]:
    """Read and parse a TOML file, bounded (:data:`~edges.inputs.MAX_TOML_BYTES`); NUL
    bytes or text that is not UTF-8 are ``error`` naming the file, the line and ``what``
    the file should have been."""
    source = str(path)
    raw = read_input_bytes(path, limit=MAX_TOML_BYTES, error=error)
    if b"\x00" in raw:  # a binary file, or UTF-16 text
        line = raw[: raw.index(b"\x00")].count(b"\n") + 1
        raise error(f"{source}: line {line}: contains NUL bytes: not UTF-8 TOML text, not {what}")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise error(
            f"{source}: line {line}: not UTF-8 text (byte {exc.start}): not {what}"
        ) from None
    return parse_toml_text(text, source, error)


# -- one table -------------------------------------------------------------------------------
class TomlTable:
    """Typed access to one parsed TOML table; every error is ``error`` naming the file
    (``source``; a key's own origin when ``origins`` has it), the table (``name``) and
    the key."""

    def __init__(
        self,
        data: Any,
        source: str,
        name: str,
        error: type[Exception],
        origins: Mapping[str, str] | None = None,
    ) -> None:
        self.source, self.name, self.error = source, name, error
        self.origins: Mapping[str, str] = origins or {}
        if not isinstance(data, dict):
            raise self.fail(None, f"expected a table, got {short(data)}")
        self.data: dict[str, Any] = data

    def fail(self, key: str | None, message: str) -> Exception:
        """The error to raise: ``ORIGIN: TABLE: key 'KEY': MESSAGE``."""
        if key is None:
            return self.error(f"{self.source}: {self.name}: {message}")
        origin = self.origins.get(key, self.source)
        return self.error(f"{origin}: {self.name}: key '{key}': {message}")

    def check_keys(self, allowed: set[str] | list[str]) -> None:
        unknown = sorted(set(self.data) - set(allowed))
        if unknown:
            raise self.fail(
                unknown[0], f"unknown key (allowed: {', '.join(sorted(allowed)) or 'none'})"
            )

    def get(self, key: str) -> Any:
        if key not in self.data:
            raise self.fail(key, "missing")
        return self.data[key]

    def number(
        self, key: str, value: Any = None, *, rng: Range = FINITE, default: float | None = None
    ) -> float:
        """A number (an integer is taken as a float) within ``rng``; ``default`` when the
        key is absent and a default is given."""
        if value is None and default is not None and key not in self.data:
            return default
        v = self.get(key) if value is None else value
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.fail(key, f"expected a number, got {short(v)}")
        given = v
        try:
            v = float(v)  # an integer of 400 digits is no float
        except OverflowError:
            v = math.inf if v > 0 else -math.inf
        if not rng.admits(v):
            raise self.fail(key, f"{rng.refusal(v)}, got {given!r}")
        return v

    def integer(self, key: str, value: Any = None, *, rng: Range = FINITE) -> int:
        v = self.get(key) if value is None else value
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(key, f"expected an integer, got {short(v)}")
        if not rng.admits(v):
            raise self.fail(key, f"{rng.refusal(v)}, got {v!r}")
        return v

    def string(self, key: str, value: Any = None, *, empty: bool = False) -> str:
        v = self.get(key) if value is None else value
        if not isinstance(v, str) or (not empty and not v.strip()):
            raise self.fail(key, f"expected a {'' if empty else 'non-empty '}string, got {v!r}")
        return v

    def boolean(self, key: str, value: Any = None) -> bool:
        v = self.get(key) if value is None else value
        if not isinstance(v, bool):
            raise self.fail(key, f"expected true or false, got {short(v)}")
        return v

    def choice(self, key: str, value: Any, choices: Sequence[Any]) -> Any:
        """One of ``choices`` (``true`` is not ``1``)."""
        if not any(type(value) is type(c) and value == c for c in choices):
            allowed = ", ".join(_toml_text(c) for c in choices)
            raise self.fail(key, f"must be one of {allowed}, got {value!r}")
        return value

    def strings(self, key: str, value: Any = None) -> tuple[str, ...]:
        """An array of non-empty strings."""
        v = self.get(key) if value is None else value
        if not isinstance(v, list):
            raise self.fail(key, f"expected an array of strings, got {short(v)}")
        for x in v:
            if not isinstance(x, str) or not x.strip():
                raise self.fail(key, f"expected an array of non-empty strings, got {short(x)}")
        return tuple(v)

    def numbers(
        self,
        key: str,
        value: Any = None,
        *,
        length: int | None = None,
        rng: Range = FINITE,
        integer: bool = False,
    ) -> tuple[Any, ...]:
        """An array of numbers (of ``length`` when given; integers when ``integer``)."""
        v = self.get(key) if value is None else value
        kind = "integers" if integer else "numbers"
        if not isinstance(v, list):
            raise self.fail(key, f"expected an array of {kind}, got {short(v)}")
        if length is not None and len(v) != length:
            raise self.fail(key, f"expected {length} {kind}, got {len(v)}")
        if not v and not rng.empty:
            raise self.fail(key, "must not be empty")
        for x in v:  # the element's type, named as the array's
            wrong = not isinstance(x, int) if integer else not isinstance(x, int | float)
            if isinstance(x, bool) or wrong:
                raise self.fail(key, f"expected an array of {kind}, got {short(x)}")
        read = self.integer if integer else self.number
        return tuple(read(key, x, rng=rng) for x in v)

    def table(self, key: str, value: Any = None) -> TomlTable:
        """The sub-table ``key`` (``value``: its parsed content, when already taken)."""
        sub = f"[{key}]" if self.name == "top level" else f"{self.name}.{key}"
        return TomlTable(self.get(key) if value is None else value, self.source, sub, self.error)

    def mapping(self, key: str, value: Any = None) -> dict[str, Any]:
        """A sub-table taken as it is (its keys and values are someone else's to check)."""
        v = self.get(key) if value is None else value
        if not isinstance(v, dict):
            raise self.fail(key, f"expected a table, got {short(v)}")
        return dict(v)

    def number_table(self, key: str) -> dict[str, float]:
        """A sub-table whose keys are names and whose values are finite numbers."""
        sub = self.table(key)
        return {k: sub.number(k) for k in sub.data}

    def matrix(self, key: str, size: int) -> NDArray[np.float64]:
        """A ``size × size`` array of finite numbers."""
        value = self.get(key)
        ok = isinstance(value, list) and len(value) == size
        ok = ok and all(isinstance(r, list) and len(r) == size for r in value)
        if not ok:
            raise self.fail(key, f"expected a {size}×{size} array of numbers")
        rows = [self.numbers(key, r, length=size) for r in value]
        return np.array(rows, dtype=float).reshape(size, size)


# -- a dataclass from a table --------------------------------------------------------------
def build(
    cls: type[T],
    data: Any,
    *,
    source: str,
    error: type[Exception],
    path: tuple[str, ...] = (),
    name: str | None = None,
    ranges: Mapping[str, Range] | None = None,
    origins: Mapping[str, str] | None = None,
) -> T:
    """The dataclass ``cls`` from the parsed table ``data`` at ``path`` (dotted keys into
    ``ranges`` and ``origins``; ``name`` overrides the table's name in messages, e.g.
    ``[[joint]] #2``). ``origins``: where a value came from when not from ``source``
    (``{"zenoh.mode": "environment DAQ_ZENOH_MODE"}``), named in its messages instead.

    Unknown keys, missing required ones, wrong types, numbers outside their range, values
    not among the key's choices and values its check refuses are ``error``; nested
    dataclass fields are sub-tables, built the same way."""
    table = TomlTable(data, source, name or where(path), error, origins_at(origins, path))
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(table.data) - set(fields))
    if unknown:
        what = "table" if not path and name is None else "key"
        raise table.fail(
            None, f"unknown {what} {unknown[0]!r} (allowed: {', '.join(sorted(fields))})"
        )
    kwargs: dict[str, Any] = {}
    for key, f in fields.items():
        has_default = (
            f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
        )
        if key not in table.data:
            if not has_default or f.metadata.get("required"):
                raise table.fail(key, "missing")
            continue
        rng = f.metadata.get("range") or (ranges or {}).get(".".join((*path, key)), FINITE)
        choices = f.metadata.get("choices")
        if choices is not None:
            kwargs[key] = table.choice(key, table.data[key], choices)
        else:
            kwargs[key] = _value(table, key, hints[key], rng, path, ranges, origins)
        check: Check | None = f.metadata.get("check")
        refusal = check(kwargs[key]) if check is not None else None
        if refusal is not None:
            raise table.fail(key, refusal)
    return cls(**kwargs)


def _toml_text(value: Any) -> str:
    """A value as a message shows it: ``true``, ``'auto'``."""
    return str(value).lower() if isinstance(value, bool) else repr(value)


def _value(
    table: TomlTable,
    key: str,
    hint: Any,
    rng: Range,
    path: tuple[str, ...],
    ranges: Mapping[str, Range] | None,
    origins: Mapping[str, str] | None,
) -> Any:
    value = table.data[key]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (types.UnionType, typing.Union) and type(None) in args:
        inner = [a for a in args if a is not type(None)]
        return _value(table, key, inner[0], rng, path, ranges, origins)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return build(
            hint,
            value,
            source=table.source,
            error=table.error,
            path=(*path, key),
            ranges=ranges,
            origins=origins,
        )
    if origin is Literal:
        return table.choice(key, value, args)
    if origin is Mapping:
        return table.mapping(key, value)
    if origin is tuple and args[0] is str:
        return table.strings(key, value)
    if origin is tuple:
        integer = args[0] is int
        length = None if len(args) == 2 and args[1] is Ellipsis else len(args)
        return table.numbers(key, value, length=length, rng=rng, integer=integer)
    if hint is bool:
        return table.boolean(key, value)
    if hint is int:
        return table.integer(key, value, rng=rng)
    if hint is float:
        return table.number(key, value, rng=rng)
    if hint is str:
        return table.string(key, value, empty=True)
    raise TypeError(f"{key}: no TOML reading for {hint!r}")  # a programming error
