"""The joint columns' names written once (edges.channel_names): the drivers name their
channels by them and every reader finds them by them, joints in numeric order."""

from __future__ import annotations

import pytest

from calibration.twin.streams import stream_kind
from drivers.grating_modbus import SCHEMA as GRATING_SCHEMA
from edges.channel_names import ENCODER, GRATING, counts_column, counts_joint, joint_columns


def test_the_grating_driver_names_its_channels_by_the_convention():
    names = [c.name for c in GRATING_SCHEMA.channels]
    assert names == [counts_column(GRATING, j) for j in range(1, len(names) + 1)]
    assert [counts_joint(n, GRATING) for n in names] == list(range(1, len(names) + 1))
    assert stream_kind(names) == "grating"


def test_the_encoder_driver_names_its_channels_by_the_convention():
    from drivers.encoder_canopen import EncoderCanopenDriver

    names = [c.name for c in EncoderCanopenDriver("socketcand://127.0.0.1:1/can0").schema.channels]
    assert names and all(counts_joint(n, ENCODER) is not None for n in names)
    assert stream_kind(names) == "encoders"


def test_joints_in_numeric_order_and_near_misses_refused():
    names = ["x_mm", "grating10_counts", "grating2_counts", "encoder1_counts", "grating1_count"]
    assert joint_columns(names, GRATING) == ["grating2_counts", "grating10_counts"]
    assert joint_columns(names, ENCODER) == ["encoder1_counts"]
    assert counts_joint("grating1_countsx") is None and counts_joint("Grating1_counts") is None
    assert counts_joint("encoder3_counts", GRATING) is None
    assert counts_joint("grating0_counts") == 0
    assert stream_kind(["grating0_counts"]) == "grating"  # joint 0 is still a grating column
    with pytest.raises(ValueError, match="unknown counts kind 'strip'"):
        counts_column("strip", 1)
