"""Drive the emulated robot through a program of joint commands and measure its TCP.

The controller servos on the grating angles (the add-on scales' purpose): a command is
the angle the gratings must read, so the ring angle is the one whose grating reading is
the command (:func:`sim_devices.effects.grating_reading_rad` inverted by fixed point).
The emulated tracker then measures the physical TCP there: geometry errors, every
switched-on effect of the campaign's cell (deflection, drift …) and the tracker's noise,
as in :func:`sim_devices.pose_campaign.generate_campaign`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.closed_loop import run_closed_loop
from calibration.compensation import compensate
from calibration.description import load_robot
from calibration.kinematics import KinematicModel, tcp_positions
from sim_devices.effects import (
    UndeclaredEffects,
    approach_direction,
    grating_reading_rad,
    tracker_reading_mm,
    true_tcp_mm,
)
from sim_devices.pose_campaign import (
    CampaignData,
    CampaignSettings,
    emulated_campaign,
    sample_reachable_poses,
)

FloatArray = NDArray[np.float64]


def ring_angles_rad(data: CampaignData, command_rad: ArrayLike) -> FloatArray:
    """Ring angles ``(m, n)`` at which the gratings read ``command_rad`` ``(m, n)``."""
    command = np.atleast_2d(np.asarray(command_rad, dtype=float))
    q = command.copy()
    for _ in range(50):  # the cyclic error is ≪ 1 rad/rad: a contraction
        q = q - (grating_reading_rad(data.effects, q) - command)
    return q


def measure_program(
    data: CampaignData, command_deg: ArrayLike, rng: np.random.Generator, t_s: ArrayLike
) -> FloatArray:
    """The tracker's readings ``(m, 3)`` mm after driving the campaign's emulated robot to
    each joint command ``(m, n)`` deg (the gratings' angles) at times ``t_s`` ``(m,)``."""
    q = ring_angles_rad(data, np.radians(command_deg))
    cell = data.cell
    tcp = cell.tcp_mm(q)
    measured, ok = cell.tracker.measure(tcp, rng)
    for _ in range(100):  # a broken beam is measured again
        if ok.all():
            break
        again, ok_again = cell.tracker.measure(tcp[~ok], rng)
        measured[~ok], ok[~ok] = again, ok_again
    if data.effects.any_active:
        t = np.asarray(t_s, dtype=float)
        physical = true_tcp_mm(data.effects, cell.arm, q, t, approach_direction(q))
        measured = measured + (tracker_reading_mm(data.effects, physical, t) - tcp)
    return measured


@dataclass(frozen=True)
class CompensationTrial:
    """One emulated before/after: errors ``target − measured`` ``(m, 3)`` mm with the
    programmed joints (before) and the compensated ones (after), and the twin's own
    held-out prediction errors ``(v, 3)`` mm (the validation set of its campaign)."""

    before_mm: FloatArray
    after_mm: FloatArray
    twin_validation_mm: FloatArray
    refused: int  # targets the compensation refused (limits, unreachable)


def compensation_trial(
    robot: str, seed: int, effects: tuple[str, ...] = (), n_targets: int = 150
) -> CompensationTrial:
    """Calibrate an emulated campaign (the twin sees the campaign only), then drive the
    emulated robot to held-out targets with the nominal program and with the compensated
    one, and measure both with the emulated tracker.

    The program: random reachable poses the campaign never visited, 1° off every limit;
    their targets by the nominal geometry registered to the tracker (the calibrated base
    and tool: what a plain registration gives), so the programmed joints are that
    model's inverse kinematics of the targets."""
    data = emulated_campaign(
        robot,
        seed,
        CampaignSettings(n_identify=100, n_validate=150, effects=UndeclaredEffects.named(*effects)),
    )
    desc = load_robot(robot)
    loop = run_closed_loop(desc, data.campaign)
    cal = loop.calibrated_description(desc)
    rng = np.random.default_rng(seed + 1000)
    q = np.degrees(sample_reachable_poses(desc, 3 * n_targets, rng))
    lo = np.array([j.lower_deg for j in desc.joints]) + 1.0
    hi = np.array([j.upper_deg for j in desc.joints]) - 1.0
    q_prog = q[np.all((q > lo) & (q < hi), axis=1)][:n_targets]
    registered = replace(desc, base=cal.base, tool=cal.tool)
    target = tcp_positions(KinematicModel.from_description(registered), np.radians(q_prog))
    res = compensate(cal, target, q_programmed_deg=q_prog)
    t = float(data.campaign.t_s[-1]) + 5.0 * np.arange(1, len(q_prog) + 1)
    before = target - measure_program(data, q_prog, rng, t)
    ok = res.ok
    after = target[ok] - measure_program(data, res.q_deg[ok], rng, t[ok])
    return CompensationTrial(before[ok], after, loop.final.errors_mm["validate"], int((~ok).sum()))
