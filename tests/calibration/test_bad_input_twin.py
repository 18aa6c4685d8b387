"""Bad input to ``twin identify``, ``twin predict``, ``twin robot``, ``twin export`` and
``twin run``, as a careless user gives it (real ``twin`` processes), and the readers
behind them fuzzed (in process, hypothesis).

Every refused case asserts: exit status 2, one line on stderr naming the file and the
line/column/key/option, no traceback, and every file in the working directory byte for
byte as before (no output created, no staging left). Accepted look-alikes (BOM, CRLF,
shuffled columns, ``--no-unit-check``) must give the same numbers as the clean file.

=================  ==========================================================================
category           cases
=================  ==========================================================================
campaign.csv       empty, header only, NaN, inf, duplicated pose, non-UTF-8, missing column,
                   short row, unknown set, outside limits, extra joint column, duplicated
                   header, metres, radians, no identify rows, 3 rows, one pose repeated,
                   /dev/zero, a directory, missing, over the size limit, binary
accepted           BOM, CRLF, shuffled columns, metres with --no-unit-check
options            --f-scale-mm -1/0/nan/inf, --tracker-mpe-um x/-1,2, --effects-alpha 0/1.5,
                   --effect-kinds bogus
outputs            --out = --data, --out = --robot file, --out a symlink to the data,
                   --out below a file, --out a directory, --report a file, --report = data,
                   --out in /proc, a failed fit with an earlier output in place, a --report
                   directory the system refuses to write
robot .toml        binary, syntax, wrong type, NaN, unknown key, bad [[effect]], fewer joints,
                   /dev/zero; ``twin robot`` refuses what ``twin predict`` refuses
joints.csv         radians, empty, header only, NaN, duplicated pose, missing q column,
                   --out = --data, --out = --model, missing model
recordings         CSV as --replay, random bytes, empty, --out a file, --out = --replay,
                   --from without run.json, --from with a broken run.json, a damaged chunk
                   without --allow-partial (export, run), --allow-partial without --replay
=================  ==========================================================================
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.cli import main as twin_main
from calibration.effects.model_effects import description_effects
from calibration.errors import CalibrationError
from calibration.identify.campaign_files import read_campaign, read_joint_readings, write_campaign
from calibration.model.description import RobotDescription, load_robot
from calibration.twin.streams import read_recording_streams
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign
from tests import bad_input
from tests.bad_input import assert_refusal, refuse_moves_into, snapshot

#: Set to a file path to list every refused input there (counted for notes).
COUNT_FILE = "BAD_INPUT_COUNT_FILE"
RECORDING = Path(__file__).parents[1] / "data" / "campaign_small.mcap"
TWIN = [sys.executable, "-m", "calibration.cli"]
FUZZ = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


# -- the clean inputs ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """campaign.csv (30 + 10 poses, kr500), joints.csv, robot.toml, cal.toml."""
    root = tmp_path_factory.mktemp("clean")
    data = emulated_campaign("kr500", 5, CampaignSettings(n_identify=30, n_validate=10))
    write_campaign(root / "campaign.csv", data.campaign)
    lines = (root / "campaign.csv").read_text().splitlines()
    header = lines[0].split(",")
    keep = [header.index(c) for c in ("pose", "t_s", *(f"q{i}_deg" for i in range(1, 7)))]
    (root / "joints.csv").write_text(
        "\n".join(",".join(row.split(",")[k] for k in keep) for row in lines) + "\n"
    )
    load_robot("kr500").save(root / "robot.toml")
    proc = twin(root, "identify", "--robot", "kr500", "--data", "campaign.csv",
                "--out", "cal.toml", "--no-effects", "--quiet")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return root


def twin(cwd: Path, *args: str, env: dict[str, str] | None = None):
    return bad_input.run([*TWIN, *args], cwd, env, timeout=120)


@pytest.fixture
def work(clean, tmp_path) -> Path:
    for f in clean.iterdir():
        shutil.copy(f, tmp_path / f.name)
    return tmp_path


def refused(work: Path, args: list[str], *keywords: str, env=None) -> str:
    """Run ``twin ARGS`` in ``work``: exit 2, one stderr line with the key words (any
    case), and no file changed (tests/bad_input.py). Returns the line."""
    proc = bad_input.refused(work, [*TWIN, *args], keywords, env=env, timeout=120, ignore_case=True)
    if os.environ.get(COUNT_FILE):  # the closing note's counts: one line per refused input
        with open(os.environ[COUNT_FILE], "a", encoding="utf-8") as fh:
            fh.write(" ".join(args) + "\n")
    return proc.stderr.strip()


def campaign_rows(work: Path) -> list[list[str]]:
    return [line.split(",") for line in (work / "campaign.csv").read_text().splitlines()]


def write_rows(path: Path, rows: list[list[str]]) -> None:
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")


def column(rows: list[list[str]], name: str) -> int:
    return rows[0].index(name)


XYZ = ("x_mm", "y_mm", "z_mm")
Q = tuple(f"q{i}_deg" for i in range(1, 7))
IDENTIFY = ["identify", "--robot", "kr500", "--out", "out.toml", "--no-effects", "--quiet"]


def identify_bad(work: Path, *keywords: str, extra=(), data="bad.csv", env=None) -> str:
    return refused(work, [*IDENTIFY, "--data", data, *extra], *keywords, env=env)


# -- campaign.csv -----------------------------------------------------------------------------
def _drop(rows, name):
    k = column(rows, name)
    return [[v for i, v in enumerate(r) if i != k] for r in rows]


def _in_units(rows, names, convert):
    """``rows`` with the columns ``names`` converted by ``convert`` (float -> float)."""
    ks = {column(rows, n) for n in names}
    return [rows[0]] + [
        [f"{convert(float(v)):.9f}" if k in ks else v for k, v in enumerate(r)] for r in rows[1:]
    ]


def _set(rows, line, name, value):
    rows[line - 1][column(rows, name)] = value
    return rows


CAMPAIGN_CASES = {
    "empty": (lambda r: [], ["bad.csv", "empty"]),
    "header only": (lambda r: r[:1], ["bad.csv", "no valid data rows"]),
    "nan": (lambda r: _set(r, 6, "x_mm", "nan"), ["bad.csv", "line 6", "x_mm", "finite"]),
    "inf": (lambda r: _set(r, 4, "q2_deg", "inf"), ["line 4", "q2_deg"]),
    "text": (lambda r: _set(r, 5, "t_s", "12:30"), ["line 5", "t_s", "not a number"]),
    "duplicated pose": (lambda r: _set(r, 7, "pose", r[2][0]), ["line 7", "duplicated pose"]),
    "missing column": (lambda r: _drop(r, "z_mm"), ["bad.csv", "missing column", "z_mm"]),
    "short row": (lambda r: [*r[:8], r[8][:5], *r[9:]], ["line 9", "fields"]),
    "unknown set": (lambda r: _set(r, 3, "set", "train"), ["line 3", "set", "train"]),
    "outside limits": (lambda r: _set(r, 10, "q2_deg", "500"), ["line 10", "q2_deg", "limits"]),
    "duplicated header": (lambda r: [[*r[0][:-1], "x_mm"], *r[1:]], ["x_mm", "twice"]),
    "no identify rows": (
        lambda r: [r[0]] + [[x[0], "validate", *x[2:]] for x in r[1:]],
        ["bad.csv", "identify"],
    ),
    "three rows": (lambda r: r[:4], ["bad.csv", "3 distinct pose"]),
    "one pose repeated": (
        lambda r: [r[0]] + [[str(k), *r[1][1:]] for k in range(1, 30)],
        ["bad.csv", "1 distinct pose"],
    ),
    "extra joint": (
        lambda r: [[*x, "q7_deg" if i == 0 else "0"] for i, x in enumerate(r)],
        ["q7_deg", "6 joints"],
    ),
}


@pytest.mark.parametrize("case", list(CAMPAIGN_CASES))
def test_identify_refuses_a_broken_campaign(work, case):
    mutate, keywords = CAMPAIGN_CASES[case]
    write_rows(work / "bad.csv", mutate(campaign_rows(work)))
    (work / "out.toml").write_text("an earlier output\n")  # must survive a failed run
    identify_bad(work, *keywords)


def test_identify_names_the_line_of_non_utf8_bytes(work):
    raw = (work / "campaign.csv").read_bytes().splitlines(keepends=True)
    raw[4] = raw[4][:10] + b"\xff\xfe" + raw[4][10:]
    (work / "bad.csv").write_bytes(b"".join(raw))
    identify_bad(work, "bad.csv", "line 5", "utf-8")


def test_identify_refuses_binary_and_endless_and_huge_inputs(work):
    (work / "bad.csv").write_bytes(bytes(range(256)) * 40)
    identify_bad(work, "bad.csv")
    identify_bad(work, "/dev/zero", "device", data="/dev/zero")
    (work / "adir").mkdir()
    identify_bad(work, "adir", "directory", data="adir")
    identify_bad(work, "missing.csv", "no such file", data="missing.csv")
    identify_bad(
        work,
        "campaign.csv",
        "limit",
        "GRATING_TWIN_MAX_INPUT_MB",
        data="campaign.csv",
        env={"GRATING_TWIN_MAX_INPUT_MB": "0.001"},
    )


def test_identify_refuses_metres_and_radians_with_a_hint(work):
    rows = campaign_rows(work)
    write_rows(work / "bad.csv", _in_units(rows, XYZ, lambda v: v / 1000))
    identify_bad(work, "bad.csv", "x_mm", "metres", "--no-unit-check")
    write_rows(work / "bad.csv", _in_units(rows, Q, math.radians))
    identify_bad(work, "bad.csv", "q1_deg", "radians", "--no-unit-check")


def _mean_ap(stdout: str) -> list[str]:
    return [line for line in stdout.splitlines() if "mean AP" in line]


def test_accepted_look_alikes_give_the_clean_numbers(work):
    clean = twin(work, *IDENTIFY, "--data", "campaign.csv")
    assert clean.returncode == 0, clean.stderr
    text = (work / "campaign.csv").read_text()
    rows = campaign_rows(work)
    order = list(reversed(range(len(rows[0]))))
    variants = {
        "bom.csv": "\ufeff" + text,
        "crlf.csv": text.replace("\n", "\r\n"),
        "shuffled.csv": "\n".join(",".join(r[k] for k in order) for r in rows) + "\n",
    }
    for name, content in variants.items():
        (work / name).write_text(content, newline="")
        proc = twin(work, *IDENTIFY, "--data", name)
        assert proc.returncode == 0, (name, proc.stderr)
        assert _mean_ap(proc.stdout) == _mean_ap(clean.stdout), name
    # metres with the override: runs (the user said so), and the fit is of a small robot
    xyz = [column(rows, c) for c in ("x_mm", "y_mm", "z_mm")]
    write_rows(
        work / "m.csv",
        [rows[0]]
        + [
            [f"{float(v) / 1000:.9f}" if k in xyz else v for k, v in enumerate(r)] for r in rows[1:]
        ],
    )
    proc = twin(work, *IDENTIFY, "--data", "m.csv", "--no-unit-check")
    assert proc.returncode in (0, 2), proc.stderr
    assert "Traceback" not in proc.stderr


# -- options ----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("option", "value", "keyword"),
    [
        ("--f-scale-mm", "-1", "--f-scale-mm"),
        ("--f-scale-mm", "0", "--f-scale-mm"),
        ("--f-scale-mm", "nan", "--f-scale-mm"),
        ("--f-scale-mm", "inf", "--f-scale-mm"),
        ("--tracker-mpe-um", "x", "--tracker-mpe-um"),
        ("--tracker-mpe-um", "-1,2", "--tracker-mpe-um"),
        ("--effects-alpha", "0", "--effects-alpha"),
        ("--effects-alpha", "1.5", "--effects-alpha"),
        ("--effect-kinds", "bogus", "--effect-kinds"),
    ],
)
def test_identify_refuses_a_bad_option_before_reading(work, option, value, keyword):
    identify_bad(work, keyword, extra=[f"{option}={value}"], data="campaign.csv")


# -- outputs ----------------------------------------------------------------------------------
def test_an_output_that_is_an_input_is_refused(work):
    base = ["identify", "--robot", "robot.toml", "--data", "campaign.csv", "--quiet"]
    refused(work, [*base, "--out", "campaign.csv"], "--out", "input")
    refused(work, [*base, "--out", "robot.toml"], "--out", "input")
    refused(work, [*base, "--out", "./sub/../campaign.csv"], "--out", "input")
    os.symlink("campaign.csv", work / "link.csv")
    refused(work, [*base, "--out", "link.csv"], "--out", "input")
    refused(work, [*base, "--out", "o.toml", "--report", "campaign.csv"], "--report", "input")


def test_an_output_that_cannot_be_written_is_refused_before_the_fit(work):
    base = ["identify", "--robot", "kr500", "--data", "campaign.csv", "--quiet"]
    refused(work, [*base, "--out", "campaign.csv/o.toml"], "--out", "not a directory")
    (work / "adir").mkdir()
    refused(work, [*base, "--out", "adir"], "--out", "directory")
    refused(work, [*base, "--out", "o.toml", "--report", "cal.toml"], "--report", "directory")
    refused(work, [*base, "--out", "/proc/o.toml"], "--out", "/proc")


def test_a_report_directory_that_cannot_be_written_leaves_no_output(work, monkeypatch, capsys):
    # in process: the system refusing the report's files is injected (root writes anywhere);
    # before, calibrated.toml was already in place when the report's move failed
    (work / "rep").mkdir()
    before = snapshot(work)
    refuse_moves_into(monkeypatch, work / "rep")
    monkeypatch.chdir(work)
    argv = ["identify", "--robot", "kr500", "--data", "campaign.csv", "--no-effects"]
    status = twin_main([*argv, "--out", "calibrated.toml", "--report", "rep", "--quiet"])
    assert_refusal(status, capsys.readouterr().err, ["--report", "rep", "cannot write"],
                   before, snapshot(work))  # fmt: skip


def test_a_successful_run_creates_directories_and_leaves_no_staging(work):
    proc = twin(work, *IDENTIFY[:-2], "--data", "campaign.csv", "--out", "new/deep/o.toml",
                "--report", "new/report", "--quiet", "--no-effects")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert (work / "new/deep/o.toml").is_file()
    assert (work / "new/report/report.json").is_file()
    assert not [p for p in work.rglob("*") if ".partial-" in p.name]


# -- robot description ------------------------------------------------------------------------
def _robot_text(work: Path) -> str:
    return (work / "robot.toml").read_text()


ROBOT_CASES = {
    "syntax": (lambda t: t + "\n[joint\n", ["bad.toml", "not valid TOML"]),
    "wrong type": (lambda t: t.replace("a_mm = ", 'a_mm = "x" #', 1), ["bad.toml", "a_mm"]),
    "nan": (lambda t: t.replace("a_mm = ", "a_mm = nan #", 1), ["bad.toml", "a_mm"]),
    "unknown key": (lambda t: "colour = 1\n" + t, ["bad.toml", "colour"]),
    "bad effect": (
        lambda t: t + '\n[[effect]]\nkind = "joint_harmonic"\njoint = 9\n',
        ["bad.toml", "effect"],
    ),
}


@pytest.mark.parametrize("case", list(ROBOT_CASES))
def test_a_broken_robot_description_is_refused_by_every_command(work, case):
    mutate, keywords = ROBOT_CASES[case]
    (work / "bad.toml").write_text(mutate(_robot_text(work)))
    refused(work, ["robot", "bad.toml"], *keywords)
    refused(work, ["predict", "--model", "bad.toml", "--data", "joints.csv", "--out", "p.csv"],
            *keywords)  # fmt: skip
    refused(work, ["identify", "--robot", "bad.toml", "--data", "campaign.csv", "--out", "o.toml",
                   "--quiet"], *keywords)  # fmt: skip


def test_binary_endless_and_short_robot_descriptions(work):
    (work / "bad.toml").write_bytes(b"\x00\xff" * 300)
    refused(work, ["robot", "bad.toml"], "bad.toml", "utf-8")
    refused(work, ["robot", "/dev/zero"], "/dev/zero", "device")
    desc = load_robot("kr500")
    replace(desc, joints=desc.joints[:5], home_deg=desc.home[:5]).save(work / "five.toml")
    refused(work, ["identify", "--robot", "five.toml", "--data", "campaign.csv", "--out",
                   "o.toml", "--quiet"], "campaign.csv", "q6_deg")  # fmt: skip


# -- twin predict -----------------------------------------------------------------------------
def joints_rows(work: Path) -> list[list[str]]:
    return [line.split(",") for line in (work / "joints.csv").read_text().splitlines()]


PREDICT_CASES = {
    "radians": (
        lambda r: (
            [r[0]] + [x[:2] + [f"{math.radians(float(v)):.9f}" for v in x[2:]] for x in r[1:]]
        ),
        ["bad.csv", "radians", "--no-unit-check"],
    ),
    "empty": (lambda r: [], ["bad.csv", "empty"]),
    "header only": (lambda r: r[:1], ["bad.csv", "no valid data rows"]),
    "nan": (lambda r: _set(r, 3, "t_s", "nan"), ["bad.csv", "line 3", "t_s"]),
    "duplicated pose": (lambda r: _set(r, 5, "pose", r[1][0]), ["line 5", "duplicated"]),
    "missing q": (lambda r: [x[:-1] for x in r], ["bad.csv", "q6_deg"]),
}


@pytest.mark.parametrize("case", list(PREDICT_CASES))
def test_predict_refuses_broken_joints(work, case):
    mutate, keywords = PREDICT_CASES[case]
    write_rows(work / "bad.csv", mutate(joints_rows(work)))
    refused(work, ["predict", "--model", "cal.toml", "--data", "bad.csv", "--out", "p.csv"],
            *keywords)  # fmt: skip


def test_predict_refuses_outputs_onto_inputs_and_a_missing_model(work):
    base = ["predict", "--model", "cal.toml", "--data", "joints.csv"]
    refused(work, [*base, "--out", "joints.csv"], "--out", "input")
    refused(work, [*base, "--out", "cal.toml"], "--out", "input")
    refused(work, ["predict", "--model", "nope.toml", "--data", "joints.csv", "--out", "p.csv"],
            "nope.toml")  # fmt: skip
    proc = twin(work, *base, "--out", "p.csv")
    assert proc.returncode == 0, proc.stderr


# -- recordings: twin export and twin run -----------------------------------------------------
def test_export_and_run_refuse_what_is_not_a_recording(work):
    (work / "noise.mcap").write_bytes(np.random.default_rng(3).bytes(5000))
    (work / "empty.mcap").write_bytes(b"")
    for cmd in ("export", "run"):
        refused(work, [cmd, "--replay", "campaign.csv", "--out", "o", "--quiet"],
                "campaign.csv", "mcap")  # fmt: skip
        refused(work, [cmd, "--replay", "noise.mcap", "--out", "o", "--quiet"], "noise.mcap")
        refused(work, [cmd, "--replay", "empty.mcap", "--out", "o", "--quiet"], "empty.mcap")
        refused(work, [cmd, "--replay", "nowhere.mcap", "--out", "o", "--quiet"], "nowhere")
        refused(work, [cmd, "--replay", "campaign.csv", "--out", "cal.toml", "--quiet"],
                "--out", "not a directory")  # fmt: skip


def test_a_damaged_recording_is_used_only_when_allowed(tmp_path):
    """A recording with a damaged chunk in the middle: export and run refuse it, saying
    what was readable and what not; --allow-partial uses the rest, says so on stderr
    (also with --quiet) and phases.json records it."""
    from tests.daq.test_bad_input_daq import damage_chunk

    work = tmp_path
    data, offset, lost = damage_chunk(RECORDING.read_bytes(), 20)
    (work / "damaged.mcap").write_bytes(data)
    read = f"read {8582 - lost} messages"
    for cmd in ("export", "run"):
        refused(work, [cmd, "--replay", "damaged.mcap", "--out", "o", "--quiet"],
                "damaged.mcap", read, f"byte {offset}", "--allow-partial")  # fmt: skip
    refused(work, ["run", "--allow-partial", "--out", "o"], "--allow-partial", "--replay")
    streams = read_recording_streams(work / "damaged.mcap", allow_partial=True)
    assert read in streams.note and f"byte {offset}" in streams.note
    assert "--allow-partial" in streams.note  # phases.json and report.json carry the note


@pytest.mark.slow
def test_a_damaged_recording_allowed_is_said_and_recorded(tmp_path):
    """``twin export --allow-partial`` on it: a warning also with --quiet, phases.json's
    note (~15 s: `pytest -m slow -k allowed_is_said`)."""
    from tests.daq.test_bad_input_daq import damage_chunk

    data, offset, lost = damage_chunk(RECORDING.read_bytes(), 20)
    (tmp_path / "damaged.mcap").write_bytes(data)
    read = f"read {8582 - lost} messages"
    proc = twin(tmp_path, "export", "--replay", "damaged.mcap", "--out", "o", "--quiet",
                "--allow-partial")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "warning" in proc.stderr and read in proc.stderr and f"byte {offset}" in proc.stderr
    note = json.loads((tmp_path / "o" / "phases.json").read_text())["note"]
    assert read in note and "--allow-partial" in note


def test_run_from_an_earlier_run_needs_its_run_json(work):
    (work / "old").mkdir()
    refused(work, ["run", "--from", "old", "--out", "o", "--quiet"], "run.json")
    (work / "old" / "run.json").write_text('{"calibrated": 3}')
    refused(work, ["run", "--from", "old", "--out", "o", "--quiet"], "run.json", "calibrated")
    (work / "old" / "run.json").write_text("{not json")
    refused(work, ["run", "--from", "old", "--out", "o", "--quiet"], "run.json")


# -- the readers, fuzzed ----------------------------------------------------------------------
def _mutations(data: bytes):
    """Random bytes, a truncation, or a few byte flips of ``data``."""
    flips = st.lists(
        st.tuples(st.integers(0, max(len(data) - 1, 0)), st.integers(0, 255)), max_size=8
    )

    def flip(changes):
        b = bytearray(data)
        for i, v in changes:
            if b:
                b[i] = v
        return bytes(b)

    return st.one_of(
        st.binary(max_size=2000),
        st.integers(0, len(data)).map(lambda n: data[:n]),
        flips.map(flip),
    )


def _fuzz_campaign_text(clean: Path) -> bytes:
    lines = (clean / "campaign.csv").read_bytes().splitlines(keepends=True)
    return b"".join(lines[:12])


def test_campaign_readers_fuzzed(clean, tmp_path):
    data = _fuzz_campaign_text(clean)
    joints = b"".join((clean / "joints.csv").read_bytes().splitlines(keepends=True)[:12])
    limits = [(j.lower_deg, j.upper_deg) for j in load_robot("kr500").joints]

    @FUZZ
    @given(_mutations(data), _mutations(joints))
    def check(campaign_bytes, joints_bytes):
        path = tmp_path / "f.csv"
        for content, reader in (
            (campaign_bytes, read_campaign),
            (joints_bytes, read_joint_readings),
        ):
            path.write_bytes(content)
            try:
                got = reader(path, 6, limits_deg=limits)
            except CalibrationError:
                continue
            assert np.all(np.isfinite(got.q_deg)) and len(got.pose) == len(set(got.pose))

    check()


def test_robot_description_reader_fuzzed(clean, tmp_path):
    data = (clean / "robot.toml").read_bytes()

    @FUZZ
    @given(_mutations(data))
    def check(content):
        path = tmp_path / "r.toml"
        path.write_bytes(content)
        try:
            desc = RobotDescription.load(path)
            description_effects(desc)
        except CalibrationError:
            return
        assert all(math.isfinite(j.a_mm) and math.isfinite(j.d_mm) for j in desc.joints)

    check()


def test_recording_reader_fuzzed(tmp_path):
    data = RECORDING.read_bytes()
    cut = st.integers(0, len(data)).map(lambda n: data[:n])
    window = st.tuples(st.integers(0, len(data) - 1), st.integers(0, 255))

    def flip(changes):
        b = bytearray(data)
        for i, v in changes:
            b[i] = v
        return bytes(b)

    @settings(max_examples=25, deadline=None)
    @given(st.one_of(st.binary(max_size=4000), cut, st.lists(window, max_size=6).map(flip)))
    def check(content):
        path = tmp_path / "r.mcap"
        path.write_bytes(content)
        try:
            streams = read_recording_streams(path)
        except CalibrationError:
            return
        assert len(streams.grating) > 0 and len(streams.tracker) > 0

    check()
