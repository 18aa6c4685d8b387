"""The closed loop's attribution matrix: does it name the true physical cause?

Emulated campaigns (:mod:`sim_devices.pose_campaign`) on cells whose every effect comes from
the emulator's own physical parameters (its own masses and counterbalance, stiffnesses,
thermal time constant: :mod:`sim_devices.physical_arm`, :mod:`sim_devices.effects`). The
twin is given the nominal description **without a mass model**, or with masses 30 % off
(odd links ×1.3, even links and the payload ×0.7): never the emulator's structure.

Per robot, twin mass variant and case (each effect kind alone, and the pairs gravity +
cyclic error on another joint, thermal lag + gravity), over seeds:

* ``named``: the right kind is among the added effects (for a lag: a drift in its lag
  form; for a pair: both);
* ``look_alike``: an effect a wrong cause would give (a harmonic, or a generic term, on a
  joint gravity loads when gravity is the truth; a polynomial in time when the truth is a
  lag; anything at all on clean data);
* ``ratio``: the final model's validation mean AP over that of the emulator's own model
  family fitted to the same identification poses (geometry plus the true effects'
  structure with their strengths free; the achievable limit): mean and **worst case**.

    python -m benchmarks.bench_attribution [--seeds N] [--quick]
    .venv/bin/python -m pytest -q -m slow tests/test_closed_loop.py -s   # the same, asserted
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.effects.closed_loop import ClosedLoopResult, run_closed_loop
from calibration.identify.identification import identify
from calibration.identify.position_residuals import EffectTerms, predicted_points
from calibration.model.description import RobotDescription
from calibration.model.gravity_regressor import base_moments
from calibration.model.kinematics import KinematicModel, identification_jacobian
from sim_devices.effects import UndeclaredEffects, approach_direction
from sim_devices.pose_campaign import CampaignData, CampaignSettings, emulated_campaign

FloatArray = NDArray[np.float64]
Row = dict[str, Any]

ROBOTS = ("kr500", "hp20d")
MASS_VARIANTS = ("none", "30% off")
#: case -> (undeclared effect names, setting overrides)
CASES: dict[str, tuple[tuple[str, ...], dict[str, Any]]] = {
    "clean": ((), {}),
    "gravity": (("gravity_deflection",), {}),
    "cyclic": (("grating_cyclic",), {}),
    "lag": (("thermal_lag",), {}),
    "drift": (("thermal_drift",), {}),
    "gravity+cyclic": (("gravity_deflection", "grating_cyclic"), {"cyclic_joint": 3}),
    "lag+gravity": (("thermal_lag", "gravity_deflection"), {}),
}
TIME_POLYNOMIALS = ("instrument_scale_drift", "cartesian_time")


def twin_description(nominal: RobotDescription, variant: str) -> RobotDescription:
    """What the twin is told: no mass model, or masses 30 % off (never the emulator's)."""
    if variant == "none":
        joints = tuple(replace(j, mass_kg=None, com_mm=None) for j in nominal.joints)
        return replace(nominal, joints=joints, tool=replace(nominal.tool, mass_kg=None))
    if variant == "30% off":
        joints = tuple(
            replace(j, mass_kg=None if j.mass_kg is None else j.mass_kg * (1.3 if i % 2 else 0.7))
            for i, j in enumerate(nominal.joints, start=1)
        )
        tool = replace(nominal.tool, mass_kg=(nominal.tool.mass_kg or 0.0) * 0.7)
        return replace(nominal, joints=joints, tool=tool)
    raise ValueError(f"unknown mass variant {variant!r} (valid: {', '.join(MASS_VARIANTS)})")


def effects_of(case: str) -> UndeclaredEffects:
    names, overrides = CASES[case]
    return UndeclaredEffects.named(*names, **overrides) if names else UndeclaredEffects()


def emulated(robot: str, case: str, seed: int) -> CampaignData:
    return emulated_campaign(robot, seed, CampaignSettings(effects=effects_of(case)))


# -- the emulator's own model family, fitted to the same data ---------------------------------
def _family_regressor(data: CampaignData, q: FloatArray, t: FloatArray, d: FloatArray):
    """The true effects' structure at poses ``q`` ``(r, n)``: a regressor
    ``(model, sel) -> (r, 3, k)`` and the parameter names (strengths free)."""
    eff = data.effects
    arm = data.cell.arm
    n = q.shape[1]
    torque = arm.joint_torques_nmm(q) if eff.gravity_deflection else None
    loaded: list[int] = []
    if eff.gravity_deflection:
        stiff = np.asarray(eff.deflection_stiffness_nmm_per_rad, dtype=float)
        loaded = [j for j in range(n) if np.isfinite(stiff[j])]
    lengths = []
    if eff.thermal_drift:
        lengths.append((eff.drift_joint, eff.drift_parameter, t / 3600.0))
    if eff.thermal_lag:
        lengths.append((eff.lag_joint, eff.lag_parameter, -np.expm1(-t / eff.lag_time_constant_s)))
    lost = [j for j, w in enumerate(eff.lost_motion_deg[:n]) if w] if eff.lost_motion else []
    names = [f"compliance{j + 1}" for j in loaded]
    names += [f"length{j}{p}" for j, p, _ in lengths]
    names += ["cyclic_cos", "cyclic_sin"] if eff.grating_cyclic else []
    names += [f"lost{j + 1}" for j in lost]

    def regressor(model: KinematicModel, sel: slice) -> FloatArray:
        _, jac = identification_jacobian(model, q[sel])
        cols = [jac[:, :, 5 * j + 3] * (torque[sel, j] * 1e-12)[:, None] for j in loaded]
        cols += [jac[:, :, 5 * (j - 1) + {"a": 0, "d": 2}[p]] * f[sel, None] for j, p, f in lengths]
        if eff.grating_cyclic:
            j = eff.cyclic_joint - 1
            k = eff.cyclic_order * q[sel, j]
            cols += [jac[:, :, 5 * j + 3] * np.cos(k)[:, None]]
            cols += [jac[:, :, 5 * j + 3] * np.sin(k)[:, None]]
        cols += [jac[:, :, 5 * j + 3] * d[sel, j][:, None] for j in lost]
        if not cols:
            return np.zeros((len(q[sel]), 3, 0))
        return np.stack(cols, axis=2)

    return regressor, tuple(names)


def family_validation_mm(data: CampaignData) -> float:
    """Validation mean AP of the emulator's own model family fitted to the identification
    poses (the nominal geometry as the start, like the twin's)."""
    c = data.campaign
    q, t = c.q_rad, c.t_s
    direction = approach_direction(q)
    idm, vm = c.mask("identify"), c.mask("validate")
    nominal = KinematicModel.from_description(data.cell.nominal)
    reg_id, names = _family_regressor(data, q[idm], t[idm], direction[idm])
    terms = EffectTerms(names, reg_id) if names else None
    fit = identify(nominal, q[idm], c.xyz_mm[idm], effects=terms)
    reg_val, _ = _family_regressor(data, q[vm], t[vm], direction[vm])
    terms_val = EffectTerms(names, reg_val) if names else None
    pred = predicted_points(fit.model, q[vm], terms_val, fit.effect_values)
    return float(np.linalg.norm(c.xyz_mm[vm] - pred, axis=1).mean())


# -- naming -----------------------------------------------------------------------------------
def _loaded_joints(description: RobotDescription) -> set[int]:
    return set(base_moments(description).loaded_joints)


def _is_lag(spec) -> bool:  # type: ignore[no-untyped-def]
    return spec.kind == "length_drift" and bool(spec.shape)


def verdict(case: str, result: ClosedLoopResult, description: RobotDescription) -> dict[str, Any]:
    """Whether the right kinds were named, and whether a look-alike was."""
    names = CASES[case][0]
    eff = effects_of(case)
    added = list(result.added)
    loaded = _loaded_joints(description)
    right = []
    look = []
    if "gravity_deflection" in names:
        right.append(any(s.kind == "gravity_deflection" for s in added))
        look += [
            s
            for s in added
            if s.kind in ("joint_harmonic", "link_harmonic", "cartesian_harmonic")
            and s.joint in loaded
            and not (
                eff.grating_cyclic and s.kind == "joint_harmonic" and s.joint == eff.cyclic_joint
            )
        ]
    if "grating_cyclic" in names:
        j, k = eff.cyclic_joint, eff.cyclic_order
        right.append(
            any(s.kind == "joint_harmonic" and (s.joint, s.order) == (j, k) for s in added)
        )
    if "thermal_lag" in names:
        right.append(
            any(
                _is_lag(s) and (s.joint, s.parameter) == (eff.lag_joint, eff.lag_parameter)
                for s in added
            )
        )
        look += [
            s
            for s in added
            if s.kind in TIME_POLYNOMIALS or (s.kind == "length_drift" and not s.shape)
        ]
    if "thermal_drift" in names:
        right.append(
            any(
                s.kind == "length_drift"
                and (s.joint, s.parameter) == (eff.drift_joint, eff.drift_parameter)
                for s in added
            )
        )
    if not names:
        look += added
        right.append(not added)
    return {
        "named": all(right),
        "look_alike": bool(look),
        "added": [s.label for s in added],
    }


@dataclass(frozen=True)
class Outcome:
    robot: str
    case: str
    masses: str
    seed: int
    named: bool
    look_alike: bool
    added: tuple[str, ...]
    final_mm: float
    family_mm: float
    loop_s: float

    @property
    def ratio(self) -> float:
        return self.final_mm / self.family_mm


def run_case(robot: str, case: str, masses: str, seed: int) -> Outcome:
    data = emulated(robot, case, seed)
    desc = twin_description(data.cell.nominal, masses)
    started = time.perf_counter()
    res = run_closed_loop(desc, data.campaign)
    elapsed = time.perf_counter() - started
    v = verdict(case, res, desc)
    final = res.final.mean_ap("validate")
    return Outcome(
        robot, case, masses, seed, v["named"], v["look_alike"], tuple(v["added"]), final,
        family_validation_mm(data), elapsed,
    )  # fmt: skip


def summarize(outcomes: Sequence[Outcome]) -> list[Row]:
    """One row per robot, mass variant and case."""
    keys = dict.fromkeys((o.robot, o.masses, o.case) for o in outcomes)
    rows = []
    for robot, masses, case in keys:
        sel = [o for o in outcomes if (o.robot, o.masses, o.case) == (robot, masses, case)]
        ratios = np.array([o.ratio for o in sel])
        worst = sel[int(np.argmax(ratios))]
        rows.append(
            {
                "robot": robot,
                "masses": masses,
                "case": case,
                "n": len(sel),
                "named": sum(o.named for o in sel),
                "look_alike": sum(o.look_alike for o in sel),
                "ratio_mean": float(ratios.mean()),
                "ratio_worst": float(ratios.max()),
                "worst_seed": worst.seed,
                "final_mm": float(np.mean([o.final_mm for o in sel])),
                "family_mm": float(np.mean([o.family_mm for o in sel])),
                "loop_s": float(np.mean([o.loop_s for o in sel])),
            }
        )
    return rows


def matrix(
    seeds: Sequence[int],
    *,
    robots: Sequence[str] = ROBOTS,
    masses: Sequence[str] = MASS_VARIANTS,
    cases: Sequence[str] = tuple(c for c in CASES if c != "clean"),
    clean_seeds: Sequence[int] = (),
    progress: Callable[[Outcome], None] | None = None,
) -> list[Outcome]:
    """Every outcome of the matrix (clean campaigns over ``clean_seeds``, no masses given)."""
    out = []
    for robot in robots:
        for variant in masses:
            for case in cases:
                for seed in seeds:
                    out.append(run_case(robot, case, variant, seed))
                    if progress:
                        progress(out[-1])
        for seed in clean_seeds:
            out.append(run_case(robot, "clean", "none", seed))
            if progress:
                progress(out[-1])
    return out


def run(quick: bool) -> list[Row]:
    if quick:
        return summarize(matrix((1,), robots=("kr500",), masses=("none",), cases=("gravity",)))
    return summarize(matrix(range(1, 11), clean_seeds=range(100, 180)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_attribution", description=__doc__
    )
    parser.add_argument("--seeds", type=int, default=10, help="seeds per cell (10)")
    parser.add_argument("--clean", type=int, default=80, help="clean campaigns per robot (80)")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    from benchmarks import format_table

    if args.quick:
        rows = run(True)
    else:
        outcomes = matrix(
            range(1, args.seeds + 1),
            clean_seeds=range(100, 100 + args.clean),
            progress=lambda o: print(
                f"{o.robot} {o.masses} {o.case} seed {o.seed}: named {o.named} look-alike "
                f"{o.look_alike} ratio {o.ratio:.3f} {list(o.added)}",
                flush=True,
            ),
        )
        rows = summarize(outcomes)
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
