"""Closed loop: its cost against the geometric identification alone, in the same run.

    python -m benchmarks --only closed_loop          # 100, 300, 1000 identification poses
    python -m benchmarks --only closed_loop --quick  # smoke run, numbers mean nothing

The whole loop (every candidate kind, 77 candidates plus the gravity term on a KR500, lag
profiles, the physical gravity form, the validation guard) on an emulated KR500 campaign
with gravity deflection (the emulator's own masses and counterbalance; the twin given no
mass model), against the geometric identification of the same poses. Its accuracy is the
attribution matrix's (``python -m benchmarks.bench_attribution``).
"""

from __future__ import annotations

from functools import partial
from typing import Any

from benchmarks import best_time
from benchmarks.bench_attribution import twin_description
from calibration.effects.closed_loop import run_closed_loop
from calibration.identify.campaign_files import Campaign
from calibration.identify.identification import identify
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign

Row = dict[str, Any]


def _timing_case(n: int) -> tuple[RobotDescription, Campaign]:
    settings = CampaignSettings(
        n_identify=n,
        n_validate=50,
        selection=None,
        effects=UndeclaredEffects.named("gravity_deflection"),
    )
    data = emulated_campaign("kr500", 1, settings)
    return twin_description(data.cell.nominal, "none"), data.campaign


def _loop_into(results: list, desc: RobotDescription, campaign: Campaign) -> None:
    results.append(run_closed_loop(desc, campaign))


def timing_rows(sizes: tuple[int, ...], repeat: int) -> list[Row]:
    rows = []
    for n in sizes:
        desc, c = _timing_case(n)
        idm = c.mask("identify")
        q, xyz = c.q_rad[idm], c.xyz_mm[idm]
        nominal = KinematicModel.from_description(desc)
        geo = best_time(partial(identify, nominal, q, xyz), repeat)
        results: list = []
        loop = best_time(partial(_loop_into, results, desc, c), repeat)
        added = [s.kind for s in results[-1].added]
        rows.append(
            {
                "benchmark": "loop vs geometry alone (KR500, gravity deflection, no masses)",
                "n": n,
                "ours_s": loop,
                "geometric_s": geo,
                "loop_over_geometric": loop / geo,
                "added": ",".join(added),
                "note": "best of the repeats; every candidate kind offered",
            }
        )
    return rows


def run(quick: bool) -> list[Row]:
    if quick:
        return timing_rows((40,), 1)
    return timing_rows((100, 300, 1000), 3)
