"""Scale-calibration files: CSV readers (errors name file, row and column), scale.toml, fuzz."""

from __future__ import annotations

import contextlib
import tempfile
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.errors import CalibrationError, DataFileError
from calibration.model.description import load_robot
from calibration.scales.grating_scale import calibrate_joint
from calibration.scales.scale_files import (
    ScaleFileError,
    read_counts_csv,
    read_home_csv,
    read_scale_toml,
    read_sweep_csv,
    scale_document,
    write_scale_toml,
)
from calibration.scales.sweep_inputs import JointSweep
from sim_devices.scale_campaign import CampaignOptions, run_campaign
from sim_devices.truth import TrueCell

SWEEP_HEADER = "joint,pass,step,counts,x_mm,y_mm,z_mm"


def sweep_text(n: int = 8, joint: int = 1) -> str:
    """A small, valid sweep: n stops per pass on a 500 mm circle."""
    lines = [SWEEP_HEADER]
    for p, sign in (("forward", -1), ("backward", 1)):
        for k in range(n):
            a = np.radians(10.0 - sign * (2.0 * k) if p == "forward" else -4.0 + 2.0 * k)
            lines.append(
                f"{joint},{p},{k},{1000 + int(8727 * np.degrees(a))},"
                f"{500 * np.cos(a):.4f},{500 * np.sin(a):.4f},100.0"
            )
    return "\n".join(lines) + "\n"


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def replace_field(text: str, line: int, column: int, value: str) -> str:
    lines = text.splitlines()
    fields = lines[line - 1].split(",")
    fields[column] = value
    lines[line - 1] = ",".join(fields)
    return "\n".join(lines) + "\n"


# -- sweep.csv -----------------------------------------------------------------------------------
def test_reading_a_valid_sweep(tmp_path):
    text = sweep_text(8).replace("\n", "\r\n")
    path = write(tmp_path, "sweep.csv", "\ufeff" + text)  # BOM and CRLF are fine
    table = read_sweep_csv(path, n_joints=6)
    js = table.joints[1]
    assert js.n_stops == 16
    assert set(js.pass_name) == {"forward", "backward"}
    assert js.rows.min() == 2 and js.rows.max() == 17
    assert js.points_mm.shape == (16, 3)


@pytest.mark.parametrize(
    ("header", "column", "message"),
    [
        ("joint,pass,step,counts,x_mm,y_mm", "z_mm", "missing"),
        ("joint,pass,step,counts,x_mm,y_mm,z_m", "z_mm", "missing"),
        ("joint,pass,step,counts,x_mm,y_mm,z_mm,temp_c", "temp_c", "unknown column"),
        ("joint,pass,step,counts,x_mm,x_mm,z_mm", "x_mm", "twice"),
    ],
)
def test_sweep_header_errors_name_file_row_and_column(tmp_path, header, column, message):
    body = sweep_text(8).split("\n", 1)[1]
    path = write(tmp_path, "sweep.csv", header + "\n" + body)
    with pytest.raises(DataFileError) as err:
        read_sweep_csv(path)
    text = str(err.value)
    assert str(path) in text and "row 1" in text and f"column '{column}'" in text
    assert message in text


@pytest.mark.parametrize(
    ("line", "column", "value", "message"),
    [
        (5, 4, "nan", "finite"),
        (5, 5, "NaN", "finite"),
        (6, 6, "abc", "expected a number"),
        (3, 3, "12.5", "expected an integer"),
        (3, 3, "nan", "NaN"),
        (3, 3, "99999999999", "32-bit"),
        (4, 1, "sideways", "expected one of forward, backward"),
        (4, 0, "7", "unknown joint 7"),
        (4, 0, "0", "unknown joint 0"),
        (4, 2, "-1", "must be ≥ 0"),
        (4, 2, "0", "already given in row 2"),
    ],
)
def test_sweep_value_errors_name_file_row_and_column(tmp_path, line, column, value, message):
    text = replace_field(sweep_text(8), line, column, value)
    path = write(tmp_path, "sweep.csv", text)
    with pytest.raises(DataFileError) as err:
        read_sweep_csv(path, n_joints=6)
    name = SWEEP_HEADER.split(",")[column]
    assert f"{path}: row {line}, column '{name}' ({column + 1})" in str(err.value)
    assert message in str(err.value)


