"""The planning proof's machinery on one small seed (the proof itself:
``python -m benchmarks.bench_plan``, docs/planning.md): a plan measured on the emulated
truth with its effects on, calibrated as a user would, against random in-view campaigns
(``python -m pytest -m slow tests/test_bench_plan.py``), and the planner's predicted
variance against random poses'."""

from __future__ import annotations

import importlib
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.model.cell_geometry import CellGeometrySpec, resolve
from calibration.model.description import load_robot
from calibration.plan.campaign_plan import PlanSettings, plan_campaign

ROOT = str(Path(__file__).resolve().parents[2])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
bench_plan = importlib.import_module("benchmarks.bench_plan")

pytestmark = pytest.mark.timeout(120)


@pytest.mark.slow  # three closed-loop calibrations: ~20 s alone, a minute on a loaded host
def test_planned_campaign_on_the_emulated_cell() -> None:
    o = bench_plan.run_seed(3, n_candidates=400, n_plan=20)
    assert o.hidden == 0  # the emulator's truth sees every planned pose, none collides
    assert o.travel_ratio <= 0.6
    for err in (o.planned_mm, o.random50_mm, o.random150_mm):
        assert math.isfinite(err) and 0.0 < err < 1.0  # calibrated: well under the 1+ mm raw


def test_plan_predicts_less_variance_than_random_poses() -> None:
    robot = load_robot("kr500")
    g = resolve(CellGeometrySpec(), robot)
    for seed in (1, 2):
        plan = plan_campaign(robot, g, PlanSettings(20, 5, n_candidates=400, seed=seed))
        assert plan.selection.i_value_mm2 < 0.7 * plan.random_i_value_mm2  # same prior
        assert np.all(plan.parameter_sigma[:10] <= plan.random_parameter_sigma[:10] * 1.5)


def test_the_proofs_truth_is_chosen_on_the_command_line() -> None:
    """``--effects`` and ``--set`` give the emulator's effects; a key or value that is not
    one is refused in words (the proof on truths the default cell does not draw)."""
    truth = bench_plan.truth_effects
    assert truth(False, None, []) == bench_plan.EFFECTS
    coupled = truth(False, "gravity_deflection,joint_coupling", ["coupling_coefficient=0.3"])
    assert coupled.active == ("gravity_deflection", "joint_coupling")
    assert coupled.coupling_coefficient == 0.3
    lost = truth(False, "lost_motion", ["lost_motion_deg=[0, 0.01, 0, 0, 0, 0]"])
    assert lost.lost_motion_deg == (0, 0.01, 0, 0, 0, 0)
    assert truth(True, None, ["cyclic_joint=3"]).active == ()
    for bad in (["cyclic_joint"], ["no_such_key=1"], ["cyclic_joint=three"]):
        with pytest.raises(ValueError, match="--set"):
            truth(False, None, bad)
    with pytest.raises(ValueError, match="unknown effect 'gravity'"):
        truth(False, "gravity", [])
