"""The shoulder joints' coupled compliance (``joint_coupling``) on emulated campaigns: what
the loop adds, with and without the emulator's cross compliance, and the held-out error
against the emulator's truth after each stage.

The emulator's gravity deflection (its own masses, counterbalance and stiffnesses) with
the cross compliance of joints 2 and 3 at coefficient ``--rho`` (``0``: the usual gravity
deflection alone, no coupling); the twin is given the campaign only.

    python -m benchmarks.bench_coupling --robot kr500 --seeds 1-10 --rho 0.5
    python -m benchmarks.bench_coupling --robot kr500 --seeds 1-10 --rho 0

Prints one line per seed: the effects added, the validation mean distance from the truth
(mm) after the geometry and after each effect, the coupling's ratio κ and, with the
gravity term in its physical form, the coefficient it implies, ``κ/√((ρ2 − κ)(ρ3 − κ))``;
then how many seeds named the coupling and the worst final error over the gravity term's.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from typing import Any

from benchmarks.bench_candidates import truth_errors_mm
from calibration.effects.closed_loop import ClosedLoopResult, run_closed_loop
from calibration.model.description import load_robot
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign


def coupling_settings(rho: float) -> CampaignSettings:
    """The emulator's gravity deflection, with the shoulder's cross compliance at ``rho``
    (0: without)."""
    if rho == 0.0:
        return CampaignSettings(effects=UndeclaredEffects.named("gravity_deflection"))
    return CampaignSettings(
        effects=UndeclaredEffects.named("joint_coupling", coupling_coefficient=rho)
    )


def implied_coefficient(result: ClosedLoopResult) -> tuple[float, float]:
    """The coupling's κ and ``κ/√((ρ2 − κ)(ρ3 − κ))`` with a physical gravity term (NaN
    otherwise)."""
    coupling = [s for s in result.added if s.kind == "joint_coupling"]
    if not coupling:
        return math.nan, math.nan
    kappa = float(result.final.values_of(coupling[0])[0])
    gravity = [s for s in result.final.specs if s.kind == "gravity_deflection"]
    if not gravity or gravity[0].parameter != "physical":
        return kappa, math.nan
    ratio = dict(zip(gravity[0].joints, gravity[0].shape, strict=True))
    a, b = coupling[0].joints
    product = (ratio[a] - kappa) * (ratio[b] - kappa)
    return kappa, kappa / math.sqrt(product) if product > 0 else math.nan


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def sweep(
    robot: str, rho: float, seeds: list[int], say: Callable[[str], None] = print
) -> dict[str, Any]:
    """The loop on each seed's campaign (one line each through ``say``); a row: how many
    seeds named the coupling, the worst final over gravity-stage truth error, the loop's
    total time (s)."""
    desc = load_robot(robot)
    named, worst, total = 0, 0.0, 0.0
    for seed in seeds:
        data = emulated_campaign(robot, seed, coupling_settings(rho))
        started = time.perf_counter()
        result = run_closed_loop(desc, data.campaign)
        elapsed = time.perf_counter() - started
        total += elapsed
        errors = truth_errors_mm(data, result)
        named += "joint_coupling" in [s.kind for s in result.added]
        if len(errors) > 1:
            worst = max(worst, errors[-1] / errors[1])
        kappa, implied = implied_coefficient(result)
        added = "; ".join(s.label for s in result.added) or "nothing"
        trail = " → ".join(f"{e:.4f}" for e in errors)
        say(
            f"{robot} rho {rho} seed {seed}: {added} | truth mm {trail} | "
            f"kappa {kappa:.3f} implied rho {implied:.2f} | {elapsed:.1f} s"
        )
    return {
        "benchmark": f"joint coupling, {robot}, rho {rho}",
        "n": len(seeds),
        "named": named,
        "worst_final_over_gravity": worst,
        "ours_s": total,
    }


def run(quick: bool) -> list[dict[str, Any]]:
    """The runner's rows: quick, KR500 seed 1 with the coupling; else seeds 1-10 of both
    robots with and without it."""
    if quick:
        return [sweep("kr500", 0.5, [1], say=lambda _line: None)]
    seeds = list(range(1, 11))
    return [sweep(r, rho, seeds) for r in ("kr500", "hp20d") for rho in (0.5, 0.0)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_coupling")
    parser.add_argument("--robot", default="kr500")
    parser.add_argument("--seeds", default="1-10", help="a seed or a range, e.g. 1-10")
    parser.add_argument("--rho", type=float, default=0.5, help="coupling coefficient, 0: off")
    args = parser.parse_args(argv)
    seeds = _seeds(args.seeds)
    row = sweep(args.robot, args.rho, seeds, say=lambda line: print(line, flush=True))
    print(
        f"coupling named in {row['named']} of {len(seeds)}; worst final / gravity-stage "
        f"truth error {row['worst_final_over_gravity']:.3f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
