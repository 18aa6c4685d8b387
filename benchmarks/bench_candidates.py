"""Issue 29's further candidates on emulated campaigns: what the loop adds and the
held-out error against the emulator's truth after each stage.

Cases (the emulator's own effects, :mod:`sim_devices.effects`; the twin is given the
campaign only): ``thermal`` (every link expanding with the arm's temperature, written as
``temp_c``), ``bending`` (gravity deflection and link bending), ``gravity`` (the gravity
deflection alone: a bending look-alike would show here).

    python -m benchmarks.bench_candidates --case thermal --robot kr500 --seeds 1-4

Prints one line per seed: the effects added, the validation mean distance from the truth
(mm) after the geometry and after each effect, and the first added term's parameters.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from calibration.effects.closed_loop import ClosedLoopResult, campaign_effect_data, run_closed_loop
from calibration.effects.effect_base import EffectContext
from calibration.effects.effect_kinds import predict_points
from calibration.model.description import load_robot
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignData, CampaignSettings, emulated_campaign

CASES = {
    "thermal": ("thermal_expansion",),
    "bending": ("gravity_deflection", "link_bending"),
    "gravity": ("gravity_deflection",),
}


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def truth_errors_mm(data: CampaignData, result: ClosedLoopResult) -> list[float]:
    """Validation mean distance (mm) from the emulator's truth after the geometry and
    after each added effect (the loop's stages from the geometric one on)."""
    desc = data.cell.nominal
    camp = data.campaign
    val = camp.mask("validate")
    ctx = EffectContext(desc, campaign_effect_data(desc, camp).subset(val))
    out = []
    for stage in result.stages[1:]:
        pred = predict_points(stage.model, stage.specs, stage.effect_values, ctx)
        out.append(float(np.mean(np.linalg.norm(pred - data.true_prediction_mm[val], axis=1))))
    return out


def run_seed(robot: str, case: str, seed: int) -> str:
    """One seed's line: added effects, truth errors per stage (mm), loop time (s)."""
    desc = load_robot(robot)
    settings = CampaignSettings(effects=UndeclaredEffects.named(*CASES[case]))
    data = emulated_campaign(robot, seed, settings)
    camp = data.campaign
    started = time.perf_counter()
    result = run_closed_loop(desc, camp)
    elapsed = time.perf_counter() - started
    errors = truth_errors_mm(data, result)
    added = "; ".join(s.label for s in result.added) or "nothing"
    first = ""
    if result.added:
        spec = result.added[0]
        values = result.final.values_of(spec)
        first = f" first term {spec.parameter_names()[0]} = {values[0]:.3f}" if len(values) else ""
    trail = " → ".join(f"{e:.4f}" for e in errors)
    return f"{robot} {case} seed {seed}: {added} | truth mm {trail} |{first} | {elapsed:.1f} s"


def run(quick: bool = False) -> list[dict[str, object]]:
    """The runner's rows (``python -m benchmarks``): the bending case on the KR500, seed 1
    (quick) or seeds 1-3, a row per seed with its line."""
    seeds = [1] if quick else [1, 2, 3]
    return [
        {
            "benchmark": f"closed loop, bending case, kr500 seed {s}",
            "result": run_seed("kr500", "bending", s),
        }
        for s in seeds
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_candidates")
    parser.add_argument("--case", choices=list(CASES), default="thermal")
    parser.add_argument("--robot", default="kr500")
    parser.add_argument("--seeds", default="1-3", help="a seed or a range, e.g. 1-4")
    args = parser.parse_args(argv)
    for seed in _seeds(args.seeds):
        print(run_seed(args.robot, args.case, seed), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
