"""What the joint fit takes out of the sweeps against the emulator's true deflection.

On :mod:`benchmarks.bench_plan_sweeps`'s cell (the narrowed KR500, the demo's planned cell
on the simulated clock, gravity deflection undeclared), per cell seed:

* ``maps``: each joint's map error against the strip (RMS about the mean, ″) refitted from
  the sweeps with nothing taken out, with the emulator's true deflection of every link
  taken out (``sim_devices.effects.link_rotation_rad`` at the stops; the terms joint 4's
  map kept), and of each joint fit round (``calibrate_twin``);
* per round, each joint's output angle at Home as the twin has it (the map and the loop's
  terms of that joint, :func:`output_errors`) against the emulator's (ring and deflection);
* per round that took deflection out: per swept joint and link, the deflection taken out
  and the true one at the stops (RMS about the mean over the stops, ″) and the RMS of
  their difference; the maps with joint 4's take-out replaced by the truth;
* round 1's gravity term (its joints and compliance ratios), per joint the signal-to-noise
  ratio over the sweeps of what round 2 takes out and the share its shrinkage keeps
  (:func:`~calibration.twin.sweep_deflections.sweep_deflections`), and per joint at the
  campaign's poses, its deflection relative to the sweep configurations (what the poses see: the
  round's fit) and plain (what the next round takes out), the twin's and the truth's.

    python -m benchmarks.sweep_deflections_vs_truth [--seeds 5-6] [--poses 40 --validate 40]
        [--variant default|planned] [--kinds gravity_deflection,...]

``--kinds`` restricts the closed loop's candidate kinds (``LoopSettings.kinds``). The
truth comes from the emulator; the twin never sees it.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.bench_plan_sweeps import cell_text, sampled
from calibration.effects.effect_base import EffectContext, EffectData, ModelAtPoses
from calibration.effects.loop_problem import LoopSettings
from calibration.model.description import RobotDescription, load_robot
from calibration.model.gravity_regressor import link_rotations
from calibration.scales.chain_scale import ScaleCampaignResult, calibrate_scales
from calibration.twin.campaign_measurement import CampaignMeasurements, measure_campaign
from calibration.twin.fit_rounds import TwinRound, calibrate_twin
from calibration.twin.phase_detection import PhaseOptions
from calibration.twin.sweep_configuration import stop_angles_rad, sweep_configurations
from calibration.twin.sweep_deflections import (
    acting_moments,
    compliance_ratio_variance,
    gravity_term,
    sweep_deflection,
)
from sim_devices.effects import link_rotation_rad
from sim_devices.plant import Plant

ARCSEC = np.degrees(1.0) * 3600.0


def map_errors(scales: ScaleCampaignResult, plant: Plant, robot: RobotDescription) -> list[float]:
    """Each map against the strip over the joint's range: RMS about the mean, ″."""
    by_joint = {r.joint: r.scale for r in scales}
    out = []
    for j, joint in enumerate(robot.joints):
        q = np.radians(np.linspace(joint.lower_deg, joint.upper_deg, 400))
        read = by_joint[j + 1].counts_to_joint_deg(plant.cell.strips[j].ideal_counts(q))
        out.append(round(float(np.std(read - np.degrees(q))) * 3600.0, 2))
    return out


