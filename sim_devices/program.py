"""Drive the emulated robot through a program of joint commands and measure its TCP.

The controller servos on the grating angles (the add-on scales' purpose): a command is
the angle the gratings must read, so the ring angle is the one whose grating reading is
the command (:func:`sim_devices.effects.grating_reading_rad` inverted by fixed point).
The emulated tracker then measures the physical TCP there: geometry errors, every
switched-on effect of the campaign's cell (deflection, drift …) and the tracker's noise,
as in :func:`sim_devices.pose_campaign.generate_campaign`. A process force on the tool
(N, tracker frame) deflects the joints after their rings by the arm's own compliance
(:func:`sim_devices.effects.force_rotation_rad`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.closed_loop import run_closed_loop
from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel, tcp_positions
from calibration.model.stiffness import ComplianceFit, fit_joint_compliance
from calibration.twin.compensation import compensate
from sim_devices.effects import (
    UndeclaredEffects,
    approach_direction,
    force_stiffness_nmm_per_rad,
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
    data: CampaignData,
    command_deg: ArrayLike,
    rng: np.random.Generator,
    t_s: ArrayLike,
    force_n: ArrayLike | None = None,
) -> FloatArray:
    """The tracker's readings ``(m, 3)`` mm after driving the campaign's emulated robot to
    each joint command ``(m, n)`` deg (the gratings' angles) at times ``t_s`` ``(m,)``,
    with an optional process force ``(m, 3)`` N on the tool (tracker frame)."""
    q = ring_angles_rad(data, np.radians(command_deg))
    cell = data.cell
    tcp = cell.tcp_mm(q)
    measured, ok = cell.tracker.measure(tcp, rng)
    for _ in range(100):  # a broken beam is measured again
        if ok.all():
            break
        again, ok_again = cell.tracker.measure(tcp[~ok], rng)
        measured[~ok], ok[~ok] = again, ok_again
    if data.effects.any_active or force_n is not None:
        t = np.asarray(t_s, dtype=float)
        direction = approach_direction(q)
        physical = true_tcp_mm(data.effects, cell.arm, q, t, direction, force_n)
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


@dataclass(frozen=True)
class CalibratedCell:
    """An emulated campaign, the twin's calibration of it (from the campaign only), and
    its held-out program: joints ``(m, n)`` deg and their targets ``(m, 3)`` mm."""

    data: CampaignData
    calibrated: RobotDescription
    twin_validation_mm: FloatArray
    q_programmed_deg: FloatArray
    target_mm: FloatArray
    t_s: FloatArray  # (m,) when the program runs, after the campaign
    rng: np.random.Generator  # the program's (poses drawn, measurements to come)


def calibrated_cell(
    robot: str, seed: int, effects: tuple[str, ...], n_targets: int
) -> CalibratedCell:
    """Calibrate an emulated campaign of 100 + 150 poses, and make a held-out program.

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
    t = float(data.campaign.t_s[-1]) + 5.0 * np.arange(1, len(q_prog) + 1, dtype=float)
    return CalibratedCell(data, cal, loop.final.errors_mm["validate"], q_prog, target, t, rng)


def compensation_trial(
    robot: str, seed: int, effects: tuple[str, ...] = (), n_targets: int = 150
) -> CompensationTrial:
    """Calibrate an emulated campaign (the twin sees the campaign only), then drive the
    emulated robot to held-out targets with the nominal program and with the compensated
    one, and measure both with the emulated tracker (:func:`calibrated_cell`)."""
    cell = calibrated_cell(robot, seed, effects, n_targets)
    q_prog, target, t, rng = cell.q_programmed_deg, cell.target_mm, cell.t_s, cell.rng
    res = compensate(cell.calibrated, target, q_programmed_deg=q_prog)
    before = target - measure_program(cell.data, q_prog, rng, t)
    ok = res.ok
    after = target[ok] - measure_program(cell.data, res.q_deg[ok], rng, t[ok])
    return CompensationTrial(before[ok], after, cell.twin_validation_mm, int((~ok).sum()))


@dataclass(frozen=True)
class LoadTest:
    """An emulated load test: poses ``(m, n)`` deg, forces ``(m, 3)`` N and the tracker's
    deflections (loaded − unloaded) ``(m, 3)`` mm."""

    q_deg: FloatArray
    force_n: FloatArray
    deflection_mm: FloatArray


def load_test(
    data: CampaignData,
    description: RobotDescription,
    n_poses: int,
    force_n: float,
    rng: np.random.Generator,
    t0_s: float,
) -> LoadTest:
    """At ``n_poses`` random poses, the TCP measured unloaded and under ``±force_n`` along
    each tracker axis (a weight over a pulley, a load cell): ``6·n_poses`` deflections,
    each the difference of two noisy tracker readings."""
    q = np.degrees(sample_reachable_poses(description, n_poses, rng))
    directions = np.vstack([np.eye(3), -np.eye(3)])
    qq = np.repeat(q, len(directions), axis=0)
    f = force_n * np.tile(directions, (n_poses, 1))
    t = t0_s + 5.0 * np.arange(len(qq))
    unloaded = np.repeat(measure_program(data, q, rng, t[:: len(directions)]), 6, axis=0)
    loaded = measure_program(data, qq, rng, t, f)
    return LoadTest(qq, f, loaded - unloaded)


@dataclass(frozen=True)
class ForceCompensationTrial:
    """Errors ``target − measured`` ``(m, 3)`` mm under a process force on the tool: the
    programmed joints (before), compensated without the force (the geometry and effects
    only) and with it; the twin's held-out prediction error ``(v, 3)`` mm; the load
    test's fit and the emulator's own stiffnesses ``(n,)`` N·mm/rad (for the check)."""

    before_mm: FloatArray
    after_no_force_mm: FloatArray
    after_mm: FloatArray
    twin_validation_mm: FloatArray
    fit: ComplianceFit
    true_stiffness_nmm_per_rad: FloatArray
    refused: int


def force_compensation_trial(
    robot: str,
    seed: int,
    force_n: float = 1000.0,
    n_targets: int = 150,
    n_load_poses: int = 12,
) -> ForceCompensationTrial:
    """Calibrate an emulated campaign with gravity deflection (the arm's compliance),
    identify the joint stiffnesses from an emulated load test, then drive held-out
    targets each under a force of ``force_n`` N in a random direction."""
    cell = calibrated_cell(robot, seed, ("gravity_deflection",), n_targets)
    data, target, q_prog, rng = cell.data, cell.target_mm, cell.q_programmed_deg, cell.rng
    test = load_test(data, cell.calibrated, n_load_poses, force_n, rng, float(cell.t_s[-1]) + 5.0)
    fit = fit_joint_compliance(
        cell.calibrated, np.radians(test.q_deg), test.force_n, test.deflection_mm
    )
    stiff = fit.applied_to(cell.calibrated)
    u = rng.normal(size=(len(target), 3))
    force = force_n * u / np.linalg.norm(u, axis=1, keepdims=True)
    plain = compensate(cell.calibrated, target, q_programmed_deg=q_prog)
    res = compensate(stiff, target, q_programmed_deg=q_prog, force_n=force)
    ok = plain.ok & res.ok
    t = cell.t_s[ok]

    def error(q_deg: FloatArray) -> FloatArray:
        return target[ok] - measure_program(data, q_deg[ok], rng, t, force[ok])

    return ForceCompensationTrial(
        error(q_prog),
        error(plain.q_deg),
        error(res.q_deg),
        cell.twin_validation_mm,
        fit,
        force_stiffness_nmm_per_rad(data.effects, data.cell.arm),
        int((~ok).sum()),
    )
