"""Bad input to the emulator's commands, as a user meets them: real processes of ``sim-cell``
(serve, truth, default-config) and of the generators ``python -m sim_devices.scale_campaign``,
``python -m sim_devices.pose_campaign`` and ``python -m sim_devices.physics_report``, plus
hypothesis fuzzing of the cell-config reader and the option parsers in process.

Every refused case runs in a fresh working directory holding valid inputs (a cell config,
a robot description, an earlier output) and asserts: exit status 2, the key words of the
message (the file and the table/key, or the option), exactly one line on stderr, no
"Traceback", nothing on stdout, and every file of the directory byte for byte as before
with nothing created (no output, no staging leftover).

| category (where) | cases |
|---|---|
| bytes: binary, NUL, UTF-16, latin-1, bad syntax, duplicate key/table, deep nesting (config) | 8 |
| unknown table/key, a table given as a value (config) | 4 |
| wrong types: string/bool/float/array/element (config) | 7 |
| NaN, inf, -inf, 1e400, NaN in an array (config) | 5 |
| out of range: seed, speed, ids, probability, port, rates, buffer, ppm, lists (config) | 16 |
| duplicates, empty lists, keys that go together (config) | 4 |
| names (program, target); joint numbers and per-joint lists against the robot (config) | 6 |
| the robot a config names: unknown, device, empty, latin-1 file (config) | 4 |
| the file: missing, directory, /dev/zero, over the size limit, empty path (--config) | 5 |
| sim-cell options: nan/inf/negative/text duration, log level, unknown, missing | 9 |
| sim-cell outputs: onto --config / the robot / a symlink to the config, a directory, | 9 |
|   under a file, empty; serve's truth onto its config (option, key); run_dir a file | |
| sim-cell serve fails after start: a port in use (alone; grating started first) | 2 |
| scale_campaign joint lists: range, duplicates, format, empty; --no-home | 10 |
| scale_campaign numbers: nan, inf, negative, too large, not a number, effect name | 18 |
| scale_campaign robot: unknown, device, latin-1, binary, directory | 5 |
| scale_campaign outputs: a file as --out, empty, onto the robot | 3 |
| scale_campaign fails after the run (a file's place is a directory) | 1 |
| pose_campaign counts, seed, selection, effect | 9 |
| pose_campaign robot; outputs (--out = --truth, onto the robot, directories, empty) | 9 |
| pose_campaign fails after start: no pose in the tracker's range | 1 |
| physics_report options; a bad robot after a good one (nothing printed) | 8 |

Accepted on purpose (checked to give the same cell as the plain file): an empty file (the
default cell), comments only, header only, a UTF-8 byte-order mark, CRLF line ends, tables
in another order.
"""

from __future__ import annotations

import argparse
import math
import re
import socket
import sys
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.model.description import PRESET_PACKAGE
from sim_devices.config import (
    RANGES,
    CellConfig,
    integer_option,
    joint_list,
    number_option,
)
from sim_devices.errors import SimError
from tests import bad_input
from tests.bad_input import snapshot

pytestmark = pytest.mark.timeout(120)

BIN = Path(sys.executable).parent
SIM_CELL = str(BIN / "sim-cell")
PY = sys.executable
TIMEOUT_S = 60
FUZZ = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])

#: Outcomes of every refused case, by kind (printed at the end of the module, ``-s``).
TALLY: Counter[str] = Counter()


def _preset(name: str) -> str:
    from importlib import resources

    return (resources.files(PRESET_PACKAGE) / f"{name}.toml").read_text(encoding="utf-8")


HP20D = _preset("hp20d")
#: the HP20D 40 m away from the tracker: every pose out of its 25 m range (found only once
#: the generator has run 1000 batches of poses)
FAR_ROBOT = re.sub(r"(\[base\]\s*\nx_mm = )[-0-9.]+", r"\g<1>40000.0", HP20D, count=1)


@pytest.fixture(scope="module", autouse=True)
def tally():
    yield
    print(
        "\nbad input (sim): tried {tried}, clear errors {clear}, tracebacks {traceback}, "
        "hangs {hang}, silent wrong results {silent}, runs that changed files {changed}".format(
            **{k: TALLY[k] for k in ("tried", "clear", "traceback", "hang", "silent", "changed")}
        )
    )


