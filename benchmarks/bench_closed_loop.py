"""Closed loop: accuracy on emulated undeclared effects, and its cost against the geometry alone.

    python -m benchmarks --only closed_loop          # 5 seeds per effect and preset
    python -m benchmarks --only closed_loop --quick  # smoke run, numbers mean nothing

Accuracy rows: per undeclared effect (and clean data) and preset, over seeds, how often the
right effect was named, the validation mean AP at each stage (nominal, geometric, final),
the true model's on the same data, and the final/true ratio. Timing rows: the whole loop
against the geometric identification alone, for growing identification sets.
"""

from __future__ import annotations

import time
from functools import partial
from typing import Any

import numpy as np

from benchmarks import best_time
from calibration.campaign_files import Campaign
from calibration.closed_loop import run_closed_loop
from calibration.description import RobotDescription
from calibration.identification import identify
from calibration.kinematics import KinematicModel
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign

Row = dict[str, Any]

#: emulated effect -> the kind the loop should add (None: nothing)
EXPECTED = {
    "none": None,
    "gravity_deflection": "gravity_compliance",
    "grating_cyclic": "joint_harmonic",
    "thermal_drift": "length_drift",
    "tracker_scale": None,  # absorbed by the geometry: not identifiable, nothing added
}


def _ap(errors: np.ndarray) -> float:
    return float(np.linalg.norm(errors, axis=1).mean())


def accuracy_rows(
    robot: str, effect: str, seeds: range, settings: CampaignSettings | None = None
) -> list[Row]:
    rows = []
    named, nominal, geometric, final, true, ratio, elapsed = ([] for _ in range(7))
    for seed in seeds:
        eff = UndeclaredEffects() if effect == "none" else UndeclaredEffects.named(effect)
        base = settings or CampaignSettings()
        data = emulated_campaign(robot, seed, CampaignSettings(**{**base.__dict__, "effects": eff}))
        c = data.campaign
        vm = c.mask("validate")
        started = time.perf_counter()
        res = run_closed_loop(data.cell.nominal, c)
        elapsed.append(time.perf_counter() - started)
        kinds = [s.kind for s in res.added]
        named.append(kinds == ([EXPECTED[effect]] if EXPECTED[effect] else []))
        nominal.append(_ap(res.stages[0].errors_mm["validate"]))
        geometric.append(_ap(res.geometric.errors_mm["validate"]))
        final.append(_ap(res.final.errors_mm["validate"]))
        true.append(_ap(c.xyz_mm[vm] - data.true_prediction_mm[vm]))
        ratio.append(final[-1] / true[-1])
    rows.append(
        {
            "benchmark": f"loop accuracy, {effect}",
            "robot": robot,
            "n": len(seeds),
            "named_right": float(np.mean(named)),
            "nominal_mm": float(np.mean(nominal)),
            "geometric_mm": float(np.mean(geometric)),
            "final_mm": float(np.mean(final)),
            "true_mm": float(np.mean(true)),
            "ratio_mean": float(np.mean(ratio)),
            "ratio_max": float(np.max(ratio)),
            "ours_s": float(np.mean(elapsed)),
            "note": "validation mean AP; ratio = final / true model on the same data",
        }
    )
    return rows


def _timing_case(n: int) -> tuple[RobotDescription, Campaign]:
    settings = CampaignSettings(
        n_identify=n,
        n_validate=50,
        selection=None,
        effects=UndeclaredEffects.named("gravity_deflection"),
    )
    data = emulated_campaign("kr500", 1, settings)
    return data.cell.nominal, data.campaign


def timing_rows(sizes: tuple[int, ...], repeat: int) -> list[Row]:
    rows = []
    for n in sizes:
        desc, c = _timing_case(n)
        idm = c.mask("identify")
        q, xyz = c.q_rad[idm], c.xyz_mm[idm]
        nominal = KinematicModel.from_description(desc)
        geo = best_time(partial(identify, nominal, q, xyz), repeat)
        loop = best_time(partial(run_closed_loop, desc, c), repeat)
        rows.append(
            {
                "benchmark": "loop vs geometry alone (KR500, gravity deflection)",
                "n": n,
                "ours_s": loop,
                "geometric_s": geo,
                "loop_over_geometric": loop / geo,
                "note": "best of the repeats; one effect added, 2 search rounds",
            }
        )
    return rows


def run(quick: bool) -> list[Row]:
    if quick:
        small = CampaignSettings(n_identify=40, n_validate=20, selection=None)
        return accuracy_rows("kr500", "gravity_deflection", range(1, 2), small) + timing_rows(
            (40,), 1
        )
    rows: list[Row] = []
    for robot in ("kr500", "hp20d"):
        for effect in EXPECTED:
            rows += accuracy_rows(robot, effect, range(1, 6))
    return rows + timing_rows((100, 300, 1000), 3)