def test_sweep_structure_errors(tmp_path):
    path = write(tmp_path, "s.csv", "")
    with pytest.raises(DataFileError, match="row 1: empty file"):
        read_sweep_csv(path)
    path = write(tmp_path, "s.csv", SWEEP_HEADER + "\n")
    with pytest.raises(DataFileError, match="row 2: no data rows"):
        read_sweep_csv(path)
    path = write(tmp_path, "s.csv", sweep_text(8).replace("1,forward,3,", "1,forward,3,5,", 1))
    with pytest.raises(DataFileError, match="row 5: expected 7 fields, got 8"):
        read_sweep_csv(path)
    path = write(tmp_path, "s.csv", sweep_text(4))
    with pytest.raises(DataFileError) as err:
        read_sweep_csv(path)
    assert "rows 2-5, column 'step'" in str(err.value) and "4 stops" in str(err.value)
    path = write(tmp_path, "s.csv", b"joint,pass\n\xff\xfe\x00")
    with pytest.raises(DataFileError, match="not UTF-8"):
        read_sweep_csv(path)
    with pytest.raises(DataFileError, match="cannot read"):
        read_sweep_csv(tmp_path / "missing.csv")


# -- home.csv and counts.csv ---------------------------------------------------------------------
def test_home_reader(tmp_path):
    path = write(tmp_path, "home.csv", "joint,trial,counts\n1,1,5\n1,2,4294967295\n3,1,-1\n")
    home = read_home_csv(path, n_joints=6)
    assert home.counts[1].tolist() == [5, 4294967295]
    assert home.counts[3].tolist() == [4294967295]  # signed 32-bit reading, wrapped
    assert home.rows[3].tolist() == [4]
    assert read_home_csv(write(tmp_path, "h.csv", "joint,trial,counts\n")).counts == {}
    bad = write(tmp_path, "h.csv", "joint,trial,counts\n1,1,5\n1,1,6\n")
    with pytest.raises(DataFileError, match=r"row 3, column 'trial' \(2\): .*row 2"):
        read_home_csv(bad)
    bad = write(tmp_path, "h.csv", "joint,trial,counts\n1,1,NaN\n")
    with pytest.raises(DataFileError, match=r"row 2, column 'counts' \(3\): .*NaN"):
        read_home_csv(bad)
    bad = write(tmp_path, "h.csv", "joint,trial\n1,1\n")
    with pytest.raises(DataFileError, match="row 1, column 'counts': missing"):
        read_home_csv(bad)


def test_counts_reader_keeps_extra_columns_and_reads_directions(tmp_path):
    text = "t_s,joint,counts,direction,note\n0.1,1,100,positive,a\n0.2,2,-5,,b\n0.3,1,7,forward,c\n"
    table = read_counts_csv(write(tmp_path, "c.csv", text))
    assert table.header == ["t_s", "joint", "counts", "direction", "note"]
    assert table.rows[1] == ["0.2", "2", "-5", "", "b"]
    assert table.counts.tolist() == [100, 2**32 - 5, 7]
    assert table.direction.tolist() == [1.0, 0.0, -1.0]
    bad = write(tmp_path, "c.csv", "joint,counts,direction\n1,5,sideways\n")
    with pytest.raises(DataFileError, match=r"row 2, column 'direction' \(3\)"):
        read_counts_csv(bad)
    assert read_counts_csv(write(tmp_path, "c.csv", "joint,counts\n1,5\n")).direction is None


# -- scale.toml ----------------------------------------------------------------------------------
@cache
def calibrated():
    desc = load_robot("kr500")
    cell = TrueCell.create(desc, 2, eccentricity_mm=0.02)
    camp = run_campaign(cell, CampaignOptions(joints=(1, 6), hysteresis_counts=8.0))
    results = []
    for j in (1, 6):
        m = camp.sweep_joint == j
        sweep = JointSweep(
            j,
            camp.sweep_pass[m],
            camp.sweep_step[m],
            camp.sweep_counts[m],
            camp.sweep_points_mm[m],
        )
        jd = desc.joints[j - 1]
        results.append(
            calibrate_joint(
                sweep,
                camp.home_counts[camp.home_joint == j],
                home_deg=0.0,
                limits_deg=(jd.lower_deg, jd.upper_deg),
            )
        )
    return camp, results


