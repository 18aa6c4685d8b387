"""campaign.csv / joints.csv / points.csv: round trip, bad rows named, fuzzing."""

from __future__ import annotations

import contextlib
import string

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.errors import DataFileError
from calibration.identify.campaign_files import (
    Campaign,
    JointReadings,
    campaign_columns,
    read_campaign,
    read_joint_readings,
    read_points,
    write_campaign,
    write_joint_readings,
    write_points,
)

LIMITS = [
    (-185.0, 185.0),
    (-40.0, 110.0),
    (-120.0, 65.0),
    (-350.0, 350.0),
    (-120.0, 120.0),
    (-350.0, 350.0),
]
HEADER = ",".join(campaign_columns(6))
GOOD = "1,identify,0.5,10,20,-30,40,50,60,1000.5,-200.25,300"


def _write(tmp_path, text: str, name: str = "c.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    m = 7
    camp = Campaign(
        source="x",
        pose=tuple(f"p{i}" for i in range(m)),
        set=("identify",) * 4 + ("validate",) * 3,
        t_s=np.cumsum(rng.uniform(5, 10, m)),
        q_deg=rng.uniform(-30, 30, (m, 6)),
        xyz_mm=rng.uniform(-3000, 3000, (m, 3)),
        encoder_deg=rng.uniform(-30, 30, (m, 6)),
    )
    path = tmp_path / "campaign.csv"
    write_campaign(path, camp)
    back = read_campaign(path, 6, limits_deg=LIMITS)
    assert back.pose == camp.pose and back.set == camp.set
    assert np.allclose(back.q_deg, camp.q_deg, atol=1e-9)
    assert np.allclose(back.xyz_mm, camp.xyz_mm, atol=1e-6)
    assert np.allclose(back.encoder_deg, camp.encoder_deg, atol=1e-9)
    assert back.subset(back.mask("validate")).pose == ("p4", "p5", "p6")

    joints = JointReadings("j", camp.pose, camp.t_s, camp.q_deg)
    write_joint_readings(tmp_path / "joints.csv", joints)
    jb = read_joint_readings(tmp_path / "joints.csv", 6)
    assert np.allclose(jb.q_deg, camp.q_deg, atol=1e-9)
    write_points(tmp_path / "points.csv", camp.pose, camp.xyz_mm)
    poses, pts = read_points(tmp_path / "points.csv")
    assert poses == camp.pose and np.allclose(pts, camp.xyz_mm, atol=1e-6)


def test_extra_columns_and_blank_lines_are_ignored(tmp_path):
    text = f"\ufeff{HEADER},comment\n\n{GOOD},hello\n  \n"
    camp = read_campaign(_write(tmp_path, text), 6, limits_deg=LIMITS)
    assert camp.pose == ("1",) and camp.encoder_deg is None


@pytest.mark.parametrize(
    ("row", "needle"),
    [
        ("2,identify,0.5,nan,20,-30,40,50,60,1,2,3", "column 'q1_deg'"),
        ("2,identify,0.5,10,20,-30,40,50,60,1,abc,3", "column 'y_mm'"),
        ("2,identify,0.5,10,200,-30,40,50,60,1,2,3", "outside the joint limits"),
        ("1,identify,0.5,10,20,-30,40,50,60,1,2,3", "duplicated pose id"),
        ("2,calibrate,0.5,10,20,-30,40,50,60,1,2,3", "column 'set'"),
        ("2,identify,0.5,10,20", "fields"),
        (",identify,0.5,10,20,-30,40,50,60,1,2,3", "empty pose id"),
    ],
)
def test_bad_rows_are_named_or_skipped(tmp_path, row, needle):
    path = _write(tmp_path, f"{HEADER}\n{GOOD}\n{row}\n")
    with pytest.raises(DataFileError, match="line 3") as info:
        read_campaign(path, 6, limits_deg=LIMITS)
    assert needle in str(info.value)
    camp = read_campaign(path, 6, limits_deg=LIMITS, skip_bad=True)
    assert len(camp) == 1 and len(camp.skipped) == 1
    assert camp.skipped[0].line == 3 and needle in camp.skipped[0].reason


def test_file_level_errors(tmp_path):
    with pytest.raises(DataFileError, match="missing column"):
        read_campaign(_write(tmp_path, "pose,set,t_s\n1,identify,0\n"), 6)
    with pytest.raises(DataFileError, match="the robot has 6 joints"):
        read_campaign(_write(tmp_path, f"{HEADER},q7_deg\n{GOOD},1\n"), 6)
    with pytest.raises(DataFileError, match="encoder columns"):
        read_campaign(_write(tmp_path, f"{HEADER},e1_deg\n{GOOD},1\n"), 6)
    with pytest.raises(DataFileError, match="empty file"):
        read_campaign(_write(tmp_path, "\n\n"), 6)
    with pytest.raises(DataFileError, match="no valid data rows"):
        read_campaign(_write(tmp_path, f"{HEADER}\n"), 6)
    with pytest.raises(DataFileError, match="appears twice"):
        read_campaign(_write(tmp_path, f"{HEADER},pose\n"), 6)
    with pytest.raises(DataFileError, match="cannot read"):
        read_campaign(tmp_path / "missing.csv", 6)
    bad = tmp_path / "bin.csv"
    bad.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(DataFileError):
        read_campaign(bad, 6)


def test_joints_file_bad_rows(tmp_path):
    text = "pose,t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,x_mm\n"
    text += "a,0,1,2,3,4,5,6,99\nb,1,1,2,3,4,500,6,99\nc,2,1,2,3,4,5,6,99\n"
    path = _write(tmp_path, text, "joints.csv")
    with pytest.raises(DataFileError, match=r"line 3 \(pose 'b'\): column 'q5_deg'"):
        read_joint_readings(path, 6, limits_deg=LIMITS)
    jr = read_joint_readings(path, 6, limits_deg=LIMITS, skip_bad=True)
    assert jr.pose == ("a", "c") and len(jr.skipped) == 1


FIXTURE_OK = [HealthCheck.function_scoped_fixture]

cell = st.one_of(
    st.sampled_from(["", "nan", "inf", "-1e400", "1e5", "identify", "validate", "0", "12.5"]),
    st.text(alphabet=string.printable, max_size=8),
)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(rows=st.lists(st.lists(cell, max_size=14), max_size=6), header=st.booleans())
def test_fuzz_structured_garbage_only_raises_data_file_error(tmp_path, rows, header):
    lines = [HEADER] if header else []
    lines += [",".join(r) for r in rows]
    path = _write(tmp_path, "\n".join(lines), "fuzz.csv")
    for reader in (read_campaign, read_joint_readings):
        for skip in (False, True):
            with contextlib.suppress(DataFileError):
                reader(path, 6, limits_deg=LIMITS, skip_bad=skip)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=300))
def test_fuzz_bytes_only_raise_data_file_error(tmp_path, data):
    path = tmp_path / "bytes.csv"
    path.write_bytes(HEADER.encode() + b"\n" + data)
    for reader in (read_campaign, read_joint_readings):
        with contextlib.suppress(DataFileError):
            reader(path, 6, limits_deg=LIMITS, skip_bad=True)
    with contextlib.suppress(DataFileError):
        read_points(path)
