"""The one payload encoding of the daemon: a columnar batch described by a JSON schema.

A batch of N samples is a 24-byte header followed by one block per column, in schema
order, each block ``N × prod(shape)`` little-endian values, zero-padded to a multiple of
8 bytes (so every block starts 8-byte aligned)::

    offset  size  field
    0       4     magic b"DQC1"
    4       2     version (uint16, 1)
    6       2     flags (uint16, 0; reserved)
    8       4     schema_id (uint32): CRC-32 of the schema's canonical layout JSON
    12      4     n_samples (uint32)
    16      8     batch_seq (uint64): per key, +1 per message (gaps = lost messages)
    24      ...   column blocks

The schema (:class:`StreamSchema`, published once per key and answered by a queryable, see
docs/topics.md) lists each column's name, dtype, per-sample shape, unit and clock, so a
subscriber in any language decodes a payload with nothing but this description. Encoding
from numpy column arrays costs ~µs per thousand samples; there is no pickle anywhere.
"""

from __future__ import annotations

import json
import struct
import sys
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from daq.errors import SchemaError

FORMAT = "daq.columnar"
VERSION = 1
#: zenoh ``Encoding`` schema suffix and MCAP message encoding of columnar payloads.
ENCODING_NAME = "daq.columnar.v1"
#: MCAP schema encoding of the JSON layout description.
SCHEMA_ENCODING = "daq.columnar.schema.v1"
MAGIC = b"DQC1"
HEADER = struct.Struct("<4sHHIIQ")
ALIGN = 8
_ZEROS = bytes(ALIGN)

#: Column dtypes allowed in a schema (numpy names; always little-endian on the wire).
DTYPES: tuple[str, ...] = (
    "bool",
    "int8",
    "uint8",
    "int16",
    "uint16",
    "int32",
    "uint32",
    "int64",
    "uint64",
    "float32",
    "float64",
)


def _le(dtype: str) -> np.dtype:
    d = np.dtype(dtype)
    if sys.byteorder == "little" and d.byteorder in "=|":
        return d  # the native singleton: encode's ``arr.dtype is dt`` check is then cheap
    return d.newbyteorder("<")


@dataclass(frozen=True)
class Column:
    """One column: name (unit in the name), numpy dtype, per-sample shape, unit, clock."""

    name: str
    dtype: str
    shape: tuple[int, ...] = ()
    unit: str = ""
    clock: str | None = None
    description: str = ""

    def __post_init__(self) -> None:
        if self.dtype not in DTYPES:
            raise SchemaError(
                f"column {self.name!r}: dtype {self.dtype!r} not allowed "
                f"(allowed: {', '.join(DTYPES)})"
            )
        if not self.name or not isinstance(self.name, str):
            raise SchemaError(f"column name must be a non-empty string, got {self.name!r}")
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        if any(s < 0 for s in self.shape):
            raise SchemaError(f"column {self.name!r}: negative shape {self.shape}")

    @property
    def per_sample(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) if self.shape else 1

    def to_json(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"name": self.name, "dtype": self.dtype, "shape": list(self.shape)}
        doc["unit"] = self.unit
        if self.clock is not None:
            doc["clock"] = self.clock
        if self.description:
            doc["description"] = self.description
        return doc

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> Column:
        try:
            return cls(
                name=str(doc["name"]),
                dtype=str(doc["dtype"]),
                shape=tuple(doc.get("shape", ())),
                unit=str(doc.get("unit", "")),
                clock=doc.get("clock"),
                description=str(doc.get("description", "")),
            )
        except KeyError as exc:
            raise SchemaError(f"column description lacks key {exc}") from exc


@dataclass(frozen=True)
class Header:
    """The fixed part of a payload."""

    version: int
    flags: int
    schema_id: int
    n_samples: int
    batch_seq: int


#: A payload's layout for ``n`` samples: its bytes, and per column its name, dtype, value
#: count, byte offset and array shape (None: ``(n,)`` as read).
PayloadLayout = tuple[int, tuple[tuple[str, np.dtype, int, int, tuple[int, ...] | None], ...]]