def test_scale_toml_round_trip(tmp_path):
    camp, results = calibrated()
    path = tmp_path / "scale.toml"
    write_scale_toml(path, scale_document(results, robot="KR500", metadata={"alpha": 0.01}))
    cal = read_scale_toml(path)
    assert cal.robot == "KR500" and cal.metadata["alpha"] == 0.01
    for r in results:
        s = cal.scale(r.joint)
        assert s.terms == r.scale.terms
        assert set(s.unmodelled) == set(r.scale.unmodelled)
        c = camp.sweep_counts[camp.sweep_joint == r.joint]
        for d in (None, 1.0, -1.0):
            np.testing.assert_allclose(
                s.counts_to_angle_deg(c, d), r.scale.counts_to_angle_deg(c, d), atol=1e-12
            )
            np.testing.assert_allclose(
                s.angle_std_deg(c, d), r.scale.angle_std_deg(c, d), rtol=1e-9
            )
    with pytest.raises(ScaleFileError, match="joint 3 is not calibrated"):
        cal.scale(3)
    angles = cal.angles_deg(np.array([1, 6, 1]), np.array([5, 6, 7]))
    assert angles.shape == (3,)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ('format = "twin-grating-scale/1"', 'format = "other"', "top level: key 'format'"),
        ("zero_counts = ", "zero_count = ", "[[joint]] #1: key 'zero_counts': missing"),
        ("scale_deg_per_count = ", "scale_deg_per_count = 'x' #", "coefficients"),
        ('terms = [\n    "cyclic",', 'terms = [\n    "wobble",', "key 'terms'"),
        ("deg2 = [", "deg2 = [[1.0], ", "key 'deg2'"),
    ],
)
def test_scale_toml_errors_name_file_table_and_key(tmp_path, old, new, message):
    _, results = calibrated()
    path = tmp_path / "scale.toml"
    write_scale_toml(path, scale_document(results))
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ScaleFileError) as err:
        read_scale_toml(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_scale_toml_not_toml(tmp_path):
    path = write(tmp_path, "scale.toml", "this is = = not toml")
    with pytest.raises(ScaleFileError, match="not valid TOML"):
        read_scale_toml(path)


# -- fuzz ----------------------------------------------------------------------------------------
CSV_CHARS = "0123456789,.-+e\n\r\"' abnNiIfxyz_"
CSV_FIELD = st.one_of(
    st.text(CSV_CHARS, max_size=12),
    st.sampled_from(["forward", "backward", "nan", "inf", "1e400", "-1", "4294967296", ""]),
)
CSV_LINE = st.lists(CSV_FIELD, max_size=9).map(",".join)
FUZZ_SETTINGS = settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


def _fuzz_file(data: bytes) -> Path:
    fd, name = tempfile.mkstemp(suffix=".csv")
    with open(fd, "wb") as fh:
        fh.write(data)
    return Path(name)


def _only_data_file_errors(data: bytes) -> None:
    path = _fuzz_file(data)
    try:
        for reader in (
            lambda p: read_sweep_csv(p, n_joints=6),
            lambda p: read_home_csv(p, n_joints=6),
            read_counts_csv,
        ):
            with contextlib.suppress(DataFileError):
                reader(path)
    finally:
        path.unlink()


@FUZZ_SETTINGS
@given(st.binary(max_size=300))
def test_fuzz_csv_readers_with_bytes(data):
    _only_data_file_errors(data)


@FUZZ_SETTINGS
@given(
    st.sampled_from([SWEEP_HEADER, "joint,trial,counts", "joint,counts,direction", ""]),
    st.lists(CSV_LINE, max_size=20),
)
def test_fuzz_csv_readers_with_csv_like_text(header, lines):
    _only_data_file_errors((header + "\n" + "\n".join(lines)).encode())


@FUZZ_SETTINGS
@given(st.integers(0, 16), st.integers(0, 6), CSV_FIELD)
def test_fuzz_one_field_of_a_valid_sweep(line, column, value):
    text = sweep_text(8)
    if line >= 1:
        text = replace_field(text, line, column, value)
    path = _fuzz_file(text.encode())
    try:
        read_sweep_csv(path, n_joints=6)
    except DataFileError as exc:
        assert str(path) in str(exc)
    except CalibrationError as exc:  # pragma: no cover - must not happen
        pytest.fail(f"not a DataFileError: {exc!r}")
    finally:
        path.unlink()
