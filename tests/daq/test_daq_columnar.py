"""daq.columnar: the self-describing batch encoding round-trips and rejects bad payloads."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daq.columnar import Column, StreamSchema, decode, encode, read_header
from daq.errors import SchemaError

SCHEMA = StreamSchema(
    key="cell/c/robot/r/dev/ch",
    columns=(
        Column("seq", "uint64"),
        Column("t_device_us", "int64", unit="us", clock="device"),
        Column("flag", "uint8"),
        Column("xyz_mm", "float64", (3,), unit="mm"),
        Column("status", "uint16", (2,)),
    ),
    meta={"device": "dev"},
)


def columns(n, rng):
    return {
        "seq": np.arange(n, dtype=np.uint64),
        "t_device_us": rng.integers(-(2**62), 2**62, n),
        "flag": rng.integers(0, 255, n).astype(np.uint8),
        "xyz_mm": rng.normal(size=(n, 3)),
        "status": rng.integers(0, 2**16, (n, 2)).astype(np.uint16),
    }


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 300), seed=st.integers(0, 2**32 - 1), batch_seq=st.integers(0, 2**64 - 1))
def test_round_trip(n, seed, batch_seq):
    cols = columns(n, np.random.default_rng(seed))
    payload = encode(SCHEMA, cols, batch_seq)
    header, out = decode(SCHEMA, payload)
    assert header.n_samples == n and header.batch_seq == batch_seq
    for name, arr in cols.items():
        np.testing.assert_array_equal(out[name], arr)
        assert out[name].dtype == np.dtype(SCHEMA.column(name).dtype)


def test_schema_json_round_trip_and_id():
    doc = json.loads(SCHEMA.dumps())
    assert doc["columns"][3] == {"name": "xyz_mm", "dtype": "float64", "shape": [3], "unit": "mm"}
    back = StreamSchema.loads(SCHEMA.dumps())
    assert back == SCHEMA and back.schema_id == SCHEMA.schema_id
    other = StreamSchema(SCHEMA.key, SCHEMA.columns[:-1])
    assert other.schema_id != SCHEMA.schema_id


def test_layout_is_documented_little_endian_aligned():
    payload = encode(SCHEMA, columns(2, np.random.default_rng(0)), 7)
    # header 24, seq 16, t 16, flag 2 -> padded 8, xyz 48, status 8 (4 values)
    assert len(payload) == 24 + 16 + 16 + 8 + 48 + 8
    assert payload[:4] == b"DQC1"
    assert int.from_bytes(payload[16:24], "little") == 7
    assert int.from_bytes(payload[24:32], "little") == 0
    assert int.from_bytes(payload[32:40], "little") == 1


def test_rejects_bad_payloads():
    payload = encode(SCHEMA, columns(3, np.random.default_rng(1)), 0)
    with pytest.raises(SchemaError, match="magic"):
        read_header(b"XXXX" + payload[4:])
    with pytest.raises(SchemaError, match="expected"):
        decode(SCHEMA, payload[:-8])
    with pytest.raises(SchemaError, match="stale schema"):
        decode(StreamSchema(SCHEMA.key, SCHEMA.columns[:-1]), payload)
    with pytest.raises(SchemaError, match="shape"):
        encode(SCHEMA, {**columns(3, np.random.default_rng(1)), "xyz_mm": np.zeros((3, 2))}, 0)
    with pytest.raises(SchemaError, match="dtype"):
        Column("x", "object")


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 400), step=st.integers(1, 120), seed=st.integers(0, 2**16))
def test_encode_slices_equals_encode_of_each_slice(n, step, seed):
    from daq.columnar import encode_slices

    cols = columns(n, np.random.default_rng(seed))
    cols["xyz_mm"] = cols["xyz_mm"][:, ::-1]  # a non-contiguous view
    got = encode_slices(SCHEMA, cols, 5, step)
    want = [
        encode(SCHEMA, {k: v[a : a + step] for k, v in cols.items()}, 5 + i)
        for i, a in enumerate(range(0, n, step))
    ]
    assert got == want
