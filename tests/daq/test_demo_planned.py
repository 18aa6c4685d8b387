"""A planned campaign through the whole chain, in real time over loopback: ``twin plan`` →
the emulated cell running it (``python -m daq.demo --plan DIR --record-only``: ``sim-cell``
under ``daq run``, recorded to MCAP, the tracker honouring the reflector's cone) → ``twin
run --replay --identify-poses N`` calibrates from the recording with every planned pose
measured (of the default campaign's 250 random poses the emulator's geometry puts 243 out of
the cone, docs/planning.md).

Kept short: a KR500 with its joint ranges narrowed (the sweeps limit to limit are most of
the program), 12 + 8 planned poses, the program at 160x (the recorded small campaign's
speed, docs/twin-run.md). Like that recording it needs a host the daemon keeps up on: at
load 15-20 on two cores the grating's clock mapping did not settle in most runs
(docs/planning.md, "The emulated cell runs a plan").
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from calibration.cli import main as twin_main
from calibration.model.description import PRESET_PACKAGE
from daq import demo
from daq.testing import free_port

#: (lower, upper) deg of the narrowed arm; Home (0) inside each, the wrist kept off 0 by
#: the planner's singularity margin
NARROW = ((-40, 40), (-20, 40), (-60, 20), (-40, 40), (-70, 70), (-60, 60))
N_IDENTIFY, N_VALIDATE = 12, 8


def narrow_kr500() -> str:
    """The KR500 preset with the joint limits of :data:`NARROW`."""
    from importlib.resources import files

    text = files(PRESET_PACKAGE).joinpath("kr500.toml").read_text(encoding="utf-8")
    head, *joints = text.split("[[joint]]")
    out = [head]
    for block, (lo, hi) in zip(joints, NARROW, strict=True):
        block = re.sub(r"lower_deg = [-0-9.]+", f"lower_deg = {lo:.1f}", block)
        out.append(re.sub(r"upper_deg = [-0-9.]+", f"upper_deg = {hi:.1f}", block))
    return "[[joint]]".join(out)


@pytest.mark.timeout(300)
# ~60 s of real time, the longest of the real-time tests: `make soak` runs it (`pytest -m
# slow tests/daq/test_demo_planned.py`); `make test` keeps the plan's pieces (the cell
# running it, tests/sim_devices/test_sim_plan.py; the demo's options,
# tests/daq/test_demo_plan_options.py) within its 15 minutes
@pytest.mark.slow
def test_a_planned_campaign_is_recorded_and_calibrated_with_every_pose_measured(tmp_path):
    robot = tmp_path / "narrow_kr500.toml"
    robot.write_text(narrow_kr500(), encoding="utf-8")
    plan = tmp_path / "plan"
    argv = ["plan", "--robot", str(robot), "--poses", str(N_IDENTIFY)]
    argv += ["--validate", str(N_VALIDATE), "--candidates", "400", "--out", str(plan)]
    assert twin_main(argv) == 0
    rec = tmp_path / "rec"
    argv = ["--robot", str(robot), "--plan", str(plan), "--speed", "160", "--no-encoders"]
    argv += ["--port", str(free_port()), "--progress-s", "0", "--out", str(rec)]
    assert demo.main([*argv, "--record-only"]) == 0
    sim = (rec / "sim-cell.toml").read_text(encoding="utf-8")
    assert "line_of_sight = true" in sim and "campaign_joints.csv" in sim
    out = tmp_path / "twin"
    argv = ["run", "--replay", str(rec / "campaign.mcap"), "--robot", str(robot)]
    argv += ["--identify-poses", str(N_IDENTIFY), "--no-report", "--out", str(out)]
    rc = twin_main(argv)
    phases = json.loads((out / "phases.json").read_text())
    assert rc == 0, phases
    assert phases["phases"]["poses"] == {"identify": N_IDENTIFY, "validate": N_VALIDATE}
    # every planned pose measured (none lost to the cone), in the plan's sets and order
    lines = (plan / "campaign_joints.csv").read_text(encoding="utf-8").splitlines()[1:]
    sets = [x.split(",")[1] for x in lines]
    q_plan = np.array([[float(v) for v in x.split(",")[2:]] for x in lines])
    order = [i for i, s in enumerate(sets) if s == "identify"]
    order += [i for i, s in enumerate(sets) if s == "validate"]
    rows = (out / "campaign.csv").read_text(encoding="utf-8").splitlines()
    header = rows[0].split(",")
    table = [dict(zip(header, r.split(","), strict=True)) for r in rows[1:]]
    assert len(table) == N_IDENTIFY + N_VALIDATE
    assert [r["set"] for r in table] == [sets[i] for i in order]
    q_read = np.array([[float(r[f"q{j}_deg"]) for j in range(1, 7)] for r in table])
    # the gratings read the planned angles (the scale maps' error and the gear's torsion
    # under load are hundredths of a degree)
    np.testing.assert_allclose(q_read, q_plan[order], atol=0.1)
    report = json.loads((out / "report" / "report.json").read_text())
    stages = report["closed_loop"]["stages"]
    val = [s["sets"]["validate"]["AP"]["mean"] for s in stages]
    assert val[-1] < 0.5 * val[0], val  # calibrated from the recording: nominal → final
