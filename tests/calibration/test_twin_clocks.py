"""The twin refuses to pair streams stamped by host clocks that disagree (the devices'
``host_clock`` in their health, docs/deployment.md "Clocks"), and pairs those of one
clock however far it is from the router's.

The recordings are tests/data/campaign_small.mcap (a real ``daq run`` of the emulated
cell, see tests/calibration/test_twin_replay.py) copied with each device's health
documents given a ``host_clock``, as a daemon that is a client of routers writes them.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from calibration.errors import StreamError
from calibration.twin.streams import host_clock_of, read_recording_streams
from daq.recording_reader import read_recording
from daq.recording_writer import McapRecorder

DATA = Path(__file__).parents[1] / "data" / "campaign_small.mcap"

pytestmark = pytest.mark.skipif(not DATA.exists(), reason="tests/data/campaign_small.mcap missing")


def _with_clocks(out: Path, offsets_ms: dict[str, float]) -> Path:
    """DATA copied to ``out``, each health document of device ``d`` with a ``host_clock``
    of ``offsets_ms[d]`` (± 0.4 ms)."""
    with McapRecorder(out) as rec:
        ids: dict[str, int] = {}
        for m in read_recording(DATA).messages_iter():
            cid = ids.get(m.topic)
            if cid is None:
                assert m.schema is not None
                cid = ids[m.topic] = rec.add_channel(
                    m.topic,
                    schema_name=m.schema.name,
                    schema_encoding=m.schema.encoding,
                    schema_data=m.schema.data,
                    message_encoding=m.channel.message_encoding,
                    metadata=m.channel.metadata,
                )
            data = m.data
            if m.topic.endswith("/health"):
                doc = json.loads(data)
                offset = offsets_ms[doc["device"]]
                doc["host_clock"] = {"offset_ms": offset, "uncertainty_ms": 0.4, "rtt_ms": 0.8}
                data = json.dumps(doc).encode()
            rec.write(cid, data, m.log_time, m.publish_time, m.sequence)
    return out


def test_streams_of_hosts_half_a_second_apart_are_refused_saying_why(tmp_path):
    path = _with_clocks(tmp_path / "apart.mcap", {"tracker": 500.0, "grating": 0.2})
    with pytest.raises(StreamError) as err:
        read_recording_streams(path)
    said = str(err.value)
    assert "the grating (grating) and the tracker (tracker)" in said, said
    assert "499.8 ms apart" in said and "+500.0 ± 0.4" in said and "NTP/PTP" in said, said


def test_one_clock_off_for_both_is_paired_and_small_differences_pass(tmp_path):
    for name, tracker, grating in (("same", 500.0, 500.0), ("near", 3.0, -6.0)):
        path = _with_clocks(tmp_path / f"{name}.mcap", {"tracker": tracker, "grating": grating})
        streams = read_recording_streams(path)  # no refusal
        assert len(streams.tracker) > 0 and len(streams.grating) > 0


def test_a_health_document_without_a_usable_clock_is_not_compared():
    assert host_clock_of(b'{"host_clock": {"offset_ms": 1.5, "uncertainty_ms": 0.2}}') == {
        "offset_ms": 1.5,
        "uncertainty_ms": 0.2,
    }
    for data in (b"[]", b"not json", b'{"host_clock": {"offset_ms": "x"}}', b'{"a": 1}',
                 b'{"host_clock": {"offset_ms": true, "uncertainty_ms": 0}}'):  # fmt: skip
        assert host_clock_of(data) is None, data