@dataclass(frozen=True)
class StreamSchema:
    """Layout and meaning of the payloads on one key.

    ``meta`` carries everything that is not layout (source device, driver, status bits,
    clocks, joints); it is published with the schema but does not change ``schema_id``.
    """

    key: str
    columns: tuple[Column, ...]
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [c.name for c in self.columns]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise SchemaError(f"schema for {self.key!r}: duplicate column {sorted(dup)[0]!r}")

    def layout_json(self) -> str:
        """Canonical JSON of what determines the byte layout (hashed into ``schema_id``)."""
        cols = [[c.name, c.dtype, list(c.shape)] for c in self.columns]
        return json.dumps({"format": FORMAT, "version": VERSION, "columns": cols}, sort_keys=True)

    @cached_property
    def schema_id(self) -> int:
        return zlib.crc32(self.layout_json().encode())

    @cached_property
    def plan(self) -> tuple[tuple[str, np.dtype, tuple[int, ...], int, int], ...]:
        """Per column: name, little-endian dtype, shape, values per sample, bytes per value."""
        return tuple(
            (c.name, _le(c.dtype), c.shape, c.per_sample, np.dtype(c.dtype).itemsize)
            for c in self.columns
        )

    @cached_property
    def _layouts(self) -> dict[int, PayloadLayout]:
        return {}

    def layout(self, n: int) -> PayloadLayout:
        """Payload bytes of ``n`` samples, and per column: name, dtype, value count, byte
        offset and array shape (None: ``(n,)`` as read). Cached per ``n``: a stream's
        messages come in a few sizes, and decoding a 1-sample message is mostly this."""
        got = self._layouts.get(n)
        if got is None:
            cols = []
            offset = HEADER.size
            for name, dt, shape, per, size in self.plan:
                count = n * per
                cols.append((name, dt, count, offset, (n, *shape) if shape else None))
                offset += _padded(count * size)
            got = (offset, tuple(cols))
            if len(self._layouts) < 64:  # bounded: sizes beyond that are computed each time
                self._layouts[n] = got
        return got

    def column(self, name: str) -> Column:
        for c in self.columns:
            if c.name == name:
                return c
        raise SchemaError(f"schema for {self.key!r} has no column {name!r}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.columns)

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "key": self.key,
            "schema_id": self.schema_id,
            "byte_order": "little",
            "header": {
                "size": HEADER.size,
                "fields": [
                    ["magic", "bytes4", MAGIC.decode()],
                    ["version", "uint16"],
                    ["flags", "uint16"],
                    ["schema_id", "uint32"],
                    ["n_samples", "uint32"],
                    ["batch_seq", "uint64"],
                ],
            },
            "column_alignment": ALIGN,
            "columns": [c.to_json() for c in self.columns],
            "meta": dict(self.meta),
        }

    def dumps(self) -> bytes:
        return json.dumps(self.to_json(), indent=1, sort_keys=False).encode()

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> StreamSchema:
        if doc.get("format") != FORMAT or doc.get("version") != VERSION:
            raise SchemaError(
                f"not a {FORMAT} v{VERSION} schema: format={doc.get('format')!r} "
                f"version={doc.get('version')!r}"
            )
        schema = cls(
            key=str(doc.get("key", "")),
            columns=tuple(Column.from_json(c) for c in doc["columns"]),
            meta=dict(doc.get("meta", {})),
        )
        if "schema_id" in doc and int(doc["schema_id"]) != schema.schema_id:
            raise SchemaError(
                f"schema for {schema.key!r}: schema_id {doc['schema_id']} does not match its "
                f"columns ({schema.schema_id})"
            )
        return schema

    @classmethod
    def loads(cls, data: bytes | str) -> StreamSchema:
        try:
            doc = json.loads(data)
        except ValueError as exc:
            raise SchemaError(f"schema is not valid JSON: {exc}") from exc
        return cls.from_json(doc)


def _padded(nbytes: int) -> int:
    return (nbytes + ALIGN - 1) // ALIGN * ALIGN


def payload_size(schema: StreamSchema, n: int) -> int:
    return schema.layout(n)[0]


def encode(schema: StreamSchema, columns: Mapping[str, ArrayLike], batch_seq: int) -> bytes:
    """One payload from column arrays (each ``(N, *shape)``; every schema column needed)."""
    plan = schema.plan
    try:
        n = len(columns[plan[0][0]])  # type: ignore[arg-type]
    except KeyError:
        raise SchemaError(f"encode {schema.key!r}: missing column {plan[0][0]!r}") from None
    parts = [HEADER.pack(MAGIC, VERSION, 0, schema.schema_id, n, batch_seq)]
    for name, dt, shape, per, size in plan:
        try:
            arr = columns[name]
        except KeyError:
            raise SchemaError(f"encode {schema.key!r}: missing column {name!r}") from None
        if not isinstance(arr, np.ndarray):
            arr = np.asarray(arr)
        if arr.shape[1:] != shape or arr.shape[:1] != (n,):
            raise SchemaError(
                f"encode {schema.key!r}: column {name!r} has shape {arr.shape}, "
                f"expected {(n, *shape)}"
            )
        if arr.dtype is not dt and arr.dtype != dt:
            arr = arr.astype(dt)
        parts.append(arr.tobytes())
        pad = -(n * per * size) % ALIGN
        if pad:
            parts.append(_ZEROS[:pad])
    return b"".join(parts)