@pytest.fixture
def work(tmp_path: Path) -> Path:
    """A working directory with valid inputs and an earlier output."""
    (tmp_path / "cell.toml").write_text('[cell]\nseed = 2\nprogram = "hold"\n', encoding="utf-8")
    (tmp_path / "robot.toml").write_text(HP20D, encoding="utf-8")
    (tmp_path / "previous.txt").write_text("an earlier run's output\n", encoding="utf-8")
    return tmp_path


def run(argv: list[str], cwd: Path, env: dict[str, str] | None = None):
    return bad_input.run(argv, cwd, env, timeout=TIMEOUT_S)


def refused(work: Path, argv: list[str], words: list[str], env: dict[str, str] | None = None):
    """Run ``argv`` in ``work`` and assert the clean refusal, nothing on stdout either
    (tests/bad_input.py)."""
    return bad_input.refused(
        work, argv, words, env=env, timeout=TIMEOUT_S, tally=TALLY, quiet_stdout=True
    ).stderr


# -- sim-cell: the cell config ---------------------------------------------------------
CONFIG_CASES: list[tuple[str, bytes, list[str]]] = [
    # the bytes
    ("binary", b"PK\x03\x04\x00\x00" + bytes(range(256)), ["bad.toml", "NUL"]),
    ("utf16", "[cell]\nseed = 1\n".encode("utf-16"), ["bad.toml", "NUL"]),
    ("latin1", "[cell]\n# café\nseed = 1\n".encode("latin-1"), ["bad.toml", "line 2", "UTF-8"]),
    ("syntax", b"[cell\nseed = 1\n", ["bad.toml", "not valid TOML", "line 1"]),
    ("open-string", b'[cell]\nrobot = "kr500\n', ["bad.toml", "not valid TOML", "line 2"]),
    ("duplicate-key", b"[cell]\nseed = 1\nseed = 2\n", ["bad.toml", "not valid TOML", "line 3"]),
    ("duplicate-table", b"[cell]\nseed = 1\n[cell]\n", ["bad.toml", "not valid TOML", "line 3"]),
    ("deep-nesting", b"x = " + b"[" * 3000 + b"]" * 3000, ["bad.toml", "nested too deeply"]),
    # keys and tables
    ("unknown-table", b"[celll]\n", ["bad.toml", "unknown table 'celll'", "allowed: cell"]),
    ("unknown-key", b"[cell]\nsed = 3\n", ["bad.toml", "[cell]", "unknown key 'sed'", "seed"]),
    ("unknown-nested", b"[grating.faults]\ncrc = 0.1\n", ["[grating.faults]", "'crc'"]),
    ("table-as-value", b"cell = 3\n", ["bad.toml", "[cell]", "expected a table"]),
    # types
    ("str-for-int", b'[cell]\nseed = "1"\n', ["bad.toml", "[cell]", "'seed'", "an integer"]),
    ("bool-for-number", b"[cell]\nspeed = true\n", ["[cell]", "'speed'", "a number"]),
    ("float-for-int", b"[grating]\nunit_id = 1.0\n", ["[grating]", "'unit_id'", "an integer"]),
    ("str-for-array", b'[encoders]\nnode_ids = "1,2"\n', ["[encoders]", "'node_ids'", "array"]),
    ("float-element", b"[encoders]\nnode_ids = [1, 2.5]\n", ["'node_ids'", "integers"]),
    ("int-for-bool", b"[tracker]\nserial = 1\n", ["[tracker]", "'serial'", "true or false"]),
    ("int-for-str", b"[cell]\nrobot = 500\n", ["[cell]", "'robot'", "a string"]),
    # NaN and infinities
    ("nan", b"[cell]\nspeed = nan\n", ["bad.toml", "[cell]", "'speed'", "finite"]),
    ("inf", b"[grating]\nrate_hz = inf\n", ["[grating]", "'rate_hz'", "finite"]),
    ("-inf", b"[grating.faults]\nsilent_after_s = -inf\n", ["'silent_after_s'", "finite"]),
    ("1e400", b"[tracker]\npressure_hpa = 1e400\n", ["[tracker]", "'pressure_hpa'", "finite"]),
    (
        "nan-in-array",
        b"[effects]\nstiffness_nmm_per_rad = [6e10, nan]\n",
        ["[effects]", "'stiffness_nmm_per_rad'", "finite"],
    ),
    # ranges
    (
        "int-overflows-float",
        b"[effects]\nsag_mm_per_m2 = 1" + b"0" * 400 + b"\n",
        ["'sag_mm_per_m2'"],
    ),
    ("seed-negative", b"[cell]\nseed = -1\n", ["[cell]", "'seed'", "0..4294967295"]),
    ("seed-huge", b"[cell]\nseed = 100000000000000000000000\n", ["'seed'", "0..4294967295"]),
    ("speed-zero", b"[cell]\nspeed = 0\n", ["'speed'", "> 0"]),
    ("eccentricity", b"[cell]\neccentricity_mm = -0.1\n", ["'eccentricity_mm'", "0..1"]),
    ("unit-id", b"[grating]\nunit_id = 0\n", ["[grating]", "'unit_id'", "1..247"]),
    ("rate", b"[grating]\nrate_hz = 0.5\n", ["'rate_hz'", "1..20000"]),
    ("buffer", b"[grating]\nbuffer_samples = 1000000000\n", ["'buffer_samples'", "1000000"]),
    ("clock-ppm", b"[grating]\nclock_ppm = -1e6\n", ["'clock_ppm'", "-1000..1000"]),
    ("counter", b"[grating]\ncounter_offset_counts = [4294967296]\n", ["'counter_offset_counts'"]),
    (
        "probability",
        b"[grating.faults]\ncrc_error_probability = 1.5\n",
        ["'crc_error_probability'"],
    ),
    ("port", b"[tracker]\ntcp_port = 70000\n", ["[tracker]", "'tcp_port'", "0..65535"]),
    ("humidity", b"[tracker]\nhumidity_pct = 101\n", ["'humidity_pct'", "0..100"]),
    ("heartbeat", b"[encoders]\nheartbeat_ms = 70000\n", ["'heartbeat_ms'", "0..65535"]),
    ("node-id", b"[encoders]\nnode_ids = [0, 1]\n", ["'node_ids'", "1..127"]),
    ("stiffness-zero", b"[effects]\nstiffness_nmm_per_rad = [0]\n", ["'stiffness_nmm_per_rad'"]),
    # duplicates, empty lists, keys that go together
    (
        "node-ids-twice",
        b"[encoders]\nnode_ids = [1, 2, 2]\n",
        ["'node_ids'", "node id 2 given twice"],
    ),
    ("empty-list", b"[effects]\nbacklash_deg = []\n", ["'backlash_deg'", "must not be empty"]),
    ("stop-node", b"[encoders]\nstop_heartbeat_node = 9\n", ["'stop_heartbeat_node'", "node_ids"]),
    ("encoder-range", b"[encoders]\ncounts_per_rev = 16777216\n", ["'turns'", "32-bit"]),
    # names, and what needs the robot
    ("program", b'[cell]\nprogram = "dance"\n', ["[cell]", "'program'", "campaign"]),
    ("target", b'[tracker]\ntarget = "link"\n', ["[tracker]", "'target'", "linkN"]),
    ("target-link7", b'[tracker]\ntarget = "link7"\n', ["'target'", "6 joints"]),
    (
        "cyclic-joint",
        b"[effects.undeclared]\ncyclic_joint = 7\n",
        ["[effects.undeclared]", "'cyclic_joint'"],
    ),
    (
        "list-length",
        b"[effects]\nbacklash_deg = [0.01, 0.01, 0.01]\n",
        ["'backlash_deg'", "3 values"],
    ),
    ("node-ids-7", b"[encoders]\nnode_ids = [1, 2, 3, 4, 5, 6, 7]\n", ["'node_ids'", "7 values"]),
    # the robot the config names
    ("robot-unknown", b'[cell]\nrobot = "kr5000"\n', ["bad.toml", "[cell]", "'robot'", "kr5000"]),
    ("robot-device", b'[cell]\nrobot = "/dev/zero"\n', ["bad.toml", "'robot'", "device"]),
    ("robot-empty", b'[cell]\nrobot = ""\n', ["bad.toml", "'robot'"]),
    ("robot-latin1", b'[cell]\nrobot = "latin1.toml"\n', ["'robot'", "latin1.toml", "UTF-8"]),
]


