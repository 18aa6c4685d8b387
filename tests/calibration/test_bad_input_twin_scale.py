"""Bad input to ``twin scale`` and ``twin scale-apply`` (real ``twin`` processes), and
their readers fuzzed (in process, hypothesis).

Every refused case asserts exit status 2, one stderr line naming the file and the
row/column, TOML table/key or option, no traceback, and every file in the working
directory byte for byte as before. Accepted look-alikes (BOM, CRLF, shuffled columns)
must give the clean file's numbers.

==============  ==============================================================================
category        cases
==============  ==============================================================================
sweep.csv       empty, header only, NaN, inf, text, duplicated stop, missing column, unknown
                column, short row, unknown pass, non-UTF-8, NUL bytes, metres, /dev/zero,
                over the size limit, a directory
home.csv        empty, header only, NaN counts, joint without a sweep
counts.csv      empty, header only, NaN, unknown joint, bad direction, counts far outside the
                calibrated angles (and the override), counts beyond 32 bits
scale.toml      binary, syntax, wrong format, NaN coefficient, missing coefficient, joint
                twice, bad calibrated range
options         --alpha 0/1, --counts-per-mm 0/nan, --step-deg -2, --tracker-mpe-um inf,
                --terms bogus
outputs         --out = --sweep, --out = --home, scale-apply --out = --data / = --scale,
                --out a directory, --report a file, --out below a file
accepted        BOM, CRLF, shuffled columns
==============  ==============================================================================
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings

from calibration.cli import main as twin_main
from calibration.errors import CalibrationError
from calibration.scales.scale_files import (
    read_counts_csv,
    read_home_csv,
    read_scale_toml,
    read_sweep_csv,
)
from tests.bad_input import assert_refusal, refuse_moves_into, snapshot
from tests.calibration.test_bad_input_twin import _mutations, refused, twin

SCALE = ["scale", "--sweep", "sweep.csv", "--home", "home.csv", "--out", "out.toml"]
APPLY = ["scale-apply", "--scale", "scale.toml", "--out", "angles.csv"]


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """home.csv, sweep.csv (joints 1 and 2 of the kr500, 60° arcs), scale.toml,
    counts.csv (joint,counts of the sweep stops)."""
    root = tmp_path_factory.mktemp("scale-clean")
    made = subprocess.run(
        [sys.executable, "-m", "sim_devices.scale_campaign", "--robot", "kr500", "--seed",
         "7", "--out", str(root), "--joints", "1,2", "--arc-deg", "60"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    (root / "truth.toml").unlink()
    done = twin(root, "scale", "--sweep", "sweep.csv", "--home", "home.csv", "--out",
                "scale.toml")  # fmt: skip
    assert done.returncode == 0, done.stderr
    rows = [line.split(",") for line in (root / "sweep.csv").read_text().splitlines()]
    j, c = rows[0].index("joint"), rows[0].index("counts")
    (root / "counts.csv").write_text(
        "joint,counts,note\n" + "".join(f"{r[j]},{r[c]},x\n" for r in rows[1:40])
    )
    return root


@pytest.fixture
def work(clean, tmp_path) -> Path:
    for f in clean.iterdir():
        shutil.copy(f, tmp_path / f.name)
    return tmp_path


def rows_of(path: Path) -> list[list[str]]:
    return [line.split(",") for line in path.read_text().splitlines()]


def write_rows(path: Path, rows: list[list[str]]) -> None:
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")


def _set(rows, line, name, value):
    rows[line - 1][rows[0].index(name)] = value
    return rows


def _drop(rows, name):
    k = rows[0].index(name)
    return [[v for i, v in enumerate(r) if i != k] for r in rows]


def _metres(rows):
    ks = {rows[0].index(c) for c in ("x_mm", "y_mm", "z_mm")}
    return [rows[0]] + [
        [f"{float(v) / 1000:.9f}" if k in ks else v for k, v in enumerate(r)] for r in rows[1:]
    ]


# -- sweep.csv ----------------------------------------------------------------------------------
SWEEP_CASES = {
    "empty": (lambda r: [], ["bad.csv", "empty"]),
    "header only": (lambda r: r[:1], ["bad.csv", "no data rows"]),
    "nan": (lambda r: _set(r, 5, "x_mm", "nan"), ["bad.csv", "row 5", "x_mm", "finite"]),
    "inf": (lambda r: _set(r, 6, "z_mm", "-inf"), ["row 6", "z_mm"]),
    "text": (lambda r: _set(r, 7, "counts", "12k"), ["row 7", "counts"]),
    "duplicated stop": (lambda r: [*r[:4], r[3], *r[4:]], ["bad.csv", "row 5"]),
    "missing column": (lambda r: _drop(r, "pass"), ["bad.csv", "pass", "missing"]),
    "unknown column": (
        lambda r: [[*x, "colour" if i == 0 else "red"] for i, x in enumerate(r)],
        ["colour", "unknown column"],
    ),
    "short row": (lambda r: [*r[:8], r[8][:3], *r[9:]], ["row 9", "fields"]),
    "unknown pass": (lambda r: _set(r, 4, "pass", "sideways"), ["row 4", "pass", "sideways"]),
    "metres": (_metres, ["bad.csv", "x_mm", "metres", "--no-unit-check"]),
}


@pytest.mark.parametrize("case", list(SWEEP_CASES))
def test_scale_refuses_a_broken_sweep(work, case):
    mutate, keywords = SWEEP_CASES[case]
    write_rows(work / "bad.csv", mutate(rows_of(work / "sweep.csv")))
    (work / "out.toml").write_text("an earlier output\n")  # must survive a failed run
    refused(work, ["scale", "--sweep", "bad.csv", "--home", "home.csv", "--out", "out.toml"],
            *keywords)  # fmt: skip


def test_scale_refuses_undecodable_endless_and_huge_sweeps(work):
    raw = (work / "sweep.csv").read_bytes().splitlines(keepends=True)
    (work / "bad.csv").write_bytes(b"".join([*raw[:5], b"1,\xff\xfe,3\n", *raw[5:]]))
    base = ["scale", "--home", "home.csv", "--out", "out.toml", "--sweep"]
    refused(work, [*base, "bad.csv"], "bad.csv", "row 6", "utf-8")
    (work / "bad.csv").write_bytes(b"".join([*raw[:3], b"\x00\x00\n", *raw[3:]]))
    refused(work, [*base, "bad.csv"], "bad.csv", "NUL")
    refused(work, [*base, "/dev/zero"], "/dev/zero", "device")
    refused(work, [*base, "."], "directory")
    refused(work, [*base, "sweep.csv"], "sweep.csv", "limit",
            env={"GRATING_TWIN_MAX_INPUT_MB": "0.001"})  # fmt: skip


HOME_CASES = {
    "empty": (lambda r: [], ["bad.csv", "empty"]),
    "nan": (lambda r: _set(r, 3, "counts", "nan"), ["bad.csv", "row 3", "counts"]),
    "joint without sweep": (lambda r: _set(r, 2, "joint", "3"), ["bad.csv", "joint 3"]),
}


@pytest.mark.parametrize("case", list(HOME_CASES))
def test_scale_refuses_a_broken_home(work, case):
    mutate, keywords = HOME_CASES[case]
    write_rows(work / "bad.csv", mutate(rows_of(work / "home.csv")))
    refused(work, ["scale", "--sweep", "sweep.csv", "--home", "bad.csv", "--out", "out.toml"],
            *keywords)  # fmt: skip


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("--alpha", "0"),
        ("--alpha", "1"),
        ("--counts-per-mm", "0"),
        ("--counts-per-mm", "nan"),
        ("--step-deg", "-2"),
        ("--tracker-mpe-um", "inf"),
        ("--terms", "bogus"),
    ],
)
def test_scale_refuses_a_bad_option(work, option, value):
    refused(work, [*SCALE, f"{option}={value}"], option if option != "--terms" else "bogus")


def test_scale_outputs_never_replace_an_input_or_land_half(work):
    base = ["scale", "--sweep", "sweep.csv", "--home", "home.csv"]
    refused(work, [*base, "--out", "sweep.csv"], "--out", "input")
    refused(work, [*base, "--out", "./x/../home.csv"], "--out", "input")
    refused(work, [*base, "--out", "out.toml", "--report", "sweep.csv"], "--report", "input")
    refused(work, [*base, "--out", "out.toml", "--report", "scale.toml"], "--report", "directory")
    refused(work, [*base, "--out", "sweep.csv/out.toml"], "--out", "not a directory")
    (work / "adir").mkdir()
    refused(work, [*base, "--out", "adir"], "--out", "directory")


def test_scale_a_report_directory_that_cannot_be_written_leaves_no_output(
    work, monkeypatch, capsys
):
    # in process: the system refusing the report's files is injected (root writes anywhere)
    (work / "rep").mkdir()
    before = snapshot(work)
    refuse_moves_into(monkeypatch, work / "rep")
    monkeypatch.chdir(work)
    status = twin_main(
        ["scale", "--sweep", "sweep.csv", "--home", "home.csv", "--out", "new.toml",
         "--report", "rep"]
    )  # fmt: skip
    assert_refusal(status, capsys.readouterr().err, ["--report", "rep", "cannot write"],
                   before, snapshot(work))  # fmt: skip


def _home_off_by(work: Path, joint: int, counts: int) -> None:
    rows = rows_of(work / "home.csv")
    j, c = rows[0].index("joint"), rows[0].index("counts")
    for r in rows[1:]:
        if r[j] == str(joint):
            r[c] = str((int(r[c]) + counts) % 2**32)
    write_rows(work / "bad.csv", rows)


def test_scale_refuses_a_home_that_puts_the_sweep_outside_the_joint(work):
    # Home counts 5 million off the sweep's (another joint's, a reset counter): the map
    # would turn joint 2 through ~640° from Home
    _home_off_by(work, 2, 5_000_000)
    base = ["scale", "--sweep", "sweep.csv", "--home", "bad.csv", "--out", "new.toml"]
    refused(work, base, "bad.csv", "joint 2", "a turn from Home", "--allow-out-of-range")
    refused(work, [*base, "--robot", "kr500"], "bad.csv", "joint 2", "limits -40..110",
            "--allow-out-of-range")  # fmt: skip
    assert twin(work, *base, "--allow-out-of-range").returncode == 0


def test_scale_keeps_a_home_off_by_less_than_the_margin(work):
    # 200 counts (under 0.03°) off: a Home's ordinary scatter, calibrated as before
    _home_off_by(work, 2, 200)
    done = twin(work, "scale", "--sweep", "sweep.csv", "--home", "bad.csv", "--out", "new.toml",
                "--robot", "kr500")  # fmt: skip
    assert done.returncode == 0, done.stderr


def test_scale_accepts_bom_crlf_and_shuffled_columns_with_the_same_numbers(work):
    clean = twin(work, *SCALE)
    assert clean.returncode == 0, clean.stderr
    expected = (work / "out.toml").read_text().split("[[joint]]", 1)[1]
    text = (work / "sweep.csv").read_text()
    rows = rows_of(work / "sweep.csv")
    order = list(reversed(range(len(rows[0]))))
    variants = {
        "bom.csv": "\ufeff" + text,
        "crlf.csv": text.replace("\n", "\r\n"),
        "shuffled.csv": "\n".join(",".join(r[k] for k in order) for r in rows) + "\n",
    }
    for name, content in variants.items():
        (work / name).write_text(content, newline="")
        proc = twin(work, "scale", "--sweep", name, "--home", "home.csv", "--out", "v.toml")
        assert proc.returncode == 0, (name, proc.stderr)
        got = (work / "v.toml").read_text().split("[[joint]]", 1)[1]
        assert got == expected, name


# -- scale-apply --------------------------------------------------------------------------------
COUNTS_CASES = {
    "empty": (lambda r: [], ["bad.csv", "empty"]),
    "header only": (lambda r: r[:1], ["bad.csv", "no data rows"]),
    "nan": (lambda r: _set(r, 4, "counts", "nan"), ["bad.csv", "row 4", "counts"]),
    "unknown joint": (lambda r: _set(r, 3, "joint", "5"), ["bad.csv", "row 3", "joint 5"]),
    "beyond 32 bits": (lambda r: _set(r, 5, "counts", str(2**40)), ["row 5", "counts"]),
    "far outside": (
        lambda r: _set(r, 6, "counts", str(int(r[5][1]) + 50_000_000)),
        ["bad.csv", "row 6", "joint", "--allow-out-of-range"],
    ),
}


@pytest.mark.parametrize("case", list(COUNTS_CASES))
def test_scale_apply_refuses_broken_counts(work, case):
    mutate, keywords = COUNTS_CASES[case]
    write_rows(work / "bad.csv", mutate(rows_of(work / "counts.csv")))
    refused(work, [*APPLY, "--data", "bad.csv"], *keywords)


def test_scale_apply_converts_far_counts_when_told(work):
    rows = COUNTS_CASES["far outside"][0](rows_of(work / "counts.csv"))
    write_rows(work / "bad.csv", rows)
    proc = twin(work, *APPLY, "--data", "bad.csv", "--allow-out-of-range")
    assert proc.returncode == 0, proc.stderr
    angles = rows_of(work / "angles.csv")
    far = float(angles[5][-1])
    assert abs(far) > 360.0  # converted as asked, not clipped
    assert all(abs(float(r[-1])) < 90.0 for i, r in enumerate(angles[1:], 2) if i != 6)


def test_scale_apply_refuses_a_direction_it_does_not_know(work):
    rows = [
        [*r, "direction" if i == 0 else "up"] for i, r in enumerate(rows_of(work / "counts.csv"))
    ]
    write_rows(work / "bad.csv", rows)
    refused(work, [*APPLY, "--data", "bad.csv"], "bad.csv", "row 2", "direction")


SCALE_TOML_CASES = {
    "syntax": (lambda t: t + "\n[[joint]\n", ["bad.toml", "not valid TOML"]),
    "format": (lambda t: t.replace("format = ", 'format = "v0" #', 1), ["bad.toml", "format"]),
    "nan": (lambda t: t.replace("zero_counts = ", "zero_counts = nan #", 1), ["zero_counts"]),
    "missing coefficient": (
        lambda t: t.replace("[joint.coefficients]\n", "[joint.coefficients]\n#", 1),
        ["bad.toml", "coefficient"],
    ),
    "joint twice": (
        lambda t: t + "\n[[joint]]" + t.split("[[joint]]")[1],
        ["bad.toml", "twice"],
    ),
    "range": (
        lambda t: t.replace("calibrated_range_deg = [", "calibrated_range_deg = [1e9, ", 1),
        ["bad.toml", "calibrated_range_deg"],
    ),
}


@pytest.mark.parametrize("case", list(SCALE_TOML_CASES))
def test_scale_apply_refuses_a_broken_scale_toml(work, case):
    mutate, keywords = SCALE_TOML_CASES[case]
    text = (work / "scale.toml").read_text()
    (work / "bad.toml").write_text(mutate(text))
    assert (work / "bad.toml").read_text() != text
    refused(work, ["scale-apply", "--scale", "bad.toml", "--data", "counts.csv", "--out",
                   "a.csv"], *keywords)  # fmt: skip


def test_scale_apply_refuses_a_binary_scale_and_outputs_onto_inputs(work):
    (work / "bad.toml").write_bytes(b"\xff\x00" * 100)
    base = ["scale-apply", "--data", "counts.csv"]
    refused(work, [*base, "--scale", "bad.toml", "--out", "a.csv"], "bad.toml")
    refused(work, [*base, "--scale", "scale.toml", "--out", "counts.csv"], "--out", "input")
    refused(work, [*base, "--scale", "scale.toml", "--out", "scale.toml"], "--out", "input")
    before = snapshot(work)
    assert before  # the directory is not empty: the snapshots compare something


# -- the readers, fuzzed ------------------------------------------------------------------------
FUZZ = settings(max_examples=40, deadline=None)


def _head(path: Path, lines: int) -> bytes:
    return b"".join(path.read_bytes().splitlines(keepends=True)[:lines])


def test_scale_readers_fuzzed(clean, tmp_path):
    sweep, home = _head(clean / "sweep.csv", 40), _head(clean / "home.csv", 12)
    counts, scale = _head(clean / "counts.csv", 12), (clean / "scale.toml").read_bytes()

    @FUZZ
    @given(_mutations(sweep), _mutations(home), _mutations(counts), _mutations(scale))
    def check(s, h, c, t):
        cases = ((s, read_sweep_csv), (h, read_home_csv), (c, read_counts_csv))
        for content, reader in (*cases, (t, read_scale_toml)):
            path = tmp_path / "f"
            path.write_bytes(content)
            try:
                got = reader(path)
            except CalibrationError:
                continue
            if reader is read_scale_toml:
                for scale_ in got.joints.values():
                    assert all(math.isfinite(v) for v in scale_.coefficients.values())
            elif reader is read_counts_csv:
                assert len(got.joint) > 0 and np.all(got.counts >= 0)

    check()
