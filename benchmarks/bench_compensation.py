"""Accuracy compensation: speed, and the emulated before/after over robots and seeds.

    python -m benchmarks --only compensation          # speed: 10 000 targets, vs a loop, vs rtb
    python -m benchmarks.bench_compensation           # the before/after tables (~2 min)

Speed: :func:`calibration.twin.compensation.compensate` on all targets at once against the
same function called once per target (measured on a subset, scaled), and against
roboticstoolbox's ``ik_LM`` on the same targets (the calibrated geometry as an ETS, the
same orientation, seeded at the programmed joints; rtb knows no effects, so it solves
less). The before/after
table: per robot and case, the Table-3 statistics of ``|target − measured|`` (mm) over
all seeds' held-out targets, the emulated robot driven to the nominal program (before)
and to the compensated one (after), and after / the twin's own held-out prediction error
(:func:`sim_devices.program.compensation_trial`). Under a process force
(:func:`sim_devices.program.force_compensation_trial`): the stiffnesses from an emulated
load test, targets each under 1000 N in a random direction, driven with the programmed
joints, compensated without the force and with it.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from benchmarks import Row, best_time, format_table
from benchmarks.bench_kinematics import RTB_IK_TOL, reference_ets
from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel, flange_poses, tcp_positions
from calibration.twin.compensation import compensate
from sim_devices.pose_campaign import sample_reachable_poses
from sim_devices.program import compensation_trial, force_compensation_trial


def _calibrated_like(robot: str, seed: int):  # type: ignore[no-untyped-def]
    """A 'calibrated' description: the nominal one with small geometry offsets (speed
    does not depend on where they came from)."""
    desc = load_robot(robot)
    rng = np.random.default_rng(seed)
    joints = tuple(
        replace(j, a_mm=j.a_mm + rng.normal(0, 0.5), alpha_deg=j.alpha_deg + rng.normal(0, 0.02))
        for j in desc.joints
    )
    return desc, replace(desc, joints=joints)


def run(quick: bool) -> list[Row]:
    n = 200 if quick else 10_000
    desc, cal = _calibrated_like("kr500", 1)
    rng = np.random.default_rng(2)
    q = np.degrees(sample_reachable_poses(desc, n, rng))
    target = tcp_positions(KinematicModel.from_description(desc), np.radians(q))
    ours = best_time(lambda: compensate(cal, target, q_programmed_deg=q), repeat=3)
    k = 20 if quick else 200
    loop = best_time(
        lambda: [
            compensate(cal, target[i : i + 1], q_programmed_deg=q[i : i + 1]) for i in range(k)
        ]
    ) * (n / k)
    res = compensate(cal, target, q_programmed_deg=q)
    model = KinematicModel.from_description(cal)
    pose = flange_poses(model, np.radians(q))
    pose[:, :3, 3] = target
    ets = reference_ets(model, tcp=True)
    q0 = np.radians(q)
    k_rtb = 20 if quick else 500

    def rtb() -> int:
        return sum(
            bool(ets.ik_LM(pose[i], q0=q0[i], slimit=1, tol=RTB_IK_TOL).success)
            for i in range(k_rtb)
        )

    rtb_s = best_time(rtb) * (n / k_rtb)
    return [
        {
            "benchmark": "compensate, kr500, joints kept",
            "n": n,
            "ours_s": ours,
            "per_target_loop_s": loop,
            "per_target_loop_measured_n": k,
            "speedup_vs_per_target_loop": loop / ours,
            "rtb_ik_LM_s": rtb_s,
            "rtb_measured_n": k_rtb,
            "rtb_reached_of_measured": rtb(),
            "speedup_vs_rtb": rtb_s / ours,
            "reached": int(res.ok.sum()),
            "max_residual_mm": float(np.nanmax(res.residual_mm)),
            "note": "best of 3; the loop calls the same function per target; rtb: "
            "geometry only, one seeded solve per target",
        }
    ]


CASES = (
    ("kr500", ()),
    ("kr500", ("gravity_deflection",)),
    ("hp20d", ()),
    ("kr210_r3100", ()),
)


def _stats(errors: np.ndarray) -> dict[str, float]:
    ap = np.linalg.norm(errors, axis=1)
    return {
        "max": float(ap.max()),
        "min": float(ap.min()),
        "mean": float(ap.mean()),
        "std": float(ap.std(ddof=1)),
        "X": float(np.mean(np.abs(errors[:, 0]))),
        "Y": float(np.mean(np.abs(errors[:, 1]))),
        "Z": float(np.mean(np.abs(errors[:, 2]))),
    }


def sweep(seeds: int, n_targets: int) -> list[Row]:
    rows: list[Row] = []
    for robot, effects in CASES:
        before, after, ratios, refused = [], [], [], 0
        for seed in range(1, seeds + 1):
            t = compensation_trial(robot, seed, effects, n_targets)
            before.append(t.before_mm)
            after.append(t.after_mm)
            twin = float(np.mean(np.linalg.norm(t.twin_validation_mm, axis=1)))
            ratios.append(float(np.mean(np.linalg.norm(t.after_mm, axis=1))) / twin)
            refused += t.refused
        for when, errors in (("before", before), ("after", after)):
            rows.append(
                {
                    "robot": robot,
                    "case": "+".join(effects) or "geometry",
                    "when": when,
                    "targets": sum(len(e) for e in errors),
                    **_stats(np.vstack(errors)),
                    "after/twin worst": max(ratios) if when == "after" else "",
                    "refused": refused if when == "after" else "",
                }
            )
    return rows


def force_sweep(seeds: int, n_targets: int, force_n: float = 1000.0) -> list[Row]:
    """Per robot: |target − measured| under a process force, before / compensated without
    the force / with it, and the load test's stiffness error against the emulator's."""
    rows: list[Row] = []
    for robot in ("kr500", "hp20d", "kr210_r3100"):
        runs = [force_compensation_trial(robot, s, force_n, n_targets) for s in range(1, seeds + 1)]
        ratios = [
            float(np.mean(np.linalg.norm(t.after_mm, axis=1)))
            / float(np.mean(np.linalg.norm(t.twin_validation_mm, axis=1)))
            for t in runs
        ]
        k_err = [
            float(
                np.max(
                    np.abs(t.true_stiffness_nmm_per_rad / t.fit.stiffness_nmm_per_rad - 1)[
                        t.fit.determined
                    ]
                )
            )
            for t in runs
        ]
        for when, attr in (("before", "before_mm"), ("no force comp.", "after_no_force_mm"),
                           ("force comp.", "after_mm")):  # fmt: skip
            errors = np.vstack([getattr(t, attr) for t in runs])
            last = when == "force comp."
            rows.append(
                {
                    "robot": robot,
                    "force_n": force_n,
                    "when": when,
                    "targets": len(errors),
                    **_stats(errors),
                    "after/twin worst": max(ratios) if last else "",
                    "compliance err worst": max(k_err) if last else "",
                    "refused": sum(t.refused for t in runs) if last else "",
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_compensation")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--targets", type=int, default=150)
    args = p.parse_args(argv)
    print(format_table(sweep(args.seeds, args.targets)))
    print()
    print(format_table(force_sweep(args.seeds, args.targets)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
