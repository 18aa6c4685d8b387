"""Foxglove channels (daq.foxglove_channels): at a bounded rate, every tracker point kept,
joints named, the twin's TCP and frames; the messages validate against Foxglove's published JSON
schemas (tests/data/foxglove_schemas, vendored from the foxglove-sdk repository) and our
own, read back with the ``mcap`` package's reader."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import jsonschema
import numpy as np
from mcap.reader import make_reader

from daq.columnar import Column, StreamSchema
from daq.foxglove_channels import StreamViewer
from daq.recording_writer import McapRecorder

PUBLISHED = Path(__file__).parents[1] / "data" / "foxglove_schemas"
T0 = 1_795_000_000_000_000_000  # host UTC ns


def _base(extra: tuple[Column, ...]) -> tuple[Column, ...]:
    return (Column("seq", "uint64"), Column("t_mapped_ns", "int64"), *extra)


TRACKER = StreamSchema(
    "cell/c/robot/r/tracker/samples",
    _base((Column("x_mm", "float64"), Column("y_mm", "float64"), Column("z_mm", "float64"))),
    {},
)
GRATING = StreamSchema(
    "cell/c/robot/r/grating/samples",
    _base(tuple(Column(f"grating{i}_counts", "int64") for i in range(1, 7))),
    {"joints": [1, 2, 3, 4, 5, 6]},
)
STATE = StreamSchema(
    "twin/c/robot/r/state",
    _base(
        (
            Column("t_publish_ns", "int64"),
            Column("q_deg", "float64", (6,)),
            Column("tcp_mm", "float64", (3,)),
            Column("flange_mm", "float64", (3,)),
            Column("flange_quat", "float64", (4,)),
            Column("encoder_minus_grating_deg", "float64", (6,)),
        )
    ),
    {},
)
NAMES = ["base", "link1", "tcp"]
FRAMES = StreamSchema(
    "twin/c/robot/r/frames",
    _base((Column("frame_mm", "float64", (3, 3)), Column("frame_quat", "float64", (3, 4)))),
    {"frames": NAMES, "parents": ["tracker", "base", "link1"]},
)


def _batch(schema: StreamSchema, k: int) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {
        "seq": np.array([k], np.uint64),
        "t_mapped_ns": np.array([T0 + k * 1_000_000], np.int64),
    }
    for c in schema.columns[2:]:
        if c.name == "frame_quat":
            q = np.zeros((1, 3, 4))
            q[0, :, 0] = 1.0
            q[0, 1] = [np.cos(0.3), 0.0, 0.0, np.sin(0.3)]  # link1 turned about z
            cols[c.name] = q
        elif c.name == "frame_mm":
            cols[c.name] = np.array([[[1000.0, 0, 0], [1000.0, 0, 500.0], [1500.0, 0, 500.0]]])
        elif c.name == "flange_quat":
            cols[c.name] = np.array([[1.0, 0, 0, 0]])
        elif c.name == "encoder_minus_grating_deg":
            cols[c.name] = np.full((1, 6), np.nan) if k < 10 else np.full((1, 6), 0.01)
        elif c.dtype == "int64":
            cols[c.name] = np.array([1_000_000 + k], np.int64)
        else:
            cols[c.name] = np.full((1, *c.shape), float(k)) + (np.nan if k == 7 else 0.0)
    return cols


def test_viewer_channels_at_a_bounded_rate_keep_every_point(tmp_path):
    path = tmp_path / "v.mcap"
    rec = McapRecorder(path)
    viewers = {s.key: StreamViewer(rec, s, rate_hz=30.0) for s in (TRACKER, GRATING, STATE, FRAMES)}
    assert all(v.active for v in viewers.values())
    decoded = 0
    for k in range(2000):  # 2 s of 1 kHz batches, one sample each
        t = T0 + k * 1_000_000
        for s in (TRACKER, GRATING, STATE, FRAMES):
            v = viewers[s.key]
            if v.due(t):
                decoded += 1
                v.add(_batch(s, k), t)
    for v in viewers.values():  # the end of the recording
        v.flush(T0 + 2000 * 1_000_000)
    rec.close()
    # decoded: every tracker batch (its points), the others ~30 times a second
    assert decoded < 2000 + 3 * 2 * 31
    published = {f"foxglove.{p.stem}": json.loads(p.read_text()) for p in PUBLISHED.glob("*.json")}
    out: dict[str, list[dict]] = {}
    validators: dict[int, jsonschema.protocols.Validator] = {}
    with path.open("rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            if schema.id not in validators:
                doc = (
                    published[schema.name]
                    if schema.name.startswith("foxglove.")
                    else json.loads(schema.data)
                )
                cls = jsonschema.validators.validator_for(doc, jsonschema.Draft7Validator)
                cls.check_schema(doc)
                validators[schema.id] = cls(doc)
            msg = json.loads(message.data)
            validators[schema.id].validate(msg)
            assert channel.metadata["daq.kind"] == "foxglove"
            out.setdefault(channel.topic, []).append(msg)
    pts = out["cell/c/robot/r/tracker/samples/points"]
    assert 55 <= len(pts) <= 63  # 30 a second over 2 s, and the flush
    n_points = sum(len(base64.b64decode(m["data"])) // 24 for m in pts)
    assert n_points == 2000 - 1  # every point (sample 7's is NaN: left out)
    g = out["cell/c/robot/r/grating/samples/joints"]
    assert 55 <= len(g) <= 62 and g[-1]["counts"]["j6"] > 1_000_000 + 1950  # the newest
    j = out["twin/c/robot/r/state/joints"]
    assert j[0]["encoder_deg"]["j1"] is None and j[-1]["encoder_deg"]["j1"] > 0  # NaN -> null
    tcp = out["twin/c/robot/r/state/tcp"][-1]
    assert tcp["frame_id"] == "tracker" and tcp["pose"]["position"]["x"] > 1.0  # metres
    tf = out["twin/c/robot/r/frames/tf"]
    assert len(tf) % 3 == 0 and [m["child_frame_id"] for m in tf[:3]] == NAMES
    base, link1, tool = tf[:3]
    assert base["translation"] == {"x": 1.0, "y": 0.0, "z": 0.0}
    assert np.isclose(link1["translation"]["z"], 0.5)  # relative to its parent, metres
    # the tcp 0.5 m along the tracker's x from link1, which is turned by 0.6 rad about z
    t = tool["translation"]
    assert np.allclose([t["x"], t["y"]], [0.5 * np.cos(0.6), -0.5 * np.sin(0.6)])


def test_no_viewer_channels_at_rate_zero(tmp_path):
    rec = McapRecorder(tmp_path / "v.mcap")
    assert not StreamViewer(rec, TRACKER, rate_hz=0.0).active
    rec.close()


def test_joint_columns_named_by_their_joint_without_meta():
    """Without ``meta.joints``, ``grating<k>_counts`` is joint ``k`` (edges.channel_names)."""
    from daq.foxglove_channels import _joint_names

    cols = ["grating10_counts", "grating2_counts", "encoder1_counts", "other"]
    schema = StreamSchema(
        "cell/c/robot/r/g/samples", _base(tuple(Column(c, "int64") for c in cols)), {}
    )
    assert _joint_names(schema, cols) == ["j10", "j2", "j1", "other"]


def test_the_twins_tracking_becomes_a_plottable_channel(tmp_path):
    from calibration.twin.twin_keys import tracking_schema

    names = ("base.x_mm", "joint2.length_scale")
    schema = tracking_schema("twin/c/robot/r/tracking", names, "c", "r", "m")
    path = tmp_path / "v.mcap"
    rec = McapRecorder(path)
    viewer = StreamViewer(rec, schema, rate_hz=30.0)
    for k in range(3):  # one update a second
        t = T0 + k * 10**9
        cols = {
            "seq": np.array([k], np.uint64),
            "t_mapped_ns": np.array([t], np.int64),
            "t_publish_ns": np.array([t], np.int64),
            "point_mm": np.zeros((1, 3)),
            "predicted_mm": np.zeros((1, 3)),
            "error_mm": np.array([0.01 * (k + 1)]),
            "parameters": np.array([[1000.0 + k, 1.0 + 1e-5 * k]]),
            "standard_errors": np.array([[0.01, 1e-6]]),
            "lambda": np.array([0.99]),
            "state": np.array([k], np.uint8),
            "displacement_mm": np.array([0.02]),
            "steps": np.array([int(k >= 1)], np.uint32),
            "alarms": np.array([int(k >= 2)], np.uint32),
        }
        assert viewer.due(t)
        viewer.add(cols, t)
    rec.close()
    with path.open("rb") as fh:
        msgs = []
        for sch, channel, message in make_reader(fh).iter_messages():
            assert sch.name == "grating_twin.Tracking"
            assert channel.topic == "twin/c/robot/r/tracking/values"
            doc = json.loads(sch.data)
            jsonschema.Draft202012Validator.check_schema(doc)
            msg = json.loads(message.data)
            jsonschema.Draft202012Validator(doc).validate(msg)
            msgs.append(msg)
    assert len(msgs) == 3
    last = msgs[-1]
    assert last["parameters"] == {"base.x_mm": 1002.0, "joint2.length_scale": 1.00002}
    assert last["tracking"]["state"] == 2 and last["tracking"]["alarms"] == 1
    assert np.isclose(last["tracking"]["error_mm"], 0.03)


def test_the_shipped_layout_plots_the_tracking_channel_by_its_fields():
    from daq.foxglove_channels import TRACKING_FIELDS

    layout = json.loads((Path(__file__).parents[2] / "docs" / "foxglove-layout.json").read_text())
    panel = layout["configById"]["Plot!tracking"]
    prefix = '"twin/emulated/robot/robot1/tracking/values".tracking.'
    fields = [p["value"].removeprefix(prefix) for p in panel["paths"]]
    assert all(p["value"].startswith(prefix) for p in panel["paths"])
    assert "error_mm" in fields and set(fields) <= set(TRACKING_FIELDS), fields
    assert "Plot!tracking" in json.dumps(layout["layout"])  # placed, not only configured
