"""Numbers of the emulator's physical arm, per preset: the figures in docs/emulator.md.

    python -m sim_devices.physics_report [--robot kr500 ...] [--seed 1] [--poses 250]

Per preset and seed: the arm's own masses against the description's, the counterbalance
and its share of joint 2's RMS gravity torque, the after-ring deflection stiffness and the
RMS deflection it gives at the TCP over random reachable poses, how far each joint held at
Home turns during every other joint's sweep with gear torsion and backlash on (static
scale campaign, the live plant's gears), and where the rings stand at the Home returns.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import numpy as np

from calibration.errors import CalibrationError
from calibration.model.description import RobotDescription, load_robot
from edges.command import run_command, take_debug_flag
from edges.options import OptionParser
from sim_devices.config import SEED_OPTION, integer_option, robot_option
from sim_devices.effects import UndeclaredEffects, deflection_stiffness_nmm_per_rad
from sim_devices.errors import SimError
from sim_devices.physical_arm import PhysicalArm
from sim_devices.pose_campaign import CampaignSettings, generate_campaign
from sim_devices.scale_campaign import CampaignOptions, run_campaign
from sim_devices.truth import TrueCell

ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0


def report(robot: str, seed: int, poses: int) -> list[str]:
    """Lines of text for one preset and seed."""
    nominal = load_robot(robot)
    cell = TrueCell.create(nominal, seed)
    return [
        f"== {robot}, seed {seed}",
        *_arm_lines(nominal, cell.arm),
        *_deflection_lines(nominal, cell, seed, poses),
        *_scale_campaign_lines(nominal, cell),
    ]


def _arm_lines(nominal: RobotDescription, arm: PhysicalArm) -> list[str]:
    """The arm's masses against the description's, its counterbalance, and the RMS joint
    torques over the joint ranges."""
    nom_kg = np.array([j.mass_kg or 0.0 for j in nominal.joints])
    lines = [
        f"links {arm.masses.arm_kg:.0f} kg (description {nom_kg.sum():.0f} kg), mass ratios "
        + " ".join(f"{r:.2f}" for r in arm.masses.mass_kg / np.where(nom_kg > 0, nom_kg, 1))
        + f"; payload {arm.masses.payload_kg:.1f} kg (description {nominal.tool.mass_kg} kg)"
    ]
    cb = arm.counterbalance
    if cb is None:
        lines.append("counterbalance: none")
    else:
        theta = np.linspace(arm.lower_rad[1], arm.upper_rad[1], 301) + arm.model.theta_offset_rad[1]
        force = cb.force_n(theta)
        lines.append(
            f"counterbalance: e {cb.anchor_radius_mm:.0f} mm, r {cb.attachment_radius_mm:.0f} mm, "
            f"free length {cb.free_length_mm:.0f} mm, k {cb.stiffness_n_per_mm:.1f} N/mm, "
            f"force {force.min() / 1e3:.1f}-{force.max() / 1e3:.1f} kN; "
            f"cancels {100 * arm.counterbalance_share:.1f} % of joint 2's RMS gravity torque"
        )
    q = arm.range_poses()
    rms_w = np.sqrt(np.mean(arm.weight_torques_nmm(q) ** 2, axis=0))
    rms_t = np.sqrt(np.mean(arm.joint_torques_nmm(q) ** 2, axis=0))
    lines.append(
        "RMS torque over the ranges (kN·m), weights / with counterbalance: "
        + " ".join(f"{w / 1e6:.2f}/{t / 1e6:.2f}" for w, t in zip(rms_w, rms_t, strict=True))
    )
    return lines


def _deflection_lines(
    nominal: RobotDescription, cell: TrueCell, seed: int, poses: int
) -> list[str]:
    """The after-ring stiffness, and the deflection it gives at the TCP over ``poses``
    reachable poses (two campaigns of the same draws, with and without it)."""
    eff = UndeclaredEffects.named("gravity_deflection")
    k = deflection_stiffness_nmm_per_rad(eff, cell.arm)
    k_desc = deflection_stiffness_nmm_per_rad(eff, nominal)
    settings = CampaignSettings(n_identify=poses // 2, n_validate=poses - poses // 2)
    rng_seed = [seed, 6]
    soft = generate_campaign(cell, np.random.default_rng(rng_seed), replace(settings, effects=eff))
    stiff = generate_campaign(cell, np.random.default_rng(rng_seed), settings)
    ap = np.linalg.norm(soft.tcp_true_mm - stiff.tcp_true_mm, axis=1)
    return [
        "after-ring stiffness (N·mm/rad, inf rigid): "
        + " ".join(f"{v:.2e}" for v in k)
        + " (from the description's masses: "
        + " ".join(f"{v:.2e}" for v in k_desc)
        + ")",
        f"after-ring deflection at the TCP over {poses} reachable poses: "
        f"RMS {np.sqrt(np.mean(ap**2)):.3f} mm, max {ap.max():.3f} mm",
    ]


def _scale_campaign_lines(nominal: RobotDescription, cell: TrueCell) -> list[str]:
    """How far the joints upstream of each swept joint turn (gear torsion and backlash
    on), and where the rings stand at the Home returns."""
    lines: list[str] = []
    camp = run_campaign(cell, CampaignOptions(torsion=True, backlash=True))
    for j in range(2, nominal.n_joints + 1):
        turn = camp.upstream_motion_rad(j)[: j - 1] * ARCSEC_PER_RAD
        lines.append(
            f"joint {j} sweep, joints 1..{j - 1} turn (peak to peak, arcsec): "
            + " ".join(f"{v:.1f}" for v in turn)
        )
    truths = [camp.truth(j) for j in range(1, 7)]
    ring = [t.home_rad if t.home_ring_rad is None else t.home_ring_rad for t in truths]
    ring = [r - t.home_rad for r, t in zip(ring, truths, strict=True)]
    lines.append(
        "ring at the Home returns minus commanded Home (arcsec): "
        + " ".join(f"{v * ARCSEC_PER_RAD:.1f}" for v in ring)
    )
    return lines


#: The most reachable poses of the deflection figure (drawn with a pool of 5 per pose).
MAX_POSES = 10_000


def build_parser() -> argparse.ArgumentParser:
    """The report's options, each checked as it is parsed."""
    parser = OptionParser(prog="python -m sim_devices.physics_report")
    parser.add_argument(
        "--robot", nargs="+", default=["kr500", "kr210_r3100", "hp20d"], help="presets or files"
    )
    parser.add_argument("--seed", type=SEED_OPTION, nargs="+", default=[1])
    parser.add_argument(
        "--poses",
        type=integer_option(2, MAX_POSES, "reachable poses"),
        default=250,
        help=f"reachable poses (deflection), 2..{MAX_POSES}",
    )
    return parser


def _run(args: argparse.Namespace) -> int:
    for robot in args.robot:  # every robot checked before any work
        nominal = robot_option(robot)
        if nominal.n_joints != 6:
            raise SimError(
                f"--robot {robot}: the report is for 6-joint arms, this one has {nominal.n_joints}"
            )
    text = [
        line
        for robot in args.robot
        for seed in args.seed
        for line in report(robot, seed, args.poses)
    ]
    print("\n".join(text))
    return 0


def main(argv: list[str] | None = None) -> int:
    """The command line (stdout only, printed once every report is done): a user's mistake
    is one line on stderr and exit 2 (:func:`edges.command.run_command`)."""
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return run_command(
        "python -m sim_devices.physics_report",
        lambda: _run(args),
        user_errors=(SimError, CalibrationError),
        debug=debug,
    )


if __name__ == "__main__":
    sys.exit(main())