@pytest.mark.parametrize(
    ("text", "words"), [c[1:] for c in CONFIG_CASES], ids=[c[0] for c in CONFIG_CASES]
)
def test_cell_config_refused(work, text, words):
    (work / "bad.toml").write_bytes(text)
    (work / "latin1.toml").write_bytes(HP20D.replace("Motoman", "Motomañ").encode("latin-1"))
    refused(work, [SIM_CELL, "truth", "--config", "bad.toml", "--out", "truth.toml"], words)


def test_config_files_refused(work):
    """The file itself: missing, a directory, a device, larger than the limit, no name."""
    argv = [SIM_CELL, "truth", "--out", "truth.toml", "--config"]
    refused(work, [*argv, "nope.toml"], ["nope.toml", "cannot read"])
    (work / "adir").mkdir()
    refused(work, [*argv, "adir"], ["adir", "is a directory"])
    refused(work, [*argv, "/dev/zero"], ["/dev/zero", "device"])
    (work / "big.toml").write_text("# padding\n" * 300 + "[cell]\nseed = 1\n")
    refused(
        work,
        [*argv, "big.toml"],
        ["big.toml", "input limit"],
        env={"GRATING_TWIN_MAX_INPUT_MB": "0.001"},
    )
    refused(work, [*argv, ""], ["--config", "empty path"])


