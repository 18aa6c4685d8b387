"""One endpoint reaches everything: a subscriber connected only to the daemon's endpoint
sees the live twin's keys; ``twin run --from DIR`` works from any working directory; the
daemon's recording holds the twin's keys and channels Foxglove reads natively, checked
with an independent reader (the ``mcap`` package's, which seeks to the summary) and
``jsonschema`` against Foxglove's published JSON schemas (tests/data/foxglove_schemas).

Separate real processes over loopback: ``daq run`` on the emulated cell (sim-cell, real
protocols), the live twin (``twin run --from``, a zenoh client of the daemon, started in
another working directory with a relative ``--from``) and ``daq echo 'twin/**'``
connected to the daemon's endpoint and nothing else. The twin's calibration is
``tests/data/twin_calibrated_small`` (made from ``campaign_small.mcap``, see its run.json).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from daq.testing import free_port, recorded_columns

DATA = Path(__file__).parents[1] / "data"
CALIBRATED = DATA / "twin_calibrated_small"
PY = sys.executable


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


def _line(p: subprocess.Popen, prefix: str, timeout_s: float) -> tuple[str | None, list[str]]:
    """The first stdout line of ``p`` starting with ``prefix``, within ``timeout_s``."""
    import selectors

    seen: list[str] = []
    sel = selectors.DefaultSelector()
    sel.register(p.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline and len(seen) < 1000:
            if not sel.select(timeout=max(0.0, min(1.0, deadline - time.monotonic()))):
                if p.poll() is not None:
                    break
                continue
            line = p.stdout.readline()
            if not line:
                break
            seen.append(line)
            if line.startswith(prefix):
                return line, seen
    finally:
        sel.close()
    return None, seen


def test_earlier_run_is_found_from_another_working_directory(tmp_path, monkeypatch):
    from calibration.cli.run import _earlier_run

    shutil.copytree(CALIBRATED, tmp_path / "runs" / "cal")
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    run = _earlier_run("../runs/cal")
    assert Path(run["calibrated"]).resolve() == (tmp_path / "runs/cal/calibrated.toml")
    assert Path(run["files"]["scale"]).is_file() and Path(run["files"]["phases"]).is_file()
    # a run.json of before (paths relative to the first run's working directory) still works
    old = json.loads((tmp_path / "runs/cal/run.json").read_text())
    old.pop("paths_relative_to")
    old["calibrated"] = "demo-out/twin/calibrated.toml"
    old["files"] = {"scale": "demo-out/twin/scale.toml", "phases": "demo-out/twin/phases.json"}
    (tmp_path / "runs/cal/run.json").write_text(json.dumps(old))
    run = _earlier_run(str(tmp_path / "runs/cal"))
    assert Path(run["files"]["scale"]) == tmp_path / "runs/cal/scale.toml"
    # a file that is gone is named, with its key
    (tmp_path / "runs/cal/scale.toml").unlink()
    from calibration.errors import DataFileError

    with pytest.raises(DataFileError, match=r"files\.scale.*not there"):
        _earlier_run(str(tmp_path / "runs/cal"))


def test_twin_run_writes_run_json_paths_beside_it():
    # the shipped run.json is what write_twin_run writes (trimmed): names relative to its folder
    run = json.loads((CALIBRATED / "run.json").read_text())
    from calibration.cli.run_files import RUN_PATHS_RELATIVE_TO

    assert run["paths_relative_to"] == RUN_PATHS_RELATIVE_TO
    assert run["calibrated"] == "calibrated.toml"


@pytest.mark.timeout(240)
def test_the_daemons_endpoint_reaches_the_live_twin(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    mcap = tmp_path / "cell.mcap"
    shutil.copytree(CALIBRATED, tmp_path / "runs" / "cal")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs: list[subprocess.Popen] = []
    try:
        daemon = subprocess.Popen(
            [
                PY,
                "-m",
                "daq.cli",
                "run",
                "--record",
                str(mcap),
                "--listen",
                ep,
                "--duration",
                "150",
            ],
            stdout=subprocess.PIPE,
            stderr=open(tmp_path / "daq.err", "w"),  # noqa: SIM115 - the process holds it
            text=True,
            env=env,
        )
        procs.append(daemon)
        up, seen = _line(daemon, '{"daq": "running"', 90)
        assert up, "".join(seen) + (tmp_path / "daq.err").read_text()[-3000:]
        assert json.loads(up)["listen"] == [ep]
        # the twin from another working directory, --from relative to it, a client
        twin = subprocess.Popen(
            [PY, "-m", "calibration.cli", "run", "--from", "../runs/cal", "--out", "out2",
             "--connect", ep, "--publish-s", "90", "--wait-s", "60"],
            cwd=elsewhere,
            stdout=subprocess.PIPE,
            stderr=open(tmp_path / "twin.err", "w"),  # noqa: SIM115 - the process holds it
            text=True,
            env={**env, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
        )  # fmt: skip
        procs.append(twin)
        live, seen = _line(twin, '{"twin": "live"', 90)
        assert live, "".join(seen) + (tmp_path / "twin.err").read_text()[-3000:]
        keys = json.loads(live)["keys"]
        assert keys["state"] == "twin/emulated/robot/robot1/state"
        # a subscriber that knows only the daemon's endpoint
        echo = subprocess.run(
            [PY, "-m", "daq.cli", "echo", "twin/**", "--connect", ep, "--listen", "none",
             "--jsonl", str(tmp_path / "twin.jsonl"), "--duration", "6"],
            capture_output=True,
            text=True,
            timeout=90,
            env=env,
        )  # fmt: skip
        assert echo.returncode == 0, echo.stderr[-3000:]
        rows = [json.loads(x) for x in (tmp_path / "twin.jsonl").read_text().splitlines() if x]
        state = [r for r in rows if r["key"] == keys["state"]]
        health = [r["json"] for r in rows if r["key"] == keys["health"]]
        assert len(state) > 10, echo.stderr[-3000:]
        cols = state[-1]["columns"]
        assert len(cols["q_deg"][-1]) == 6 and len(cols["tcp_mm"][-1]) == 3
        assert all(abs(v) < 10_000 for v in cols["tcp_mm"][-1])
        assert health and health[-1]["samples"] > 0
        assert {"upstream_ms", "twin_ms", "latency_ms"} <= set(health[-1])
        # the model has [tracking] (its updates: tests/calibration/test_twin_live_tracking.py)
        assert health[-1]["tracking"]["on"] is True
        assert twin.poll() is None and daemon.poll() is None
        time.sleep(1.0)  # a few more viewer messages of the twin into the recording
    finally:
        for p in reversed(procs):
            _stop(p)
    assert daemon.returncode == 0, (tmp_path / "daq.err").read_text()[-3000:]
    _check_foxglove_channels(mcap)


FOXGLOVE_SCHEMAS = DATA / "foxglove_schemas"


def _check_foxglove_channels(path: Path) -> None:
    """Every JSON channel of the recording validates against its schema: Foxglove's
    published one for ``foxglove.*``, else the one the file carries (itself checked as a
    JSON schema); the channels the issue asks for are there; the frame transforms compose
    to the twin's TCP."""
    import base64

    import jsonschema
    from mcap.reader import make_reader

    published = {
        f"foxglove.{p.stem}": json.loads(p.read_text()) for p in FOXGLOVE_SCHEMAS.glob("*.json")
    }
    topics: dict[str, tuple[str, list[dict]]] = {}
    columnar: set[str] = set()
    with path.open("rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary() is not None  # a whole file: summary and indexes
        validators: dict[int, jsonschema.protocols.Validator] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding != "json":
                columnar.add(channel.topic)
                continue
            if schema.id not in validators:
                if schema.name.startswith("foxglove."):
                    doc = published[schema.name]  # the published schema, not the file's
                else:
                    doc = json.loads(schema.data)
                cls = jsonschema.validators.validator_for(doc, jsonschema.Draft7Validator)
                cls.check_schema(doc)
                validators[schema.id] = cls(doc)
            msg = json.loads(message.data)
            validators[schema.id].validate(msg)
            topics.setdefault(channel.topic, (schema.name, []))[1].append(msg)
    cell, twin = "cell/emulated/robot/robot1", "twin/emulated/robot/robot1"
    want = {
        f"{cell}/tracker/samples/points": "foxglove.PointCloud",
        f"{cell}/grating/samples/joints": "grating_twin.Joints",
        f"{cell}/encoders/samples/joints": "grating_twin.Joints",
        f"{twin}/state/joints": "grating_twin.Joints",
        f"{twin}/state/tcp": "foxglove.PoseInFrame",
        f"{twin}/frames/tf": "foxglove.FrameTransform",
    }
    for topic, name in want.items():
        assert topic in topics and topics[topic][0] == name, (topic, sorted(topics))
        assert topics[topic][1], topic
    assert {f"{twin}/state", f"{twin}/frames", f"{cell}/grating/samples"} <= columnar
    # named joints, plottable: counts of the gratings, degrees of the twin
    assert set(topics[f"{cell}/grating/samples/joints"][1][-1]["counts"]) == {
        f"j{i}" for i in range(1, 7)
    }
    assert all(
        isinstance(v, int)
        for v in topics[f"{cell}/grating/samples/joints"][1][-1]["counts"].values()
    )
    tj = topics[f"{twin}/state/joints"][1][-1]
    assert set(tj) == {"timestamp", "grating_deg", "encoder_deg", "encoder_minus_grating_deg"}
    assert all(isinstance(v, float) for v in tj["grating_deg"].values())
    cloud = topics[f"{cell}/tracker/samples/points"][1][-1]
    assert len(base64.b64decode(cloud["data"])) % cloud["point_stride"] == 0
    # one transform per link frame, chained tracker -> base -> link1 ... link6 -> tcp
    tf = topics[f"{twin}/frames/tf"][1]
    chain = ["base", *(f"link{i}" for i in range(1, 7)), "tcp"]
    last = {m["child_frame_id"]: m for m in tf[-len(chain) :]}
    assert set(last) == set(chain)
    assert [last[c]["parent_frame_id"] for c in chain] == ["tracker", *chain[:-1]]
    # composed, they put the TCP where the twin says it is (its effects: < 1 mm)
    rot, pos = np.eye(3), np.zeros(3)
    for c in chain:
        t, r = last[c]["translation"], last[c]["rotation"]
        pos = pos + rot @ np.array([t["x"], t["y"], t["z"]])
        rot = rot @ _rotation(r["w"], r["x"], r["y"], r["z"])
    # ... at the frames' own instant: the twin's state at that grating sample time (the
    # last TCP message is another instant: the arm moves ~15 mm between them)
    stamp = last["tcp"]["timestamp"]
    t_ns = int(stamp["sec"]) * 10**9 + int(stamp["nsec"])
    state = recorded_columns(path, f"{twin}/state")
    at = np.flatnonzero(state["t_mapped_ns"] == t_ns)
    assert at.size, "the frames' sample time is one of the twin's state samples"
    tcp_mm = state["tcp_mm"][at[0]]
    # the shipped layout names these topics
    layout = (Path(__file__).parents[2] / "docs" / "foxglove-layout.json").read_text()
    for topic in (*want, f"{twin}/frames/tf"):
        if not topic.endswith("encoders/samples/joints"):
            assert topic in layout, topic
    assert np.allclose(pos * 1000, tcp_mm, atol=1.0), (pos * 1000, tcp_mm)


def _rotation(w: float, x: float, y: float, z: float) -> np.ndarray:
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
