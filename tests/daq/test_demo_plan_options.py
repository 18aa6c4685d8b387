"""``python -m daq.demo --plan DIR``, checked before anything runs: the cell it writes runs
the plan with the tracker's line of sight on and a start hold, the default campaign is
untouched without it, and a bad plan is one line naming the file, line and column (exit 2,
nothing written). The recording itself: tests/daq/test_demo_planned.py (real time)."""

from __future__ import annotations

import argparse

import pytest

from daq import demo
from tests.bad_input import assert_refusal, snapshot

Q = ",".join(f"q{j}_deg" for j in range(1, 7))


def _args(**over: object) -> argparse.Namespace:
    return demo.build_parser().parse_args(
        [x for k, v in over.items() for x in (f"--{k.replace('_', '-')}", str(v))]
    )


def test_a_plan_becomes_the_campaigns_poses_and_the_default_is_untouched(tmp_path):
    plan = tmp_path / "plan"
    plan.mkdir()
    rows = ["1,validate,10,5,-5,0,30,0", "2,identify,-10,5,-5,0,-30,0", "3,identify,0,10,0,5,40,5"]
    (plan / "campaign_joints.csv").write_text(f"pose,set,{Q}\n" + "\n".join(rows) + "\n")
    text, length, n_identify = demo.prepare(_args(plan=plan), tmp_path / "sim-cell.toml")
    assert n_identify == 2
    assert f'plan = "{(plan / "campaign_joints.csv").resolve()}"' in text
    assert "line_of_sight = true" in text and "start_hold_s = 800" in text  # 8 s at 100x
    default_text, default_length, default_n = demo.prepare(_args(), tmp_path / "d.toml")
    assert "plan" not in default_text and "line_of_sight" not in default_text
    assert default_n == 100 and default_length > length


@pytest.mark.parametrize(
    ("case", "csv", "words"),
    [
        ("no-file", None, ["--plan", "no campaign_joints.csv"]),
        ("bad-angle", f"pose,set,{Q}\n1,identify,0,0,zz,0,30,0\n", ["line 2", "'q3_deg'"]),
        ("bad-set", f"pose,set,{Q}\n1,both,0,0,0,0,30,0\n", ["line 2", "'set'", "'both'"]),
    ],
)
def test_a_bad_plan_is_one_line_and_nothing_written(tmp_path, capsys, case, csv, words):
    plan = tmp_path / "plan"
    plan.mkdir()
    if csv is not None:
        (plan / "campaign_joints.csv").write_text(csv, encoding="utf-8")
        words = ["campaign_joints.csv", "[cell]", "'plan'", *words]
    before = snapshot(tmp_path)
    rc = demo.main(["--plan", str(plan), "--out", str(tmp_path / "out"), "--port", "17999"])
    assert_refusal(rc, capsys.readouterr().err, words, before, snapshot(tmp_path))
