"""Bad input, second round, for the commands that read forces and programmed joints:
``twin compensate`` and ``twin stiffness`` (real ``twin`` processes).

The files are the emulated cell's own (tests/test_stiffness.py's fixture: a calibrated
model, a load test the emulator measured with its own compliances, targets): the cases
spoil them as a user would. Every refused case asserts exit 2, one stderr line with the
key words, no traceback, and no file changed (``tests/test_bad_input_twin.refused``).

=================  ==========================================================================
class              cases
=================  ==========================================================================
units              compensate: programmed joints in radians (also with --skip-bad), targets
                   in metres; stiffness --data: joints in radians; --load-test: joints in
                   radians, points in metres; --no-unit-check lets each through the check
column groups      targets: joints with rx_deg,ry_deg; orientation with q1..q5; a lone
                   fx_n; campaign: e1..e5 of six
load test          two loads at one pose along one axis, one pose along two axes (rank),
                   loaded and unloaded swapped, a force's sign flipped
=================  ==========================================================================
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

from tests.calibration.test_bad_input_twin import (
    campaign_rows,
    clean,
    refused,
    twin,
    work,
    write_rows,
)
from tests.calibration.test_stiffness import stiffness_files, with_stiffness

__all__ = ["clean", "stiffness_files", "work"]  # fixtures used by name

Q = [f"q{i}_deg" for i in range(1, 7)]
XYZ = ["x_mm", "y_mm", "z_mm"]
XYZ0 = ["x0_mm", "y0_mm", "z0_mm"]


@pytest.fixture
def files(stiffness_files, tmp_path) -> Path:
    """cal.toml, stiff.toml (stiffnesses stated), loads.csv, targets.csv (no force)."""
    root, cell, _ = stiffness_files
    for f in ("cal.toml", "loads.csv", "targets.csv"):
        (tmp_path / f).write_bytes((root / f).read_bytes())
    with_stiffness(cell.calibrated).save(tmp_path / "stiff.toml")
    rows = read(tmp_path / "targets.csv")
    write(tmp_path / "targets.csv", [{k: r[k] for k in ["target", *XYZ, *Q]} for r in rows])
    return tmp_path


def read(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def write(path: Path, rows: list[dict[str, str]]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def scaled(rows: list[dict[str, str]], columns: list[str], factor: float) -> list[dict[str, str]]:
    return [{k: (f"{float(v) * factor:.12g}" if k in columns else v) for k, v in r.items()}
            for r in rows]  # fmt: skip


# -- units: one check for every command that reads joints or points --------------------------
COMPENSATE = ["compensate", "--model", "stiff.toml", "--targets", "bad.csv", "--out", "j.csv"]
DATA = ["stiffness", "--model", "stiff.toml", "--data", "bad.csv"]
LOAD_TEST = ["stiffness", "--model", "cal.toml", "--load-test", "bad.csv", "--out-model", "m.toml"]


@pytest.mark.parametrize(
    ("source", "columns", "factor", "command", "words"),
    [
        ("targets.csv", Q, math.pi / 180, COMPENSATE, ["bad.csv", "radians", "--no-unit-check"]),
        ("targets.csv", Q, math.pi / 180, [*COMPENSATE, "--skip-bad"], ["bad.csv", "radians"]),
        ("targets.csv", XYZ, 1e-3, COMPENSATE, ["bad.csv", "x_mm", "metres", "--no-unit-check"]),
        ("targets.csv", Q, math.pi / 180, DATA, ["bad.csv", "q1_deg", "--no-unit-check"]),
        ("loads.csv", Q, math.pi / 180, LOAD_TEST, ["bad.csv", "radians", "--no-unit-check"]),
        ("loads.csv", XYZ + XYZ0, 1e-3, LOAD_TEST, ["bad.csv", "metres", "--no-unit-check"]),
    ],
)  # fmt: skip
def test_joints_and_points_in_other_units_are_refused(
    files, source, columns, factor, command, words
):
    write(files / "bad.csv", scaled(read(files / source), columns, factor))
    refused(files, command, *words)


def test_no_unit_check_lets_radians_through_the_check(files):
    write(files / "bad.csv", scaled(read(files / "targets.csv"), Q, math.pi / 180))
    proc = twin(files, *DATA, "--no-unit-check")
    assert proc.returncode == 0, proc.stderr
    assert "radians" not in proc.stderr


def test_the_clean_files_pass_the_units_check(files):
    proc = twin(files, "compensate", "--model", "stiff.toml", "--targets", "targets.csv",
                "--out", "j.csv")  # fmt: skip
    assert proc.returncode == 0, proc.stderr


# -- one rule for every optional column group ------------------------------------------------
def _targets_with(files: Path, keep: list[str], add: dict[str, str]) -> None:
    rows = read(files / "targets.csv")
    write(files / "bad.csv", [{**{k: r[k] for k in keep}, **add} for r in rows])


@pytest.mark.parametrize(
    ("keep", "add", "words"),
    [
        (["target", *XYZ, *Q], {"rx_deg": "0", "ry_deg": "0"}, ["bad.csv", "rz_deg", "rx_deg"]),
        (["target", *XYZ, *Q[:5]], {"rx_deg": "0", "ry_deg": "0", "rz_deg": "0"},
         ["bad.csv", "q6_deg", "missing"]),
        (["target", *XYZ, *Q], {"fx_n": "10"}, ["bad.csv", "fy_n", "fz_n", "missing"]),
        (["target", *XYZ, *Q], {"fx_n": "10", "fz_n": "0"}, ["bad.csv", "fy_n", "missing"]),
    ],
)  # fmt: skip
def test_a_partial_column_group_in_targets_is_refused(files, keep, add, words):
    _targets_with(files, keep, add)
    refused(files, COMPENSATE, *words)


def test_a_partial_encoder_group_in_a_campaign_is_refused(work):
    rows = campaign_rows(work)
    assert "e6_deg" in rows[0]  # the emulated campaign has every motor encoder
    k = rows[0].index("e6_deg")
    write_rows(work / "bad.csv", [[v for i, v in enumerate(r) if i != k] for r in rows])
    refused(work, ["identify", "--robot", "kr500", "--data", "bad.csv", "--out", "o.toml",
                   "--no-effects", "--quiet"], "bad.csv", "e6_deg", "missing")  # fmt: skip


# -- a load test that cannot determine the stiffnesses, or that the physics forbids -----------
def _loads_subset(files: Path, keep: list[int], *, one_unloaded: bool = False) -> None:
    """The rows ``keep`` of loads.csv; ``one_unloaded``: every row of a pose with the first
    row's unloaded point (the TCP measured once unloaded per pose)."""
    rows = [read(files / "loads.csv")[i] for i in keep]
    if one_unloaded:
        rows = [{**r, **{c: rows[0][c] for c in XYZ0}} for r in rows]
    write(files / "bad.csv", rows)