def test_sim_cell_options_refused(work):
    for value in ("nan", "inf", "-5", "soon"):
        refused(
            work, [SIM_CELL, "serve", "--duration", value], ["sim-cell serve", "--duration", value]
        )
    refused(work, [SIM_CELL, "serve", "--log-level", "loud"], ["--log-level", "'LOUD'"])
    refused(work, [SIM_CELL, "serve", "--bogus"], ["unrecognized arguments: --bogus"])
    refused(work, [SIM_CELL], ["sim-cell", "required"])
    refused(work, [SIM_CELL, "truth"], ["--out", "required"])
    refused(work, [SIM_CELL, "default-config", "extra"], ["unrecognized arguments: extra"])


def test_sim_cell_outputs_refused(work):
    """An output that is an input, a directory, under a file, or nameless: refused before
    anything runs; the serving cases fail before any device starts."""
    truth = [SIM_CELL, "truth", "--config", "cell.toml", "--out"]
    refused(work, [*truth, "cell.toml"], ["--out cell.toml", "is an input"])
    (work / "uses_robot.toml").write_text('[cell]\nrobot = "robot.toml"\n')
    refused(
        work,
        [SIM_CELL, "truth", "--config", "uses_robot.toml", "--out", "robot.toml"],
        ["--out robot.toml", "is an input"],
    )
    (work / "link.toml").symlink_to("cell.toml")
    refused(work, [*truth, "link.toml"], ["--out link.toml", "is an input"])
    (work / "adir").mkdir()
    refused(work, [*truth, "adir"], ["--out adir", "is a directory"])
    refused(work, [*truth, "previous.txt/truth.toml"], ["previous.txt", "not a directory"])
    refused(work, [*truth, ""], ["--out", "empty path"])
    serve = [SIM_CELL, "serve", "--duration", "0.1", "--config"]
    refused(
        work, [*serve, "cell.toml", "--truth", "cell.toml"], ["--truth cell.toml", "is an input"]
    )
    (work / "self.toml").write_text('[cell]\ntruth_file = "self.toml"\n')
    refused(work, [*serve, "self.toml"], ["self.toml", "truth_file", "is an input"])
    (work / "rundir.toml").write_text('[cell]\nrun_dir = "previous.txt"\n')
    refused(work, [*serve, "rundir.toml"], ["rundir.toml", "'run_dir'", "not a directory"])


def _seven_joints(kr500: str) -> str:
    """The KR500 with a seventh joint after its sixth (home 0°)."""
    text = kr500.replace("home_deg = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]", "home_deg = [0.0] * 7")
    text = text.replace("home_deg = [0.0] * 7", "home_deg = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]")
    assert text != kr500
    return text + (
        "\n[[joint]]\na_mm = 0.0\nalpha_deg = 90.0\nd_mm = 100.0\ntheta_offset_deg = 0.0\n"
        "lower_deg = -170.0\nupper_deg = 170.0\ngear_ratio = 100.0\n"
    )


