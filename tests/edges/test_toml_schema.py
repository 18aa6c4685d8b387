"""The one TOML reader (edges.toml_schema): a dataclass per table, checked by its types,
defaults and ranges; every mistake one line naming the file, the table and the key."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edges.toml_schema import (
    REQUIRED,
    Range,
    TomlTable,
    build,
    key_spec,
    parse_toml_file,
    parse_toml_text,
)


class Bad(ValueError):
    pass


@dataclass(frozen=True)
class Sub:
    rate_hz: float = field(default=100.0, metadata=key_spec(range=Range(1.0, 1e4, what="Hz")))
    mode: Literal["a", "d"] = "a"


@dataclass(frozen=True)
class Top:
    name: str
    count: int = 1
    gain: float = field(default=0.0, metadata=REQUIRED)
    on: bool = False
    ids: tuple[int, ...] = (1, 2)
    xyz: tuple[float, float, float] | None = None
    sub: Sub = field(default_factory=Sub)


def read(text: str) -> Top:
    doc = parse_toml_text(text, "f.toml", Bad)
    return build(Top, doc, source="f.toml", error=Bad, ranges={"count": Range(0, 10)})


def test_a_table_becomes_its_dataclass():
    top = read('name = "x"\ngain = 2\nids = [3]\nxyz = [1, 2, 3.5]\n[sub]\nmode = "d"\n')
    assert top == Top("x", 1, 2.0, False, (3,), (1.0, 2.0, 3.5), Sub(100.0, "d"))
    assert isinstance(top.gain, float)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("gain = 1", ["top level", "key 'name'", "missing"]),
        ('name = "x"', ["key 'gain'", "missing"]),
        ('name = "x"\ngain = 1\ncolour = 3', ["top level", "unknown table 'colour'", "allowed"]),
        ('name = "x"\ngain = nan', ["key 'gain'", "finite"]),
        ('name = "x"\ngain = true', ["key 'gain'", "expected a number", "bool"]),
        ('name = "x"\ngain = 1\ncount = 11', ["key 'count'", "in 0..10"]),
        ('name = "x"\ngain = 1\ncount = 1.5', ["key 'count'", "expected an integer"]),
        ('name = "x"\ngain = 1\nids = [1, 2.5]', ["key 'ids'", "array of integers"]),
        ('name = "x"\ngain = 1\nxyz = [1, 2]', ["key 'xyz'", "expected 3 numbers, got 2"]),
        ('name = "x"\ngain = 1\n[sub]\nrate_hz = 0', ["[sub]", "key 'rate_hz'", "(Hz)"]),
        ('name = "x"\ngain = 1\n[sub]\nmode = "b"', ["[sub]", "key 'mode'", "one of"]),
        ('name = "x"\ngain = 1\n[sub]\nspeed = 1', ["[sub]", "unknown key 'speed'"]),
        ('name = "x"\ngain = 1\nsub = 3', ["[sub]", "expected a table"]),
        ("name = ", ["f.toml", "not valid TOML"]),
    ],
)
def test_each_mistake_is_one_line_naming_file_table_and_key(text, words):
    with pytest.raises(Bad) as info:
        read(text)
    message = str(info.value)
    assert message.startswith("f.toml: ") and "\n" not in message
    for w in words:
        assert w in message, (w, message)


def _odd(value: int) -> str | None:
    return None if value % 2 else f"must be odd, got {value}"


@dataclass(frozen=True)
class Link:
    mode: bool | str = field(default="auto", metadata=key_spec(choices=(True, False, "auto")))
    hosts: tuple[str, ...] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)
    port: int = field(default=1, metadata=key_spec(range=Range(1), check=_odd))


@dataclass(frozen=True)
class Doc:
    link: Link = field(default_factory=Link)


def test_choices_string_arrays_data_tables_and_checks():
    doc = {"link": {"mode": True, "hosts": ["a", "b"], "extra": {"x/y": [1]}, "port": 3}}
    assert build(Doc, doc, source="f.toml", error=Bad).link == Link(
        True, ("a", "b"), {"x/y": [1]}, 3
    )
    for table, words in [
        ({"mode": 1}, "key 'mode': must be one of true, false, 'auto', got 1"),  # 1 is not true
        ({"hosts": "a"}, "key 'hosts': expected an array of strings, got str 'a'"),
        ({"hosts": ["a", ""]}, "key 'hosts': expected an array of non-empty strings, got str ''"),
        ({"extra": 3}, "key 'extra': expected a table, got int 3"),
        ({"port": 0}, "key 'port': must be >= 1, got 0"),
        ({"port": 4}, "key 'port': must be odd, got 4"),
    ]:
        with pytest.raises(Bad) as info:
            build(Doc, {"link": table}, source="f.toml", error=Bad)
        assert str(info.value) == f"f.toml: [link]: {words}"


def test_a_value_from_elsewhere_is_named_by_its_origin():
    origins = {"link.port": "environment LINK_PORT", "link": "not a key of [link]"}
    doc = {"link": {"port": 4, "mode": "auto"}}
    with pytest.raises(Bad) as info:
        build(Doc, doc, source="f.toml", error=Bad, origins=origins)
    assert str(info.value) == "environment LINK_PORT: [link]: key 'port': must be odd, got 4"
    with pytest.raises(Bad) as info:  # the file's own values are still the file's
        build(Doc, {"link": {"mode": "x"}}, source="f.toml", error=Bad, origins=origins)
    assert str(info.value).startswith("f.toml: [link]: key 'mode': ")


def test_files_are_read_bounded_and_as_utf8(tmp_path):
    (tmp_path / "nul.toml").write_bytes(b'name = "x"\x00\n')
    (tmp_path / "latin.toml").write_bytes(b'name = "x"\n# \xe9\n')
    (tmp_path / "bom.toml").write_bytes('\ufeffname = "é"\n'.encode())
    with pytest.raises(Bad, match="NUL"):
        parse_toml_file(tmp_path / "nul.toml", Bad, "a thing")
    with pytest.raises(Bad, match=r"latin.toml: line 2: not UTF-8.*not a thing"):
        parse_toml_file(tmp_path / "latin.toml", Bad, "a thing")
    assert parse_toml_file(tmp_path / "bom.toml", Bad, "a thing") == {"name": "é"}


def test_a_table_of_named_numbers_and_a_matrix():
    t = TomlTable({"c": {"a": 1, "b": 2.5}, "m": [[1, 0], [0, 1]]}, "f", "[[j]] #1", Bad)
    assert t.number_table("c") == {"a": 1.0, "b": 2.5}
    assert t.matrix("m", 2).tolist() == [[1.0, 0.0], [0.0, 1.0]]
    with pytest.raises(Bad, match=r"\[\[j\]\] #1: key 'm': expected a 3×3"):
        t.matrix("m", 3)
    with pytest.raises(Bad, match=r"\[\[j\]\] #1.c: key 'a'"):
        TomlTable({"c": {"a": "x"}}, "f", "[[j]] #1", Bad).number_table("c")


toml_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda children: (
        st.lists(children, max_size=3)
        | st.dictionaries(
            st.sampled_from(["name", "gain", "ids", "sub", "x"]), children, max_size=4
        )
    ),
    max_leaves=10,
)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.sampled_from(["name", "gain", "count", "ids", "xyz", "sub", "on"]),
                       toml_values, max_size=7))  # fmt: skip
def test_any_parsed_document_gives_a_value_or_the_one_error(doc):
    doc = {k: v for k, v in doc.items() if v is not None}
    try:
        top = build(Top, doc, source="f.toml", error=Bad)
    except Bad as exc:
        assert str(exc).startswith("f.toml: ") and "\n" not in str(exc)
    else:
        assert isinstance(top, Top) and isinstance(top.sub, Sub)
