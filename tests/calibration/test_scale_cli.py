"""``twin scale`` and ``twin scale-apply`` as subprocesses on generated campaign files."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.cli import main as cli_main
from calibration.model.description import load_robot
from calibration.scales.scale_files import read_scale_toml
from sim_devices.scale_campaign import CampaignOptions, run_campaign
from sim_devices.truth import TrueCell

SEED = 4
ECC_MM = 0.03
HYSTERESIS = 8.0


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, timeout=120, cwd=cwd
    )


def twin(*args: str) -> subprocess.CompletedProcess:
    return run("-m", "calibration.cli", *args)


def twin_here(capsys, *args: str) -> tuple[int, str]:
    """The same command line in this process (error cases: no interpreter start-up)."""
    code = cli_main(list(args))
    return code, capsys.readouterr().err


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scale")
    done = run(
        "-m", "sim_devices.scale_campaign", "--robot", "kr500", "--seed", str(SEED),
        "--out", str(out), "--eccentricity-mm", str(ECC_MM),
        "--hysteresis-counts", str(HYSTERESIS), "--no-home", "5",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert {p.name for p in out.iterdir()} >= {"home.csv", "sweep.csv", "truth.toml"}
    return out


@pytest.fixture(scope="module")
def calibrated(files) -> Path:
    done = twin(
        "scale", "--sweep", str(files / "sweep.csv"), "--home", str(files / "home.csv"),
        "--out", str(files / "scale.toml"), "--report", str(files / "report"),
        "--robot", "kr500",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "joint 5: no Home returns" in done.stdout
    return files / "scale.toml"


def test_scale_writes_a_calibration_that_matches_the_truth(files, calibrated):
    cal = read_scale_toml(calibrated)
    assert sorted(cal.joints) == [1, 2, 3, 4, 5, 6]
    cell = TrueCell.create(load_robot("kr500"), SEED, eccentricity_mm=ECC_MM)
    camp = run_campaign(
        cell, CampaignOptions(hysteresis_counts=HYSTERESIS, joints_without_home=(5,))
    )
    text = (files / "sweep.csv").read_text()
    assert text == camp.sweep_csv()  # the same campaign as the files
    for j, scale in cal.joints.items():
        counts = camp.sweep_counts[camp.sweep_joint == j]
        err = scale.counts_to_angle_deg(counts) - camp.truth(j).angle_deg(counts)
        assert np.abs(err / scale.angle_std_deg(counts)).max() < 4.5
        assert scale.home_deg == 0.0
    assert "cyclic" in cal.joints[1].terms and "hysteresis" in cal.joints[6].terms


def test_report_files(files, calibrated):
    report = files / "report"
    doc = json.loads((report / "report.json").read_text())
    rows = {r["joint"]: r for r in doc["joints"]}
    assert sorted(rows) == [1, 2, 3, 4, 5, 6]
    assert rows[5]["zero_source"] == "sweep-crossing" and rows[5]["notes"]
    for r in rows.values():
        assert r["residual_rms_arcsec"] == pytest.approx(r["residual_rms_deg"] * 3600)
        assert len(r["circle"]["normal"]) == 3 and r["circle"]["radius_mm"] > 100
        assert {t["term"] for t in r["tests"]} == {"cyclic", "hysteresis", "nonlinear"}
    md = (report / "report.md").read_text()
    assert md.count("\n| 6 |") >= 2 and "Term selection" in md
    assert (report / "residuals.png").read_bytes()[:4] == b"\x89PNG"


def test_scale_apply_adds_angles_and_passes_columns_through(files, calibrated):
    cal = read_scale_toml(calibrated)
    rows = [
        ["t_s", "joint", "counts", "direction", "note"],
        ["0.0", "1", str(round(cal.joints[1].zero_counts)), "", "home"],
        ["0.1", "6", str(round(cal.joints[6].zero_counts) + 5000), "positive", "x"],
        ["0.2", "6", str(round(cal.joints[6].zero_counts) + 5000), "negative", "y"],
    ]
    data = files / "counts.csv"
    with data.open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)
    out = files / "angles.csv"
    done = twin(
        "scale-apply", "--scale", str(calibrated), "--data", str(data), "--out", str(out),
        "--joint-angle", "--std",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    with out.open() as fh:
        got = list(csv.reader(fh))
    assert got[0] == [*rows[0], "angle_deg", "q_deg", "angle_std_deg"]
    assert [r[:5] for r in got[1:]] == rows[1:]
    angles = [float(r[5]) for r in got[1:]]
    assert abs(angles[0]) < 1e-4
    s6 = cal.joints[6]
    for k, d in ((1, 1.0), (2, -1.0)):
        assert angles[k] == pytest.approx(float(s6.counts_to_angle_deg(int(rows[k + 1][2]), d)))
    # the hysteresis kept on joint 6 separates the two directions by about 8 counts
    assert (angles[1] - angles[2]) / s6.scale_deg_per_count == pytest.approx(-8.0, abs=2.5)


def write_sweep(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def edited_sweep(files: Path, line: int, column: str, value: str) -> str:
    lines = (files / "sweep.csv").read_text().splitlines()
    header = lines[0].split(",")
    fields = lines[line - 1].split(",")
    fields[header.index(column)] = value
    lines[line - 1] = ",".join(fields)
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (("header", "x_m"), "row 1, column 'x_mm'"),
        ((5, "x_mm", "nan"), "row 5, column 'x_mm' (5): must be finite"),
        ((9, "joint", "7"), "row 9, column 'joint' (1): unknown joint 7"),
        ((12, "counts", "1.5e3"), "row 12, column 'counts' (4): expected an integer"),
    ],
)
def test_scale_errors_name_file_row_and_column(files, tmp_path, capsys, edit, expected):
    if edit[0] == "header":
        text = (files / "sweep.csv").read_text().replace("x_mm", edit[1], 1)
    else:
        text = edited_sweep(files, *edit)
    sweep = write_sweep(tmp_path / "bad.csv", text)
    args = ("scale", "--sweep", str(sweep), "--home", str(files / "home.csv"),
            "--out", str(tmp_path / "s.toml"), "--robot", "kr500")  # fmt: skip
    if edit[0] == "header":  # one of them as a real subprocess
        done = twin(*args)
        code, err = done.returncode, done.stderr
    else:
        code, err = twin_here(capsys, *args)
    assert code == 2
    assert f"twin scale: error: {sweep}: {expected}" in err
    assert not (tmp_path / "s.toml").exists()


def test_scale_error_too_few_stops(files, tmp_path, capsys):
    lines = (files / "sweep.csv").read_text().splitlines()
    keep = [lines[0]] + [ln for ln in lines[1:] if not ln.startswith("2,")]
    keep += [ln for ln in lines[1:] if ln.startswith("2,forward,")][:3]
    keep += [ln for ln in lines[1:] if ln.startswith("2,backward,")]
    sweep = write_sweep(tmp_path / "few.csv", "\n".join(keep) + "\n")
    first = keep.index(next(ln for ln in keep if ln.startswith("2,forward,"))) + 1
    code, err = twin_here(capsys, "scale", "--sweep", str(sweep), "--home",
                          str(files / "home.csv"), "--out", str(tmp_path / "s.toml"))  # fmt: skip
    assert code == 2
    assert (
        f"{sweep}: rows {first}-{first + 2}, column 'step' (3): joint 2 forward sweep "
        "has 3 stops" in err
    )


def test_scale_errors_between_files(files, tmp_path, capsys):
    lines = (files / "sweep.csv").read_text().splitlines()
    only_1 = write_sweep(
        tmp_path / "j1.csv", "\n".join([lines[0]] + [ln for ln in lines if ln.startswith("1,")])
    )
    code, err = twin_here(capsys, "scale", "--sweep", str(only_1), "--home",
                          str(files / "home.csv"), "--out", str(tmp_path / "s.toml"))  # fmt: skip
    assert code == 2
    assert f"{files / 'home.csv'}: row 12, column 'joint': joint 2 has Home rows" in err
    # a joint without Home rows needs the robot description for its nominal Home
    code, err = twin_here(capsys, "scale", "--sweep", str(files / "sweep.csv"), "--home",
                          str(files / "home.csv"), "--out", str(tmp_path / "s.toml"))  # fmt: skip
    assert code == 2
    assert "joint 5: no Home returns" in err and "robot description" in err


def test_scale_apply_errors(files, calibrated, tmp_path, capsys):
    data = tmp_path / "c.csv"
    args = ("scale-apply", "--scale", str(calibrated), "--data", str(data),
            "--out", str(tmp_path / "a.csv"))  # fmt: skip
    data.write_text("joint,counts\n1,5\n9,7\n")
    done = twin(*args)
    assert done.returncode == 2
    assert f"twin scale-apply: error: {data}: row 3, column 'joint': joint 9 is not in" in (
        done.stderr
    )
    data.write_text("joint,count\n1,5\n")
    code, err = twin_here(capsys, *args)
    assert code == 2 and "row 1, column 'counts': missing" in err
    data.write_text("joint,counts\n1,NaN\n")
    code, err = twin_here(capsys, *args)
    assert code == 2 and "row 2, column 'counts' (2): expected an integer, got NaN" in err
    assert not (tmp_path / "a.csv").exists()