def test_serve_refuses_a_robot_the_grating_box_cannot_serve(work):
    """A 7-joint robot ended as an internal error (exit 70) of the grating device: the box
    has 6 channels, and the configuration check now knows it (``sim-cell truth``, whose
    plant is built for the same box, crashed the same way)."""
    (work / "r7.toml").write_text(_seven_joints(_preset("kr500")))
    (work / "c7.toml").write_text('[cell]\nrobot = "r7.toml"\n')
    words = ["c7.toml", "'robot'", "7 joints", "6 channels"]
    refused(work, [SIM_CELL, "serve", "--config", "c7.toml", "--duration", "2"], words)
    refused(work, [SIM_CELL, "truth", "--config", "c7.toml", "--out", "truth.toml"], words)


def test_maps_vs_truth_refuses_like_every_command(work):
    """``python -m benchmarks.maps_vs_truth`` (a README command) had no error boundary:
    a missing file or a bad cell was a traceback."""
    (work / "r7.toml").write_text(_seven_joints(_preset("kr500")))
    (work / "c7.toml").write_text('[cell]\nrobot = "r7.toml"\n')
    (work / "noise.mcap").write_bytes(bytes(range(256)) * 4)
    maps = [PY, "-m", "benchmarks.maps_vs_truth"]
    # benchmarks/ is not installed: a user runs it from the checkout (README)
    checkout = {"PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    refused(work, maps, ["recording", "required"], checkout)
    refused(work, [*maps, "nope.mcap", "cell.toml"], ["nope.mcap"], checkout)
    refused(work, [*maps, "noise.mcap", "nope.toml"], ["nope.toml"], checkout)
    refused(work, [*maps, "noise.mcap", "c7.toml"], ["c7.toml", "7 joints"], checkout)
    refused(work, [*maps, "noise.mcap", "cell.toml"], ["noise.mcap"], checkout)


@pytest.mark.parametrize("grating", [False, True], ids=["tracker-alone", "grating-started-first"])
def test_serve_port_in_use_leaves_nothing(work, grating):
    """A failure after the run started: the tracker's port is taken. No device is
    announced, no truth file appears (it is committed only once every device listens)."""
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        (work / "ports.toml").write_text(
            f"[grating]\nenabled = {str(grating).lower()}\n[encoders]\nenabled = false\n"
            f"[tracker]\nserial = false\ntcp_port = {port}\n"
        )
        refused(
            work,
            [SIM_CELL, "serve", "--config", "ports.toml", "--duration", "5", "--truth", "t.toml"],
            ["ports.toml", "tracker", "Address already in use", f"tcp_port = {port}"],
        )


# -- the generators ----------------------------------------------------------------------
SCALE = [PY, "-m", "sim_devices.scale_campaign", "--out", "camp", "--joints", "1"]
SCALE += ["--arc-deg", "10", "--stops-per-arc", "3"]  # a small campaign: 6 stops
SCALE_CASES: list[tuple[list[str], list[str]]] = [
    (["--joints", "7"], ["--joints", "joint 7", "1..6"]),
    (["--joints", "1,1"], ["--joints", "joint 1 given twice"]),
    (["--joints", "a"], ["--joints", "'a'"]),
    (["--joints", "0"], ["--joints", "numbered from 1"]),
    (["--joints", ","], ["--joints", "joint numbers like"]),
    (["--joints", "1,,2"], ["--joints", "joint numbers like"]),
    (["--joints", "1.5"], ["--joints", "'1.5'"]),
    (["--joints", ""], ["--joints", "got nothing"]),
    (["--no-home", "2"], ["--no-home", "joint 2 is not swept"]),
    (["--no-home", "9"], ["--no-home", "joint 9"]),
    (["--seed", "-1"], ["--seed", "0..4294967295"]),
    (["--seed", "nan"], ["--seed", "integer"]),
    (["--seed", "1.5"], ["--seed", "integer"]),
    (["--seed", "99999999999"], ["--seed", "0..4294967295"]),
    (["--eccentricity-mm", "nan"], ["--eccentricity-mm", "finite"]),
    (["--eccentricity-mm", "-0.1"], ["--eccentricity-mm", "0..1"]),
    (["--eccentricity-mm", "5"], ["--eccentricity-mm", "0..1"]),
    (["--hysteresis-counts", "inf"], ["--hysteresis-counts", "finite"]),
    (["--settling-deg", "nan"], ["--settling-deg", "finite"]),
    (["--settling-deg", "-1"], ["--settling-deg", "0..10"]),
    (["--wild-points", "-1"], ["--wild-points", "0..100000"]),
    (["--wild-points", "2.5"], ["--wild-points", "integer"]),
    (["--targets", "0"], ["--targets", "1..12"]),
    (["--targets", "13"], ["--targets", "1..12"]),
    (["--arc-deg", "0"], ["--arc-deg", "> 0"]),
    (["--arc-deg", "nan"], ["--arc-deg", "finite"]),
    (["--stops-per-arc", "1"], ["--stops-per-arc", "2..10000"]),
    (["--effect", "sag"], ["--effect", "'sag'"]),
    (["--robot", "kr5000"], ["--robot kr5000", "no such file", "presets"]),
    (["--robot", "/dev/zero"], ["--robot /dev/zero", "device"]),
    (["--robot", "latin1.toml"], ["--robot latin1.toml", "UTF-8"]),
    (["--robot", "binary.toml"], ["--robot binary.toml"]),
    (["--robot", "adir"], ["--robot adir", "directory"]),
    (["--out", "previous.txt"], ["--out previous.txt", "not a directory"]),
    (["--out", ""], ["--out", "empty path"]),
]


def _generator_inputs(work: Path) -> None:
    (work / "latin1.toml").write_bytes(HP20D.replace("Motoman", "Motomañ").encode("latin-1"))
    (work / "binary.toml").write_bytes(bytes(range(256)) * 4)
    (work / "adir").mkdir()


@pytest.mark.parametrize(
    ("extra", "words"), SCALE_CASES, ids=[" ".join(c[0]) or "empty" for c in SCALE_CASES]
)
def test_scale_campaign_refused(work, extra, words):
    _generator_inputs(work)
    refused(work, [*SCALE, *extra], ["python -m sim_devices.scale_campaign: error:", *words])


def test_scale_campaign_output_onto_robot(work):
    """--out is the robot file: an output that is an input is refused, whatever its kind."""
    refused(
        work,
        [*SCALE, "--robot", "robot.toml", "--out", "robot.toml"],
        ["--out robot.toml", "is an input"],
    )


def test_scale_campaign_fails_after_the_run_and_keeps_the_old_files(work):
    """The campaign runs, then one of the three files cannot be placed (its name is a
    directory): none of the three is written, the earlier home.csv stays as it was."""
    old = work / "old"
    (old / "sweep.csv").mkdir(parents=True)
    (old / "home.csv").write_text("joint,trial,counts\n1,1,42\n")
    refused(work, [*SCALE, "--out", "old"], ["sweep.csv", "is a directory"])


POSE = [PY, "-m", "sim_devices.pose_campaign", "--out", "campaign.csv"]
POSE += ["--identify", "3", "--validate", "1", "--selection", "none"]  # 4 poses
POSE_CASES: list[tuple[list[str], list[str]]] = [
    (["--identify", "0"], ["--identify", "1..10000"]),
    (["--identify", "nan"], ["--identify", "integer"]),
    (["--identify", "-3"], ["--identify", "1..10000"]),
    (["--identify", "20000"], ["--identify", "1..10000"]),
    (["--validate", "-1"], ["--validate", "0..10000"]),
    (["--validate", "inf"], ["--validate", "integer"]),
    (["--selection", "O9"], ["--selection", "'O9'"]),
    (["--effect", "bogus"], ["--effect", "'bogus'"]),
    (["--seed", "nan"], ["--seed", "integer"]),
    (["--robot", "kr5000"], ["--robot kr5000", "no such file"]),
    (["--robot", "/dev/zero"], ["--robot /dev/zero", "device"]),
    (["--robot", "latin1.toml"], ["--robot latin1.toml", "UTF-8"]),
    (["--truth", "campaign.csv"], ["--truth campaign.csv", "also given as --out"]),
    (["--robot", "robot.toml", "--out", "robot.toml"], ["--out robot.toml", "is an input"]),
    (["--out", "adir"], ["--out adir", "is a directory"]),
    (["--truth", "adir"], ["--truth adir", "is a directory"]),
    (["--out", ""], ["--out", "empty path"]),
    (["--truth", ""], ["--truth", "empty path"]),
]


@pytest.mark.parametrize(("extra", "words"), POSE_CASES, ids=[" ".join(c[0]) for c in POSE_CASES])
def test_pose_campaign_refused(work, extra, words):
    _generator_inputs(work)
    refused(work, [*POSE, *extra], ["python -m sim_devices.pose_campaign: error:", *words])


def test_pose_campaign_fails_late_and_writes_nothing(work):
    """Found bad only while running: no pose of this robot is in the tracker's range.
    Neither campaign.csv nor the truth appears."""
    (work / "far.toml").write_text(FAR_ROBOT)
    refused(
        work,
        [*POSE, "--robot", "far.toml", "--truth", "out/truth.toml"],
        ["pose_campaign: error:", "reachable", "tracker's range"],
    )


REPORT = [PY, "-m", "sim_devices.physics_report", "--poses", "4"]
REPORT_CASES: list[tuple[list[str], list[str]]] = [
    (["--poses", "1"], ["--poses", "2..10000"]),
    (["--poses", "nan"], ["--poses", "integer"]),
    (["--poses", "20000"], ["--poses", "2..10000"]),
    (["--seed", "-1"], ["--seed", "0..4294967295"]),
    (["--seed", "x"], ["--seed", "integer"]),
    (["--robot", "nope"], ["--robot nope", "no such file"]),
    (["--robot", "hp20d", "nope"], ["--robot nope", "no such file"]),
    (["--robot"], ["--robot", "expected at least one argument"]),
]


@pytest.mark.parametrize(
    ("extra", "words"), REPORT_CASES, ids=[" ".join(c[0]) for c in REPORT_CASES]
)
def test_physics_report_refused(work, extra, words):
    refused(work, [*REPORT, *extra], ["python -m sim_devices.physics_report: error:", *words])


# -- what is accepted, and that success leaves exactly its outputs -----------------------
def test_accepted_variants_give_the_same_cell(work):
    """Empty, comments only, header only: the default cell. BOM, CRLF, tables in another
    order: the same cell as the plain file (and the same truth file)."""
    plain = '[cell]\nseed = 4\nprogram = "hold"\n[grating]\nrate_hz = 500.0\n'
    variants = {
        "bom.toml": ("\ufeff" + plain).encode("utf-8"),
        "crlf.toml": plain.replace("\n", "\r\n").encode("utf-8"),
        "order.toml": b'[grating]\nrate_hz = 500.0\n[cell]\nprogram = "hold"\nseed = 4\n',
    }
    (work / "plain.toml").write_text(plain)
    for name, raw in variants.items():
        (work / name).write_bytes(raw)
        assert CellConfig.load(work / name) == CellConfig.load(work / "plain.toml"), name
    for name, text in {
        "empty.toml": "",
        "comments.toml": "# nothing\n\n",
        "header.toml": "[cell]\n",
    }.items():
        (work / name).write_text(text)
        assert CellConfig.load(work / name) == CellConfig(), name
    for name in ("plain.toml", "bom.toml", "crlf.toml"):
        proc = run([SIM_CELL, "truth", "--config", name, "--out", f"out/{name}"], work)
        assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    texts = {(work / "out" / n).read_text() for n in ("plain.toml", "bom.toml", "crlf.toml")}
    assert len(texts) == 1


def test_generators_write_exactly_their_outputs(work):
    """Directories created, the outputs and nothing else (no staging leftover)."""
    before = set(snapshot(work))
    proc = run([*SCALE, "--out", "deep/camp"], work)
    assert proc.returncode == 0, proc.stderr
    proc = run([*POSE, "--out", "p/campaign.csv", "--truth", "p/t/truth.toml"], work)
    assert proc.returncode == 0, proc.stderr
    new = set(snapshot(work)) - before
    assert new == {
        "deep", "deep/camp", "deep/camp/home.csv", "deep/camp/sweep.csv", "deep/camp/truth.toml",
        "p", "p/campaign.csv", "p/t", "p/t/truth.toml",
    }  # fmt: skip
    proc = run([SIM_CELL, "--debug", "truth", "--config", "nope.toml", "--out", "x.toml"], work)
    assert proc.returncode == 2 and "Traceback" in proc.stderr  # --debug shows it


def test_serve_writes_the_truth_when_the_devices_listen(work):
    (work / "one.toml").write_text(
        '[cell]\nprogram = "hold"\n[encoders]\nenabled = false\n[tracker]\nenabled = false\n'
    )
    proc = run(
        [SIM_CELL, "serve", "--config", "one.toml", "--duration", "0.3", "--truth", "t/t.toml"],
        work,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count('"kind": "grating_reader"') == 1
    assert (work / "t" / "t.toml").exists()
    assert not [p for p in (work / "t").iterdir() if ".partial-" in p.name]


# -- hypothesis: the reader and the option parsers ---------------------------------------
DEFAULT_TEXT = CellConfig().dumps()
TOKENS = [
    "nan", "inf", "-inf", "-1", "0", "1e400", "99999999999999999999", '"x"', "true", "[]",
    "[1, 1]", "[", "]", "=", "\n", "[cell]\n", "[bogus]\n", "\x00", "\ufeff", "\r\n", "#",
    "'", '"', "{", "}", ".", "link9", "[effects.undeclared]\nlag_joint = 9\n",
]  # fmt: skip


def _valid(cfg: CellConfig) -> None:
    """A config the reader accepted: every number finite (bar an inf stiffness: rigid),
    and it survives its own round trip."""
    assert CellConfig.loads(cfg.dumps()) == cfg

    def walk(value, key=""):
        if isinstance(value, dict):
            for k, v in value.items():
                walk(v, k)
        elif isinstance(value, list | tuple):
            for v in value:
                walk(v, key)
        elif isinstance(value, float):
            assert math.isfinite(value) or key == "deflection_stiffness_nmm_per_rad", key

    walk(cfg.to_document())


def _outcome(load) -> None:
    try:
        cfg = load()
    except SimError as exc:
        assert "\n" not in str(exc)
        return
    _valid(cfg)


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz-cell")


@FUZZ
@given(raw=st.binary(max_size=400))
def test_fuzz_config_bytes(fuzz_dir, raw):
    path = fuzz_dir / "fuzz.toml"
    path.write_bytes(raw)
    _outcome(lambda: CellConfig.load(path))


@FUZZ
@given(data=st.data())
def test_fuzz_config_mutations(fuzz_dir, data):
    text = DEFAULT_TEXT
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["truncate", "delete", "insert", "replace-number"]))
        i = data.draw(st.integers(0, len(text)))
        if op == "truncate":
            text = text[:i]
        elif op == "delete":
            text = text[:i] + text[i + data.draw(st.integers(1, 40)) :]
        elif op == "insert":
            text = text[:i] + data.draw(st.sampled_from(TOKENS)) + text[i:]
        else:
            numbers = list(re.finditer(r"(?<==\s)-?[0-9][0-9.e+_-]*", text))
            if numbers:
                m = data.draw(st.sampled_from(numbers))
                text = text[: m.start()] + data.draw(st.sampled_from(TOKENS)) + text[m.end() :]
    _outcome(lambda: CellConfig.loads(text, source="fuzz.toml"))
    raw = text.encode("utf-8", "surrogatepass")
    path = fuzz_dir / "mut.toml"
    path.write_bytes(raw)
    _outcome(lambda: CellConfig.load(path))


@FUZZ
@given(st.text(max_size=30))
def test_fuzz_option_parsers(text):
    try:
        joints = joint_list(text)
    except argparse.ArgumentTypeError:
        pass
    else:
        assert joints and len(set(joints)) == len(joints) and min(joints) >= 1
    try:
        v = number_option(0.0, 10.0)(text)
    except argparse.ArgumentTypeError:
        pass
    else:
        assert math.isfinite(v) and 0.0 <= v <= 10.0
    try:
        n = integer_option(1, 100)(text)
    except argparse.ArgumentTypeError:
        pass
    else:
        assert 1 <= n <= 100


def test_every_range_names_a_real_key():
    """A typo in the table of ranges would leave a key unchecked."""
    doc = CellConfig().to_document()
    for dotted in RANGES:
        node = doc
        for part in dotted.split("."):
            assert part in node, dotted
            node = node[part]
