"""Replay a small recorded campaign through the twin: bit-identical results; a dropout.

The recording ``tests/data/campaign_small.mcap`` is made by (docs/twin-run.md):

    python -m daq.demo --record-only --speed 160 --no-encoders --seed 5 \
        --out /tmp/campaign-small --mcap tests/data/campaign_small.mcap

a real ``daq run`` on the emulated cell (whole KR500 campaign at 160x, gravity deflection
switched on and not told to the twin; gear torsion and backlash on, as always).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calibration.cli.run_files import write_twin_run
from calibration.twin.streams import read_recording_streams
from calibration.twin.twin_run import TwinRun, run_twin

DATA = Path(__file__).parents[1] / "data" / "campaign_small.mcap"

pytestmark = pytest.mark.skipif(not DATA.exists(), reason="tests/data/campaign_small.mcap missing")


def _run(src: Path, out: Path) -> tuple[TwinRun, dict[str, Any]]:
    """The twin of ``src`` in memory, and run.json's document of its files, written to ``out``."""
    result = run_twin(read_recording_streams(src), "kr500")
    return result, write_twin_run(out, out, result, report=False)


@pytest.fixture(scope="module")
def replayed(tmp_path_factory) -> tuple[TwinRun, dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("replay") / "a"
    return (*_run(DATA, out), out)


def test_replay_gives_bit_identical_model_and_report(replayed, tmp_path):
    _, a, a_dir = replayed
    _, b = _run(DATA, tmp_path / "b")
    for name in (
        "calibrated.toml",
        "report/report.json",
        "campaign.csv",
        "sweep.csv",
        "home.csv",
        "scale.toml",
        "phases.json",
    ):
        assert (a_dir / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert a["stage_table"] == b["stage_table"]
    phases = json.loads((a_dir / "phases.json").read_text())["phases"]
    # the emulator's KR500 campaign: 2° stops limit to limit and back, 250 poses
    assert phases["sweep_stops"] == {
        "1": {"forward": 185, "backward": 185},
        "2": {"forward": 75, "backward": 75},
        "3": {"forward": 92, "backward": 92},
        "4": {"forward": 350, "backward": 350},
        "5": {"forward": 120, "backward": 120},
        "6": {"forward": 350, "backward": 350},
    }
    assert phases["poses"] == {"identify": 100, "validate": 150}
    assert sum(phases["home_returns"].values()) >= 58  # of 60
    report = json.loads((a_dir / "report" / "report.json").read_text())
    stages = report["closed_loop"]["stages"]
    val = [s["sets"]["validate"]["AP"]["mean"] for s in stages]
    assert val[-1] < 0.025 < 0.1 < val[0]  # nominal (mm) -> final, with the found effects
    # the emulated cell's one undeclared effect, and nothing else: round 1's loop models
    # the deflection relative to each sweep, round 2 reads rings through maps refitted
    # without it (with torsion and backlash of the upstream joints taken out too)
    assert [s["effect"]["kind"] for s in stages if "effect" in s] == ["gravity_deflection"]
    rounds = report["twin_run"]["joint_fit"]["rounds"]
    assert len(rounds) >= 2 and rounds[-1]["deflection_taken_out_of_sweeps"]
    assert not rounds[0]["deflection_taken_out_of_sweeps"]
    assert rounds[-1]["added"] == [s["label"] for s in stages if "effect" in s]
    # every map the strip's, but joint 2's: its counterbalance's torque depends on its own
    # angle alone, so the deflection that torque causes is the same at every pose and stays
    # in its map (docs/scale-calibration.md)
    terms = rounds[-1]["scale_terms"]
    assert all("nonlinear" not in t for j, t in terms.items() if j != "2"), terms


def _drop_slice(src: Path, dst: Path, device: str, t_from_s: float, t_to_s: float) -> int:
    """Copy ``src`` without ``device``'s messages logged in [t_from_s, t_to_s) from the start."""
    from daq.recording_reader import read_recording
    from daq.recording_writer import McapRecorder

    rec = read_recording(src)
    dropped = 0
    start = None
    with McapRecorder(dst) as out:
        for m in rec.messages_iter():
            if start is None:
                start = m.log_time
                for name, meta in rec.metadata.items():
                    out._writer.add_metadata(name, meta)
            cid = out.add_channel(
                m.topic,
                schema_name=m.schema.name if m.schema else "",
                schema_encoding=m.schema.encoding if m.schema else "",
                schema_data=m.schema.data if m.schema else b"",
                message_encoding=m.channel.message_encoding,
                metadata=dict(m.channel.metadata),
            )
            t = (m.log_time - start) * 1e-9
            if f"/{device}/" in m.topic + "/" and t_from_s <= t < t_to_s:
                dropped += 1
                continue
            out.write(cid, m.data, m.log_time, m.publish_time, m.sequence)
    return dropped


def test_a_tracker_dropout_still_calibrates_and_reports_the_lost_interval(tmp_path):
    src = tmp_path / "dropout.mcap"
    assert _drop_slice(DATA, src, "tracker", 30.0, 33.0) > 0
    result, run = _run(src, tmp_path / "out")
    phases = json.loads((tmp_path / "out" / "phases.json").read_text())
    lost = [x for x in phases["lost_intervals"] if x["device"] == "tracker"]
    assert len(lost) == 1
    assert 2.9 < lost[0]["duration_s"] < 3.2
    assert lost[0]["samples_missing"] > 2500
    assert phases["stops_lost"]  # the stops in the gap have no tracker point
    assert all(s["reason"] for s in phases["stops_lost"])
    assert (tmp_path / "out" / "calibrated.toml").exists()
    report = json.loads((tmp_path / "out" / "report" / "report.json").read_text())
    assert report["twin_run"]["lost_intervals"][0]["device"] == "tracker"
    assert run["success"] and result.success


def test_the_twin_in_memory_is_the_twin_its_files_give(replayed):
    """The live twin after ``twin run`` is built in memory; ``--from DIR`` reads it back
    from the files: the same angles from the same counts, the same TCP points, bit for bit
    (every float in calibrated.toml and scale.toml is written as its shortest repr, which
    reads back as the same double)."""
    from calibration.effects.model_effects import predict_tcp
    from calibration.twin.live_twin import CalibratedTwin

    result, run, _ = replayed
    memory = CalibratedTwin.from_twin_run(result, run["calibrated"])
    files = CalibratedTwin.from_run(run)
    assert memory.name == files.name == run["calibrated"]
    assert (
        memory.t0_ns == files.t0_ns
        and memory.encoder_counts_per_rev == files.encoder_counts_per_rev
    )
    assert np.array_equal(memory.encoder_offset_deg, files.encoder_offset_deg)
    counts = result.measurements.pose_counts.astype(np.int64)  # (m, n): every pose's gratings
    n = memory.description.n_joints
    angles = {}
    for key, twin in (("memory", memory), ("files", files)):
        maps = [twin.scale.scale(j).counts_to_angle_deg(counts[:, j - 1]) for j in range(1, n + 1)]
        angles[key] = np.asarray(twin.description.home) + np.column_stack(maps)
    assert np.array_equal(angles["memory"], angles["files"])
    q_rad = np.radians(angles["memory"])
    t_s = np.linspace(0.0, 600.0, len(q_rad))
    tcp_memory = predict_tcp(memory.description, q_rad, t_s)
    tcp_files = predict_tcp(files.description, q_rad, t_s)
    assert tcp_memory.shape == (len(counts), 3) and np.isfinite(tcp_memory).all()
    assert np.array_equal(tcp_memory, tcp_files)
    # the description itself, not only its predictions, reads back as it was
    assert memory.description.dumps() == files.description.dumps()


def test_the_joint_fit_goes_on_while_the_deflection_moves_beyond_its_noise():
    """Round 1's gravity term can lend one joint another's deflection (its maps carried the
    load); the next round's differs by far more than its noise, and the maps are refitted
    once more. Within twice the standard error nothing moves."""
    import numpy as np

    from calibration.twin.fit_rounds import _deflection_moved

    old = {1: np.zeros((4, 3)), 2: np.zeros((5, 3))}
    noise = np.full(3, 1e-10)  # summed variance per joint over the 9 stops (rad²)
    within = {j: np.full_like(d, 1.9 * np.sqrt(1e-10 / 9)) for j, d in old.items()}
    assert _deflection_moved(old, within, noise) == []
    beyond = {j: d.copy() for j, d in within.items()}
    beyond[2][:, 2] = 3e-5  # joint 3 moved by 6″ at every stop of joint 2's sweep
    assert _deflection_moved(old, beyond, noise) == [3]