def true_relative(plant: Plant, q: np.ndarray, ref: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The emulator's deflection ``(P, n)`` rad at poses ``q`` less what each joint's map
    absorbed in its sweep configuration ``ref`` (the twin's round-1 form, axes ``z``)."""
    out = link_rotation_rad(plant.undeclared, plant.arm, q)
    for j in range(q.shape[1]):
        at = np.tile(ref[j], (len(q), 1))
        at[:, j] = q[:, j]
        absorbed = link_rotation_rad(plant.undeclared, plant.arm, at)
        out[:, j] -= sum(float(z[j, i] @ z[j, j]) * absorbed[:, i] for i in range(j + 1))
    return out


def round_one_term(meas: CampaignMeasurements, first: TwinRound, plant: Plant) -> None:
    """Round 1's gravity term at the poses against the truth (module docstring)."""
    term = None if first.loop is None else gravity_term(first.loop)
    if term is None:
        print("  round 1: no gravity term")
        return
    robot = meas.robot
    ratios = ", ".join(
        f"{j}: {r:.3g}" for j, r in zip(term.spec.joints, term.spec.shape, strict=False)
    )
    print(f"  round 1 gravity term {term.spec.parameter} form, compliance ratios {ratios}")
    ref = sweep_configurations(robot, meas.sweeps, first.scales)
    q = first.campaign.q_rad
    kin = ModelAtPoses.of(term.model, q)
    data = EffectContext(robot, EffectData(q, sweep_reference=ref))
    rel = term.kind.joint_deflections_rad(term.spec, term.values, data, kin)
    plain = term.kind.joint_deflections_rad(
        term.spec, term.values, EffectContext(robot, EffectData(q)), kin
    )
    z = link_rotations(term.model, ref)[:, :, :, 2]
    t_rel = true_relative(plant, q, ref, z)
    t_plain = link_rotation_rad(plant.undeclared, plant.arm, q)
    acting = acting_moments(robot, first.campaign, term, ref)
    ratio_var = compliance_ratio_variance(term.spec, first.loop, robot.n_joints)
    signal, noise = np.zeros(robot.n_joints), np.zeros(robot.n_joints)
    for sweep in meas.sweeps.values():  # as sweep_deflections sums them
        value, var = sweep_deflection(robot, first.scales, sweep, term, acting)
        signal += np.sum(value**2, axis=0)
        noise += np.sum(var, axis=0) + np.sum(value**2, axis=0) * ratio_var
    snr = np.sqrt(signal / np.maximum(noise, 1e-300))
    shrink = np.clip(1.0 - noise / np.maximum(signal, 1e-300), 0.0, 1.0)
    print(f"    what round 2 takes out, per joint: signal-to-noise over the sweeps "
          f"{np.round(snr, 2).tolist()}, share kept {np.round(shrink, 2).tolist()}")  # fmt: skip
    for j in term.spec.joints:
        i = j - 1
        miss = np.sqrt(np.mean((rel[:, i] - t_rel[:, i]) ** 2)) * ARCSEC
        print(
            f"    joint {j} at the poses: relative twin {np.std(rel[:, i]) * ARCSEC:6.1f} truth "
            f"{np.std(t_rel[:, i]) * ARCSEC:6.1f} (difference {miss:5.1f})″, plain twin "
            f"{np.std(plain[:, i]) * ARCSEC:6.1f} truth {np.std(t_plain[:, i]) * ARCSEC:6.1f}″"
        )


def output_errors(rnd: TwinRound, plant: Plant, robot: RobotDescription) -> list[float]:
    """Per joint, the round's twin against the emulator at Home with that joint moved over
    its range: the map's reading plus the round's loop terms of that joint (its cyclic
    errors; the gravity term's plain deflection when the round took deflection out, none
    in the relative form of round 1, whose reference is Home) against the ring angle plus
    the true deflection; RMS about the mean, ″. Other terms (link harmonics, geometry) are
    left out."""
    from calibration.effects.effect_kinds import split_values

    by_joint = {r.joint: r.scale for r in rnd.scales}
    terms = []
    if rnd.loop is not None and rnd.loop.final.result is not None:
        final = rnd.loop.final
        terms = list(
            zip(final.specs, split_values(final.specs, final.result.effect_values), strict=True)
        )
    term = None if rnd.loop is None else gravity_term(rnd.loop)
    out = []
    for j, joint in enumerate(robot.joints):
        q = np.zeros((400, robot.n_joints))
        q[:, j] = np.radians(np.linspace(joint.lower_deg, joint.upper_deg, 400))
        twin = np.radians(
            by_joint[j + 1].counts_to_joint_deg(plant.cell.strips[j].ideal_counts(q[:, j]))
        )
        for spec, v in terms:
            if spec.kind == "joint_harmonic" and spec.joint == j + 1:
                k = spec.order * q[:, j]
                twin += np.radians(v[0] * np.cos(k) + v[1] * np.sin(k))
        if term is not None and rnd.deflection_rad is not None:
            ctx = EffectContext(robot, EffectData(q))
            twin += term.kind.joint_deflections_rad(
                term.spec, term.values, ctx, ModelAtPoses.of(term.model, q)
            )[:, j]
        true = q[:, j] + link_rotation_rad(plant.undeclared, plant.arm, q)[:, j]
        out.append(round(float(np.std(twin - true) * ARCSEC), 2))
    return out


def one_seed(robot_file: Path, plan: Path, seed: int, args: argparse.Namespace) -> None:
    robot = load_robot(str(robot_file))
    text = cell_text(robot_file, plan, sweeps=args.variant == "planned", seed=seed)
    streams, plant = sampled(text)
    meas = measure_campaign(streams, robot, phase_options=PhaseOptions(identify_count=args.poses))
    kinds = tuple(args.kinds.split(",")) if args.kinds else None
    twin = calibrate_twin(meas, loop_settings=LoopSettings(kinds=kinds) if kinds else None)
    limits = [(j.lower_deg, j.upper_deg) for j in robot.joints]
    final = twin.final.scales
    truth = {
        j: link_rotation_rad(plant.undeclared, plant.arm, stop_angles_rad(robot, final, sweep))
        for j, sweep in meas.sweeps.items()
    }

    def refit(taken: dict[int, np.ndarray] | None) -> str:
        scales = calibrate_scales(
            meas.sweeps, meas.home_counts, home_deg=robot.home, limits_deg=limits,
            link_rotations_rad=taken,
        )  # fmt: skip
        terms = next(r.scale.terms for r in scales if r.joint == 4)
        return f"{map_errors(scales, plant, robot)} (joint 4's terms {list(terms)})"

    print(f"seed {seed}: maps with nothing taken out {refit(None)}, the truth {refit(truth)}")
    round_one_term(meas, twin.rounds[0], plant)
    for k, rnd in enumerate(twin.rounds, start=1):
        added = [] if rnd.loop is None else [s.label for s in rnd.loop.stages[2:]]
        val = None if rnd.loop is None else round(rnd.loop.stages[-1].mean_ap("validate"), 4)
        print(f"  round {k}: maps {map_errors(rnd.scales, plant, robot)}; validate {val} mm; "
              f"loop added {added}")  # fmt: skip
        print(f"    output at Home (map + the loop's terms of the joint) against the truth "
              f"{output_errors(rnd, plant, robot)}")  # fmt: skip
        if rnd.deflection_rad is None:
            continue
        for j in sorted(rnd.deflection_rad):
            taken, true = rnd.deflection_rad[j] * ARCSEC, truth[j] * ARCSEC
            links = []
            for i in range(j):
                a, b = taken[:, i] - taken[:, i].mean(), true[:, i] - true[:, i].mean()
                if max(np.abs(a).max(), np.abs(b).max()) > 0.05:
                    links.append(f"link {i + 1} {np.std(a):6.2f} true {np.std(b):6.2f} "
                                 f"miss {np.sqrt(np.mean((a - b) ** 2)):6.2f}")  # fmt: skip
            print(f"    sweep {j}: " + (" | ".join(links) or "-"))
        mixed = {**rnd.deflection_rad, 4: truth[4]}
        print(f"    maps with joint 4's take-out the truth: {refit(mixed)}")


def main(argv: list[str] | None = None) -> int:
    from calibration.cli import main as twin_main
    from tests.daq.test_demo_planned import narrow_kr500

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="5-6", help="cell seeds, a-b")
    parser.add_argument("--poses", type=int, default=40, help="identification poses")
    parser.add_argument("--validate", type=int, default=40, help="validation poses")
    parser.add_argument("--variant", choices=("default", "planned"), default="default")
    parser.add_argument("--kinds", default="", help="the loop's candidate kinds (default: all)")
    args = parser.parse_args(argv)
    a, _, b = args.seeds.partition("-")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        robot_file = root / "narrow_kr500.toml"
        robot_file.write_text(narrow_kr500(), encoding="utf-8")
        argv_plan = ["plan", "--robot", str(robot_file), "--poses", str(args.poses)]
        argv_plan += ["--validate", str(args.validate), "--candidates", "400"]
        if twin_main([*argv_plan, "--out", str(root / "plan")]) != 0:
            raise RuntimeError("twin plan failed")
        for seed in range(int(a), int(b or a) + 1):
            one_seed(robot_file, root / "plan", seed, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
