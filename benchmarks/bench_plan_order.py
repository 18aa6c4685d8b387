"""What the planned order is worth against a drift in time, the poses and the noise held.

Per seed (the cell, plan and held-out poses of :mod:`benchmarks.bench_plan`), the planned
50 identification poses are measured **once**, with the same random draws, and given the
times either order would give them: one pass (``--passes 1``, the shortest tour: a pose's
time follows where it is) or forward then back (``--passes 2``, the default,
:mod:`calibration.plan.travel_order`). The rows stay in the one-pass order, so the closed
loop's folds and every draw are the same; only ``t_s`` differs (the times of the
benchmark's campaign: one move-and-settle after another, identification poses first). So
the difference is the order's own, not a new noise draw (common random numbers), which
:mod:`benchmarks.bench_plan`, measuring each order as the robot runs it, cannot separate.
On a truth that does not change with time both columns are equal by construction (a
check); the approach direction of each pose is the one-pass order's (lost motion is the
one-pass campaign's).

    python -m benchmarks.bench_plan_order [--seeds 10] [--effects A,B,...] [--set K=V]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from benchmarks.bench_plan import EFFECTS, seed_campaigns, truth_effects
from calibration.effects.calibrate import calibrate
from calibration.effects.model_effects import predict_tcp
from sim_devices.effects import UndeclaredEffects
from sim_devices.pose_campaign import CampaignSettings, measure_campaign

FloatArray = NDArray[np.float64]
Row = dict[str, Any]

#: Truths that change with time, as ``bench_plan`` runs them (the three default effects on).
DRIFT = replace(EFFECTS, thermal_drift=True)


def positions_in(q_rad: FloatArray, other: FloatArray) -> NDArray[np.intp]:
    """Where each row of ``q_rad`` ``(m, n)`` comes in ``other`` ``(m, n)``, the same joint
    vectors in another order ``(m,)``."""
    d = np.abs(q_rad[:, None, :] - other[None, :, :]).max(axis=2)
    pos: NDArray[np.intp] = d.argmin(axis=1)
    if not np.allclose(d[np.arange(len(q_rad)), pos], 0.0) or len(set(pos)) != len(pos):
        raise ValueError("the two orders hold different poses")
    return pos


def run_seed(
    seed: int, effects: UndeclaredEffects, n_candidates: int = 5000, n_plan: int = 50
) -> Row:
    """One seed's held-out error (mm) of the planned campaign with the one-pass and the
    forward-then-back times (module text)."""
    from calibration.model.cell_geometry import resolve
    from calibration.plan.campaign_plan import PlanSettings, plan_campaign

    sc = seed_campaigns(seed, n_candidates, n_plan, passes=1)
    geometry = resolve(sc.cell_spec, sc.nominal)
    settings = PlanSettings(n_plan, 20, n_candidates, seed, passes=2)
    two = plan_campaign(sc.nominal, geometry, settings)  # the same poses, another order
    q_id, q_val = sc.q_id, sc.q_val
    pos = positions_in(q_id, two.q_rad[two.is_identify])
    campaign = CampaignSettings(effects=effects)
    base = measure_campaign(sc.cell, q_id, q_val, np.random.default_rng([seed, 7]), campaign)
    t_one = base.campaign.t_s
    t_two = t_one.copy()
    t_two[: len(q_id)] = t_one[pos]
    span_s = float(t_one[-1])
    t_held = np.sort(np.random.default_rng([seed, 9]).uniform(0.0, span_s, len(sc.held)))
    held = measure_campaign(
        sc.cell, sc.held[:0], sc.held, np.random.default_rng([seed, 8]), campaign, t_held
    )
    errors = []
    for t in (t_one, t_two):
        data = measure_campaign(sc.cell, q_id, q_val, np.random.default_rng([seed, 7]), campaign, t)
        result = calibrate(sc.nominal, data.campaign, effects=True)
        predicted = predict_tcp(
            result.description, held.campaign.q_rad, held.campaign.t_s, temp_c=held.campaign.temp_c
        )
        errors.append(float(np.mean(np.linalg.norm(predicted - held.true_prediction_mm, axis=1))))
    return {
        "seed": seed,
        "one_pass_mm": errors[0],
        "forward_back_mm": errors[1],
        "ratio": errors[1] / errors[0],
    }


def summarize(rows: list[Row]) -> list[Row]:
    one = float(np.mean([r["one_pass_mm"] for r in rows]))
    two = float(np.mean([r["forward_back_mm"] for r in rows]))
    better = sum(r["forward_back_mm"] < r["one_pass_mm"] for r in rows)
    worse = sum(r["forward_back_mm"] > r["one_pass_mm"] for r in rows)
    return [
        *rows,
        {
            "seed": "mean",
            "one_pass_mm": one,
            "forward_back_mm": two,
            "ratio": two / one,
            "better": better,
            "worse": worse,
        },
    ]


def run(quick: bool) -> list[Row]:
    if quick:
        return summarize([run_seed(1, DRIFT, n_candidates=400, n_plan=20)])
    return summarize([run_seed(s, DRIFT) for s in range(1, 11)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_plan_order", description=__doc__
    )
    parser.add_argument("--seeds", type=int, default=10, help="seeds 1.. (10)")
    parser.add_argument("--first-seed", type=int, default=1, help="the seeds run from this one (1)")
    parser.add_argument(
        "--effects",
        default=",".join(DRIFT.active),
        help="the truth's effects (default: bench_plan's three and thermal_drift)",
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="an effect setting"
    )
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    from benchmarks import format_table

    if args.quick:
        rows = run(True)
    else:
        effects = truth_effects(False, args.effects, args.set)
        seeds = range(args.first_seed, args.first_seed + args.seeds)
        rows = summarize([run_seed(s, effects) for s in seeds])
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
