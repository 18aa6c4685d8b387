"""MCAP recording: round trip, Foxglove viewer channels, kill -9 leaves a readable file,
and ``recover`` writes a truncated file's messages whole (beside it, or in place with a
backup). Damaged files: tests/test_bad_input_daq.py."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from daq import foxglove
from daq.columnar import Column, StreamSchema, decode, encode
from daq.recording_reader import read_recording, scan
from daq.recording_recover import recover
from daq.recording_writer import McapRecorder

SCHEMA = StreamSchema(
    "cell/c/robot/r/dev/ch",
    (Column("seq", "uint64"), Column("x_mm", "float64", unit="mm")),
    meta={"device": "dev"},
)


def _write(path, n, **kw):
    rec = McapRecorder(path, metadata={"daq": {"cell": "c"}}, **kw)
    cid = rec.add_columnar(SCHEMA, {"device": "dev"})
    for i in range(n):
        cols = {"seq": np.arange(i * 10, i * 10 + 10), "x_mm": np.ones(10) * i}
        payload = encode(SCHEMA, cols, i)
        rec.write(cid, payload, 1_000_000_000 + i * 10_000_000, sequence=i)
    return rec


def test_round_trip_streaming_and_seeking(tmp_path):
    p = tmp_path / "a.mcap"
    _write(p, 50).close()
    rec = read_recording(p)
    msgs = list(rec.messages_iter())
    assert rec.complete and not rec.truncated and len(msgs) == 50
    schema = StreamSchema.loads(msgs[0].schema.data)
    assert schema == SCHEMA
    _, cols = decode(schema, msgs[7].data)
    np.testing.assert_array_equal(cols["seq"], np.arange(70, 80))
    assert rec.metadata["daq"] == {"cell": "c"}
    assert msgs[0].channel.metadata["device"] == "dev"
    # common tooling (a seeking reader using the summary) opens the finished file
    with open(p, "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary().statistics.message_count == 50
        assert sum(1 for _ in reader.iter_messages(topics=[SCHEMA.key])) == 50


def test_foxglove_channels(tmp_path):
    p = tmp_path / "f.mcap"
    rec = McapRecorder(p)
    cid = rec.add_json(
        "viz/points", foxglove.POINT_CLOUD, foxglove.schema_bytes(foxglove.POINT_CLOUD)
    )
    pid = rec.add_json(
        "viz/poses", foxglove.POSES_IN_FRAME, foxglove.schema_bytes(foxglove.POSES_IN_FRAME)
    )
    xyz = np.array([[1000.0, 2000.0, 3000.0], [np.nan, 0, 0], [1.0, 2.0, 3.0]])
    rec.write(cid, foxglove.point_cloud(1_500_000_000, "tracker", xyz), 1)
    rec.write(pid, foxglove.poses_in_frame(1_500_000_000, "tracker", xyz), 1)
    rec.close()
    with open(p, "rb") as fh:
        reader = make_reader(fh)
        out = {ch.topic: (schema, json.loads(m.data)) for schema, ch, m in reader.iter_messages()}
    schema, cloud = out["viz/points"]
    assert schema.name == "foxglove.PointCloud" and schema.encoding == "jsonschema"
    assert cloud["timestamp"] == {"sec": 1, "nsec": 500_000_000}
    import base64

    pts = np.frombuffer(base64.b64decode(cloud["data"]), "<f8").reshape(-1, 3)
    np.testing.assert_allclose(pts, [[1.0, 2.0, 3.0], [0.001, 0.002, 0.003]])  # metres
    _, poses = out["viz/poses"]
    assert len(poses["poses"]) == 2 and poses["poses"][0]["orientation"]["w"] == 1.0
    assert foxglove.xyz_columns(["seq", "tcp_x_mm", "tcp_y_mm", "tcp_z_mm"]) == (
        "tcp_x_mm",
        "tcp_y_mm",
        "tcp_z_mm",
    )


WRITER = r"""
import sys, time, numpy as np
from daq.columnar import Column, StreamSchema, encode
from daq.recording_writer import McapRecorder
schema = StreamSchema("cell/c/robot/r/dev/ch", (Column("seq", "uint64"),))
rec = McapRecorder(sys.argv[1], chunk_interval_s=0.05, chunk_size_bytes=1 << 20)
cid = rec.add_columnar(schema)
i = 0
t_end = time.monotonic() + 30
while time.monotonic() < t_end:
    rec.write(cid, encode(schema, {"seq": np.arange(i * 10, i * 10 + 10)}, i), time.time_ns())
    i += 1
    if i == 100:
        print("ready", flush=True)
    time.sleep(0.001)
"""


@pytest.mark.timeout(60)
def test_kill_9_leaves_readable_file_and_recover_rewrites_it(tmp_path):
    p = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(p)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.5)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    # a seeking reader needs the summary, which a killed writer never wrote
    with open(p, "rb") as fh, pytest.raises(Exception):  # noqa: B017
        list(make_reader(fh).iter_messages())
    rec, counts = scan(p)
    assert not rec.complete
    n = counts["cell/c/robot/r/dev/ch"]
    assert n >= 100  # everything up to the last closed chunk (≤ 50 ms before the kill)
    # messages are whole and in order
    seqs = []
    for m in read_recording(p).messages_iter():
        seqs.extend(np.frombuffer(m.data[24:], "<u8").tolist())
    assert seqs == list(range(len(seqs)))
    out = tmp_path / "fixed.mcap"
    recover(p, out)
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary().statistics.message_count == n
        assert sum(1 for _ in reader.iter_messages()) == n
    before = p.read_bytes()
    result = recover(p)  # beside the original by default; the original untouched
    assert result.output == tmp_path / "killed.recovered.mcap" and p.read_bytes() == before
    rec2, counts2 = scan(result.output)
    assert rec2.complete and counts2 == counts
    result = recover(p, in_place=True)  # replaced, the original kept as a backup
    assert result.backup == tmp_path / "killed.mcap.bak"
    assert result.backup.read_bytes() == before
    rec3, counts3 = scan(p)
    assert rec3.complete and counts3 == counts
    assert recover(p).output is None  # complete now: left alone, nothing written
