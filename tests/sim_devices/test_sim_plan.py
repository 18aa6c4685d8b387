"""The emulated cell runs a plan: ``[cell] plan = "campaign_joints.csv"`` (``twin plan``'s
joint list) is the campaign's pose phase, identify poses then validate poses in the plan's
order, the scale-calibration phases as in the default campaign; a bad plan file is one line
naming the file, its line and column (``sim-cell``, exit 2, nothing written)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.cli import main as twin_main
from sim_devices.config import CellConfig, load_cell
from sim_devices.plant import Plant
from sim_devices.tracker_view import cell_geometry, true_view_codes
from tests import bad_input

SIM_CELL = str(Path(sys.executable).parent / "sim-cell")


@pytest.fixture(scope="module")
def plan_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("plan") / "plan"
    argv = ["plan", "--robot", "kr500", "--poses", "6", "--validate", "4", "--no-sweeps"]
    assert twin_main([*argv, "--candidates", "300", "--out", str(out)]) == 0
    return out


def _rows(plan_dir: Path) -> tuple[list[str], np.ndarray]:
    lines = (plan_dir / "campaign_joints.csv").read_text(encoding="utf-8").splitlines()[1:]
    sets = [line.split(",")[1] for line in lines]
    q = np.array([[float(v) for v in line.split(",")[2:]] for line in lines])
    return sets, q


def _poses(plant: Plant) -> tuple[list[str], np.ndarray]:
    """The program's pose dwells: labels and commanded angles (deg)."""
    sched = [s for s in plant.trajectory.schedule() if s["label"].startswith(("ident", "valid"))]
    t = np.array([0.5 * (s["arrive_s"] + s["leave_s"]) for s in sched])
    return [s["label"] for s in sched], np.degrees(plant.joint_state(t).q_cmd_rad)


def test_the_campaign_runs_the_plan_identify_then_validate_in_its_order(plan_dir, tmp_path):
    cell = tmp_path / "cell.toml"
    cell.write_text(f'[cell]\nplan = "{plan_dir / "campaign_joints.csv"}"\n', encoding="utf-8")
    planned = Plant.from_config(load_cell(str(cell)))
    sets, q = _rows(plan_dir)
    labels, q_prog = _poses(planned)
    order = [i for i, s in enumerate(sets) if s == "identify"]
    order += [i for i, s in enumerate(sets) if s == "validate"]
    assert order != list(range(len(sets)))  # the tour mixes the sets: reordered here
    assert labels == [f"identification {k}" for k in range(6)] + [
        f"validation {k}" for k in range(4)
    ]
    np.testing.assert_allclose(q_prog, q[order], atol=1e-9)
    # the scale-calibration phases are the default campaign's, move for move
    default = Plant.from_config(CellConfig()).trajectory
    k = planned.trajectory.labels.index("identification 0")
    assert planned.trajectory.labels[:k] == default.labels[:k]
    np.testing.assert_array_equal(planned.trajectory.q0_rad[:k], default.q0_rad[:k])
    # every planned pose in view of the emulated tracker, on the true arm
    geometry = cell_geometry(planned.cell, planned.config.geometry)
    assert not true_view_codes(planned.cell, geometry, np.radians(q_prog)).any()
    # a relative path is relative to the cell file, not the working directory
    (tmp_path / "sub" / "p").mkdir(parents=True)
    (tmp_path / "sub" / "cell.toml").write_text(
        '[cell]\nplan = "p/campaign_joints.csv"\n', encoding="utf-8"
    )
    (tmp_path / "sub" / "p" / "campaign_joints.csv").write_bytes(
        (plan_dir / "campaign_joints.csv").read_bytes()
    )
    again = Plant.from_config(load_cell(str(tmp_path / "sub" / "cell.toml")))
    np.testing.assert_array_equal(_poses(again)[1], q_prog)


BAD_PLANS = [
    # (case, csv text, key words of the one line)
    ("not-a-number", "pose,set,{q}\n1,identify,{row_x}\n", ["line 2", "column 'q3_deg'", "'x'"]),
    ("limits", "pose,set,{q}\n1,identify,{row_far}\n", ["line 2", "q1_deg", "joint limits"]),
    ("set", "pose,set,{q}\n1,identify,{row}\n2,check,{row}\n", ["line 3", "'set'", "'check'"]),
    ("column", "pose,set,q1_deg\n1,identify,0\n", ["header", "missing column", "q2_deg"]),
    ("no-identify", "pose,set,{q}\n1,validate,{row}\n", ["no 'identify' pose"]),
    ("duplicate", "pose,set,{q}\n1,identify,{row}\n1,validate,{row}\n", ["line 3", "duplicated"]),
    ("empty", "", ["empty file"]),
]


@pytest.mark.parametrize(("case", "text", "words"), BAD_PLANS, ids=[c[0] for c in BAD_PLANS])
def test_a_bad_plan_is_one_line_naming_file_line_and_column(tmp_path, case, text, words):
    q = ",".join(f"q{j}_deg" for j in range(1, 7))
    row = "10,20,-30,5,40,0"
    csv = text.format(
        q=q, row=row, row_x="10,20,x,5,40,0", row_far="400,20,-30,5,40,0"
    )  # fmt: skip
    (tmp_path / "plan.csv").write_text(csv, encoding="utf-8")
    (tmp_path / "cell.toml").write_text('[cell]\nplan = "plan.csv"\n', encoding="utf-8")
    argv = [SIM_CELL, "truth", "--config", "cell.toml", "--out", "truth.toml"]
    bad_input.refused(tmp_path, argv, ["cell.toml", "[cell]", "'plan'", "plan.csv", *words])


def test_a_plan_needs_the_campaign_program_and_an_existing_file(tmp_path):
    (tmp_path / "hold.toml").write_text(
        '[cell]\nprogram = "hold"\nplan = "p.csv"\n', encoding="utf-8"
    )
    argv = [SIM_CELL, "truth", "--config", "hold.toml", "--out", "truth.toml"]
    bad_input.refused(tmp_path, argv, ["hold.toml", "'plan'", "'campaign' program"])
    (tmp_path / "gone.toml").write_text('[cell]\nplan = "gone.csv"\n', encoding="utf-8")
    argv = [SIM_CELL, "truth", "--config", "gone.toml", "--out", "truth.toml"]
    bad_input.refused(tmp_path, argv, ["gone.toml", "'plan'", "gone.csv"])
    # the plan is an input: the truth cannot be written over it
    q = ",".join(f"q{j}_deg" for j in range(1, 7))
    (tmp_path / "p.csv").write_text(f"pose,set,{q}\n1,identify,0,0,0,0,30,0\n", encoding="utf-8")
    (tmp_path / "onto.toml").write_text('[cell]\nplan = "p.csv"\n', encoding="utf-8")
    argv = [SIM_CELL, "truth", "--config", "onto.toml", "--out", "p.csv"]
    bad_input.refused(tmp_path, argv, ["p.csv"])