@pytest.mark.parametrize(
    ("keep", "one_unloaded", "words"),
    [
        ([2, 5], False, ["bad.csv", "rank", "1 distinct pose", "1 distinct axis", "joint"]),
        ([2, 5], True, ["bad.csv", "rank", "1 distinct pose", "1 distinct axis", "joint"]),
        ([0, 2, 3, 5], False, ["bad.csv", "rank", "2 distinct axis", "other"]),
    ],
)
def test_a_load_test_that_cannot_determine_the_stiffnesses_is_refused(
    files, keep, one_unloaded, words
):
    """±z at one pose: 3 equations for the loaded joints' compliances (the fit used to say
    ± 0.0 % and write them); ±x and ±z at one pose: still not all of them. One unloaded
    reading for the pose is what a user measures: not taken for a unit slip."""
    _loads_subset(files, keep, one_unloaded=one_unloaded)
    refused(files, LOAD_TEST, *words)


@pytest.mark.parametrize("spoil", ["swap", "flip"])
def test_deflections_against_their_forces_are_questioned(files, spoil):
    rows = read(files / "loads.csv")
    if spoil == "swap":  # loaded and unloaded exchanged
        rows = [{**r, **{a: r[b] for a, b in zip(XYZ + XYZ0, XYZ0 + XYZ, strict=True)}}
                for r in rows]  # fmt: skip
        words = ["bad.csv", "against their forces", "swapped"]
    else:  # every force's sign flipped
        rows = scaled(rows, ["fx_n", "fy_n", "fz_n"], -1.0)
        words = ["bad.csv", "against their forces", "sign"]
    write(files / "bad.csv", rows)
    refused(files, LOAD_TEST, *words)


def test_deflections_lost_in_the_trackers_noise_are_not_taken_for_a_swap():
    """A robot too stiff for the test: deflections that are tracker noise (10 µm) point
    against their forces about half the time; only a mean beyond its noise is refused."""
    import numpy as np

    from calibration.errors import StiffnessError
    from calibration.model.stiffness import _check_deflection_signs

    f = np.tile(np.vstack([np.eye(3), -np.eye(3)]) * 1000.0, (8, 1))
    for seed in range(20):
        noise = np.random.default_rng(seed).normal(0.0, 0.01, (48, 3))
        _check_deflection_signs(f, noise)  # not refused
        with pytest.raises(StiffnessError, match="against their forces"):
            _check_deflection_signs(f, noise - 0.02 * f / 1000.0)  # 20 µm against each force
