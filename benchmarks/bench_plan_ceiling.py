"""What any 50-pose design can be worth: the linear ceiling for the model the loop ends with.

Per seed (the cell, plan and random poses of :mod:`benchmarks.bench_plan`), the closed loop
fits the emulator's noise-free points of the 150 random poses (the effects of
``bench_plan.EFFECTS``, the loop offered gravity and the cyclic errors, ``ADMITTED``): the
model the data call for (on every seed measured, the physical gravity form and joint 1's
cyclic error). At that model, linearised, with every parameter free (no prior: the fit as
done), the **mean prediction variance** (mm², summed over x, y, z) over the 300 held-out
poses of the fit as the benchmark does it (every point weighed alike) under the tracker's
noise as the emulator draws it (1 σ per axis from its MPE at each point's distance: the
sandwich ``(AᵀA)⁻¹AᵀΣA(AᵀA)⁻¹``), of

* the planned 50 identification poses, random 50 and random 150;
* an **oracle 50**: chosen for that very model (greedy D-optimal start, then the
  planner's own I-optimal exchange, :func:`calibration.plan.plan_criterion.exchange`, the
  points weighed by 1/σ² as the planner does) from the plan's candidates: what a planner
  that knew the final model, its compliance ratios included, could reach.

``equivalent_random`` is ``150 · v(random 150) / v(design)``: how many random poses the
design's variance is worth; ``rms_vs_random150`` is ``√(v / v(random 150))``, the ratio a
held-out RMS error would show where the variance dominates.

    python -m benchmarks.bench_plan_ceiling [--seeds 1,7,8]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from benchmarks.bench_plan import ADMITTED, EFFECTS, PlannedArm, seed_campaigns
from calibration.effects.calibrate import calibrate
from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec, ModelAtPoses
from calibration.effects.effect_kinds import regressor_matrix
from calibration.identify.identifiability import analyze_model
from calibration.identify.pose_selection import select_poses
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel, identification_jacobian
from calibration.plan.plan_criterion import DesignProblem, exchange
from sim_devices.pose_campaign import CampaignSettings, measure_campaign
from sim_devices.truth import TrackerModel

FloatArray = NDArray[np.float64]
Row = dict[str, Any]


class _FinalModel:
    """The loop's final model as a linear design problem: blocks ``(N, 3, p)`` of the
    free geometry and the effects' parameters at any poses, and the emulator's tracker."""

    def __init__(
        self,
        nominal: RobotDescription,
        model: KinematicModel,
        specs: tuple[EffectSpec, ...],
        q_span: FloatArray,
        tracker: TrackerModel,
    ) -> None:
        self.nominal, self.model, self.specs, self.tracker = nominal, model, specs, tracker
        n_effect = self._all(q_span[:1]).shape[2] - len(model.parameter_names())
        free = analyze_model(model, q_span).free
        self.free = np.concatenate([free, np.ones(n_effect, dtype=bool)])

    def _all(self, q: FloatArray) -> FloatArray:
        tcp, jac = identification_jacobian(self.model, q)
        ctx = EffectContext(self.nominal, EffectData(q))
        kin = ModelAtPoses(self.model, q, tcp, jac)
        return np.concatenate([jac, regressor_matrix(self.specs, ctx, slice(0, len(q)), kin)], 2)

    def blocks(self, q: FloatArray) -> FloatArray:
        return self._all(q)[:, :, self.free]

    def sigma_mm(self, q: FloatArray) -> FloatArray:
        """The tracker's 1 σ per axis ``(N,)`` at the poses' points, as the emulator draws it."""
        tcp, _ = identification_jacobian(self.model, q)
        sigma: FloatArray = self.tracker.sigma_mm(tcp)
        return sigma


def prediction_variance(final: _FinalModel, q_design: FloatArray, held: FloatArray) -> float:
    """Mean over ``held`` of the prediction variance (mm², summed over x, y, z) of the
    unweighted fit from ``q_design`` ``(m, n)``, every parameter free, under the tracker's
    noise at each point."""
    a = final.blocks(q_design).reshape(-1, int(final.free.sum()))
    var = np.repeat(final.sigma_mm(q_design) ** 2, 3)
    inv = np.linalg.pinv(a.T @ a, rcond=1e-12)
    cov = inv @ (a.T * var) @ a @ inv
    h = final.blocks(held)
    return float(np.mean(np.einsum("nip,pq,niq->n", h, cov, h)))


def oracle_design(final: _FinalModel, candidates: FloatArray, k: int) -> FloatArray:
    """``k`` of ``candidates`` chosen for the final model itself (D start, I exchange),
    the points weighed by 1/σ² as the planner does."""
    b = final.blocks(candidates) / final.sigma_mm(candidates)[:, None, None]
    scale = np.sqrt(np.mean(b**2, axis=(0, 1)))
    scale[scale == 0] = 1.0
    b = b / scale
    ev, vec = np.linalg.eigh(np.einsum("nip,niq->pq", b, b))
    plain = b @ vec[:, ev > 1e-10 * ev[-1]]
    n, r = len(plain), plain.shape[2]
    problem = DesignProblem(
        plain, np.zeros((n, 3, 0)), np.einsum("nip,niq->pq", plain, plain) / n,
        np.zeros((r, 0)), 0.0, 1e-9 * np.eye(r),
    )  # fmt: skip
    chosen = [int(i) for i in select_poses(plain, k, index="O1", exchange_passes=0).indices]
    exchange(problem, chosen, 6)
    out: FloatArray = candidates[np.array(chosen)]
    return out


def run_seed(
    seed: int, n_candidates: int = 5000, n_plan: int = 50, arm: PlannedArm | None = None
) -> Row:
    """One seed's variances and what they are worth (module text), on ``arm`` (the KR500
    in the default cell when omitted)."""
    sc = seed_campaigns(seed, n_candidates, n_plan, arm)
    nominal, cell, plan, q_id, q_val = sc.nominal, sc.cell, sc.plan, sc.q_id, sc.q_val
    random150, held = sc.random, sc.held
    pool = np.vstack([random150, held])
    exact = replace(CampaignSettings(effects=EFFECTS), grating_noise_deg=0.0)
    data = measure_campaign(cell, random150, q_val, np.random.default_rng([seed, 7]), exact)
    assert data.expected_mm is not None  # the tracker's scale error is on
    campaign = replace(data.campaign, xyz_mm=data.expected_mm)
    fitted = calibrate(nominal, campaign, effects=True, loop_settings=ADMITTED, learned=False)
    assert fitted.loop is not None
    stage = fitted.loop.final
    final = _FinalModel(nominal, stage.model, stage.specs, pool, cell.tracker)
    oracle = oracle_design(final, plan.candidates.q_rad, n_plan)
    v = {
        name: prediction_variance(final, q, held)
        for name, q in (
            ("planned", q_id), ("random50", random150[:n_plan]), ("random150", random150),
            ("oracle", oracle),
        )
    }  # fmt: skip
    row: Row = {"seed": seed, "model": "; ".join(s.label for s in stage.specs)}
    for name, value in v.items():
        row[f"{name}_var"] = value
    for name in ("planned", "oracle", "random50"):
        row[f"{name}_equivalent_random"] = 3 * n_plan * v["random150"] / v[name]
        row[f"{name}_rms_vs_random150"] = float(np.sqrt(v[name] / v["random150"]))
    return row


def run(quick: bool) -> list[Row]:
    if quick:
        return [run_seed(1, n_candidates=400, n_plan=20)]
    return [run_seed(s) for s in (1, 7, 8)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_plan_ceiling", description=__doc__
    )
    parser.add_argument("--seeds", default="1,7,8", help="comma-separated seeds (1,7,8)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--robot", default="kr500", help="preset or description file (kr500)")
    parser.add_argument("--cell", help="cell.toml (default: the emulated default cell)")
    args = parser.parse_args(argv)
    from benchmarks import format_table

    seeds = [int(s) for s in args.seeds.split(",")]
    arm = PlannedArm.from_files(args.robot, args.cell)
    rows = run(True) if args.quick else [run_seed(s, arm=arm) for s in seeds]
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