_HEADER_DTYPE = np.dtype(
    [
        ("magic", "S4"),
        ("version", "<u2"),
        ("flags", "<u2"),
        ("schema_id", "<u4"),
        ("n_samples", "<u4"),
        ("batch_seq", "<u8"),
    ]
)
assert _HEADER_DTYPE.itemsize == HEADER.size


def encode_slices(
    schema: StreamSchema, columns: Mapping[str, ArrayLike], batch_seq: int, step: int
) -> list[bytes]:
    """Payloads of consecutive slices of at most ``step`` samples (``batch_seq`` counting
    up from the given one); each equals ``encode`` of that slice. The full slices are laid
    out at once in one ``(slices, payload bytes)`` array, one numpy copy per column for
    all of them; each payload is then one ``tobytes`` of its row."""
    plan = schema.plan
    try:
        n = len(columns[plan[0][0]])  # type: ignore[arg-type]
    except KeyError:
        raise SchemaError(f"encode {schema.key!r}: missing column {plan[0][0]!r}") from None
    if n <= step:
        return [encode(schema, columns, batch_seq)]
    full = n // step
    size = payload_size(schema, step)
    buf = np.empty((full, size), np.uint8)
    hdr = np.empty(full, _HEADER_DTYPE)
    hdr["magic"] = MAGIC
    hdr["version"] = VERSION
    hdr["flags"] = 0
    hdr["schema_id"] = schema.schema_id
    hdr["n_samples"] = step
    hdr["batch_seq"] = np.arange(batch_seq, batch_seq + full, dtype=np.uint64)
    buf[:, : HEADER.size] = hdr.view(np.uint8).reshape(full, HEADER.size)
    off = HEADER.size
    tails: dict[str, Any] = {}
    for name, dt, shape, per, item in plan:
        try:
            arr = np.asarray(columns[name])
        except KeyError:
            raise SchemaError(f"encode {schema.key!r}: missing column {name!r}") from None
        if arr.shape != (n, *shape):
            raise SchemaError(
                f"encode {schema.key!r}: column {name!r} has shape {arr.shape}, "
                f"expected {(n, *shape)}"
            )
        nbytes = step * per * item
        # a typed view of the column's bytes in every row: one strided, casting copy
        buf[:, off : off + nbytes].view(dt)[...] = arr[: full * step].reshape(full, step * per)
        pad = _padded(nbytes) - nbytes
        if pad:
            buf[:, off + nbytes : off + nbytes + pad] = 0
        off += nbytes + pad
        tails[name] = arr[full * step :]
    out = list(map(np.ndarray.tobytes, buf))
    if n > full * step:
        out.append(encode(schema, tails, batch_seq + full))
    return out


def read_header(payload: bytes | bytearray | memoryview) -> Header:
    if len(payload) < HEADER.size:
        raise SchemaError(f"payload of {len(payload)} bytes is shorter than the header")
    magic, version, flags, schema_id, n, batch_seq = HEADER.unpack_from(payload, 0)
    if magic != MAGIC:
        raise SchemaError(f"bad magic {magic!r} (expected {MAGIC!r})")
    if version != VERSION:
        raise SchemaError(f"unsupported payload version {version}")
    return Header(version, flags, schema_id, n, batch_seq)


def decode(
    schema: StreamSchema, payload: bytes | bytearray | memoryview
) -> tuple[Header, dict[str, NDArray[Any]]]:
    """Header and column arrays ``(N, *shape)`` (read-only views into ``payload``)."""
    header = read_header(payload)
    if header.schema_id != schema.schema_id:
        raise SchemaError(
            f"decode {schema.key!r}: payload schema_id {header.schema_id:#010x} "
            f"!= {schema.schema_id:#010x} (stale schema?)"
        )
    n = header.n_samples
    expected, cols = schema.layout(n)
    if len(payload) != expected:
        raise SchemaError(
            f"decode {schema.key!r}: payload is {len(payload)} bytes, expected {expected} "
            f"for {n} samples"
        )
    out: dict[str, NDArray[Any]] = {}
    for name, dt, count, offset, shape in cols:
        arr = np.frombuffer(payload, dtype=dt, count=count, offset=offset)
        out[name] = arr if shape is None else arr.reshape(shape)
    return header, out
