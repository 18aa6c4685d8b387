"""Grating-scale calibration: accuracy against the truth and the Cramér-Rao bound, and time.

Data: emulated campaigns (:mod:`sim_devices.scale_campaign`) on true cells from
:mod:`sim_devices.truth`, all noise on (tracker MPE 15 µm + 6 µm/m at 2σ, grating read
noise 0.5 count, whole counts, 32-bit wrap, stop jitter 0.005°).

Rows:

* ``accuracy`` per preset, eccentricity and joint, over ``seeds`` campaigns:
  ``err_rms_arcsec`` the RMS over stops and seeds of (recovered − true) angle relative to
  Home at the stops' counts; ``crb_rms_arcsec`` the Cramér-Rao bound of the same
  quantity at the true geometry and noise, for the true model (zero and scale, plus the
  cyclic term when the strip has one) plus the Home zero's read noise;
  ``ratio_vs_crb = err / crb`` (1.0 is efficient; the goal is ≤ 1.2); ``z_rms`` the RMS of
  error / reported standard uncertainty (≤ 1: the uncertainty covers the error);
  ``cyclic_kept`` and ``other_terms_kept`` the fraction of seeds that kept the cyclic term
  and any other term.
* ``accuracy_pooled`` per case: the RMS over joints of ``ratio_vs_crb`` and ``z_rms``.
* ``cyclic_detection`` (full run only): fraction of 20 seeds keeping the cyclic term, per
  joint, for a range of strip eccentricities (kr500): the detection limit per joint.
* ``calibrate_6_joints``: wall time of one full 6-joint calibration (library, from
  arrays), best of a few; ``generate_campaign`` the time of the emulated campaign.

    python -m benchmarks.bench_scale [--quick] [--seeds N]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from benchmarks import best_time
from calibration.model.description import RobotDescription, load_robot
from calibration.scales.chain_scale import calibrate_scales
from calibration.scales.circle_fit import fit_circle_3d
from calibration.scales.grating_scale import calibrate_joint
from calibration.scales.joint_scale_result import JointScaleResult
from calibration.scales.relation_fit import crb_covariance
from calibration.scales.scale_relation import ARCSEC_PER_DEG, RelationBasis
from calibration.scales.sweep_inputs import JointSweep
from calibration.scales.target_set_fit import fit_target_set
from sim_devices.scale_campaign import CampaignOptions, ScaleCampaign, run_campaign
from sim_devices.truth import TrueCell

Row = dict[str, Any]


def calibrate_campaign(
    camp: ScaleCampaign, desc: RobotDescription, joints: tuple[int, ...] | None = None
) -> dict[int, JointScaleResult]:
    """Calibrate every joint of an emulated campaign with the library (default options)."""
    out = {}
    for j in joints or tuple(sorted(set(camp.sweep_joint.tolist()))):
        m = camp.sweep_joint == j
        sweep = JointSweep(
            j, camp.sweep_pass[m], camp.sweep_step[m], camp.sweep_counts[m], camp.sweep_points_mm[m]
        )
        jd = desc.joints[j - 1]
        out[j] = calibrate_joint(
            sweep,
            camp.home_counts[camp.home_joint == j],
            home_deg=desc.home[j - 1],
            limits_deg=(jd.lower_deg, jd.upper_deg),
        )
    return out


def crb_angle_var_deg2(camp: ScaleCampaign, joint: int) -> np.ndarray:
    """CRB variance (deg²) of the angle relative to Home at every stop of ``joint``.

    The 3-D model's bound at the true circle and noise for the true relation (zero and
    scale, plus the cyclic term and the hysteresis offset when the truth has them), plus
    the Home zero's read noise (Gaussian noise and rounding) over the Home returns.
    """
    truth = camp.truth(joint)
    m = camp.sweep_joint == joint
    true_pts = camp.sweep_true_points_mm[m]
    q = camp.sweep_true_rad[m]
    order = np.argsort(q, kind="stable")
    circle = fit_circle_3d(true_pts[order])  # noise-free: the exact circle
    if circle.normal @ np.cross(true_pts[order][1] - circle.centre_mm, true_pts[order][-1]) < 0:
        circle = circle.flipped()
    theta = np.empty(q.size)
    theta[order] = circle.unwrapped_angle_rad()
    g = 1.0 / truth.counts_per_rad  # rad per count
    u = truth.strip.ideal_counts(q) - truth.home_counts
    s = np.where(camp.sweep_pass[m] == "backward", 0.5, -0.5)
    terms = []
    if truth.strip.eccentricity_mm > 0:
        terms.append("cyclic")
    if truth.hysteresis_counts != 0:
        terms.append("hysteresis")
    basis = RelationBasis(phase_rad_per_count=g)
    _, x = basis.columns(u, s, terms)
    design = np.column_stack([np.ones_like(u), x])
    sigma = camp.cell.tracker.sigma_mm(true_pts)
    cov = crb_covariance(circle, theta, design, sigma)[1:, 1:]
    _, x0 = basis.columns(u, np.zeros_like(u), terms)
    var = np.einsum("ij,jk,ik->i", x0, cov, x0)
    n_home = int(np.sum(camp.home_joint == joint)) or 1
    read_var = truth.strip.noise_counts**2 + 1.0 / 12.0
    return np.degrees(np.sqrt(var + g * g * read_var / n_home)) ** 2


@dataclass
class JointStats:
    err2: list[float]
    crb2: list[float]
    z2: list[float]
    cyclic: int = 0
    other: int = 0
    runs: int = 0


def calibrate_chain(camp: ScaleCampaign, desc: RobotDescription) -> dict[int, JointScaleResult]:
    """Calibrate in chain order with the other joints' motion taken out (the twin's way)."""
    limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
    res = calibrate_scales(
        camp.joint_sweeps(), camp.home_readings(), home_deg=desc.home, limits_deg=limits
    )
    return res.by_joint()


def accuracy_trials(
    preset: str,
    eccentricity_mm: float,
    seeds: range,
    hysteresis_counts: float = 0.0,
    *,
    gears: bool = False,
) -> dict[int, JointStats]:
    """Per joint: squared errors, CRB variances and z² over stops and seeds; terms kept.

    ``gears``: the live cell's gear torsion and backlash on every joint (the upstream
    joints turn during a sweep), calibrated through the chain; the truth is then the
    strip's relation from where the ring stands at the Home returns.
    """
    desc = load_robot(preset)
    stats: dict[int, JointStats] = {}
    for seed in seeds:
        cell = TrueCell.create(desc, seed, eccentricity_mm=eccentricity_mm)
        options = CampaignOptions(
            hysteresis_counts=hysteresis_counts, torsion=gears, backlash=gears
        )
        camp = run_campaign(cell, options)
        results = calibrate_chain(camp, desc) if gears else calibrate_campaign(camp, desc)
        for j, r in results.items():
            st = stats.setdefault(j, JointStats([], [], []))
            c = camp.sweep_counts[camp.sweep_joint == j]
            truth = camp.truth(j)
            true = truth.angle_from_home_ring_deg(c) if gears else truth.angle_deg(c)
            err = r.scale.counts_to_angle_deg(c) - true
            std = r.scale.angle_std_deg(c)
            st.err2 += list(err**2)
            st.crb2 += list(crb_angle_var_deg2(camp, j))
            st.z2 += list((err / std) ** 2)
            st.cyclic += "cyclic" in r.kept_terms
            st.other += any(t != "cyclic" for t in r.kept_terms)
            st.runs += 1
    return stats


def _accuracy_rows(
    preset: str, ecc: float, hysteresis: float, seeds: range, gears: bool = False
) -> list[Row]:
    stats = accuracy_trials(preset, ecc, seeds, hysteresis, gears=gears)
    rows: list[Row] = []
    ratios2, z2 = [], []
    case = {
        "preset": preset,
        "eccentricity_mm": ecc,
        "hysteresis_counts": hysteresis,
        "torsion_backlash": gears,
    }
    for j, st in stats.items():
        err = math.sqrt(np.mean(st.err2)) * ARCSEC_PER_DEG
        crb = math.sqrt(np.mean(st.crb2)) * ARCSEC_PER_DEG
        ratios2.append((err / crb) ** 2)
        z2.append(np.mean(st.z2))
        rows.append(
            {
                "benchmark": "accuracy",
                **case,
                "joint": j,
                "seeds": st.runs,
                "err_rms_arcsec": err,
                "crb_rms_arcsec": crb,
                "ratio_vs_crb": err / crb,
                "z_rms": math.sqrt(np.mean(st.z2)),
                "cyclic_kept": st.cyclic / st.runs,
                "other_terms_kept": st.other / st.runs,
            }
        )
    rows.append(
        {
            "benchmark": "accuracy_pooled",
            **case,
            "joint": "all",
            "seeds": len(seeds),
            "ratio_vs_crb": math.sqrt(np.mean(ratios2)),
            "z_rms": math.sqrt(np.mean(z2)),
            "note": "RMS over joints of err/CRB and of z",
        }
    )
    return rows


def detection_rows(preset: str, eccentricities: tuple[float, ...], seeds: range) -> list[Row]:
    """Fraction of seeds that keep the cyclic term, per joint and eccentricity."""
    desc = load_robot(preset)
    rows: list[Row] = []
    for ecc in eccentricities:
        kept: dict[int, int] = {}
        for seed in seeds:
            camp = run_campaign(TrueCell.create(desc, seed, eccentricity_mm=ecc))
            for j, r in calibrate_campaign(camp, desc).items():
                kept[j] = kept.get(j, 0) + ("cyclic" in r.kept_terms)
        row: Row = {"benchmark": "cyclic_detection", "preset": preset, "eccentricity_mm": ecc}
        row.update({f"joint{j}": k / len(seeds) for j, k in sorted(kept.items())})
        rows.append(row)
    return rows


def short_arc_rows(arcs: tuple[float, ...], targets: tuple[int, ...], seeds: range) -> list[Row]:
    """Statistical honesty on few stops: 10 stops per arc, linear strips (no eccentricity),
    joint 4 (its travel allows every arc). Over seeds: the share of maps that kept any
    extra term (all false here), and the RMS of error / reported uncertainty at the stops
    with its standard error."""
    desc = load_robot("kr500")
    rows: list[Row] = []
    for arc in arcs:
        for t in targets:
            false_terms = 0
            z2: list[float] = []
            err2: list[float] = []
            for seed in seeds:
                cell = TrueCell.create(desc, seed)
                opts = CampaignOptions(joints=(4,), targets=t, arc_deg=arc, stops_per_arc=10)
                camp = run_campaign(cell, opts)
                sweep = camp.joint_sweeps()[4]
                r = calibrate_joint(sweep, camp.home_readings()[4])
                false_terms += bool(r.kept_terms)
                c = r.stop_counts
                err = r.scale.counts_to_angle_deg(c) - camp.truth(4).angle_deg(c)
                z2.append(float(np.mean((err / r.scale.angle_std_deg(c)) ** 2)))
                err2 += list(err**2)
            rows.append(
                {
                    "benchmark": "short_arcs",
                    "arc_deg": arc,
                    "targets": t,
                    "seeds": len(seeds),
                    "false_terms": false_terms / len(seeds),
                    "err_rms_arcsec": math.sqrt(np.mean(err2)) * ARCSEC_PER_DEG,
                    "z_rms": math.sqrt(np.mean(z2)),
                    # delta method over seeds (a seed's stops share one map: not independent)
                    "z_rms_se": float(np.std(z2) / (2 * math.sqrt(np.mean(z2) * len(z2)))),
                    "note": "10 stops per arc, linear strip; goal: false terms <= 1 %, z 0.8-1.25",
                }
            )
    return rows


def target_set_speed_row(repeat: int) -> Row:
    """The target-set fit (3 reflectors) against the circle fit on the same 700 stops."""
    cell = TrueCell.create(load_robot("kr500"), 1)
    camp = run_campaign(cell, CampaignOptions(joints=(4,), targets=3))
    sweep = camp.joint_sweeps()[4]
    first = sweep.target == 1
    pts = sweep.points_mm[first]
    grouped = np.stack([sweep.points_mm[sweep.target == t] for t in (1, 2, 3)], axis=1)
    sigma = camp.cell.tracker.sigma_mm(grouped.reshape(-1, 3)).reshape(grouped.shape[:2])
    circle = best_time(partial(fit_circle_3d, pts, sigma[:, 0]), repeat)
    targets = best_time(partial(fit_target_set, grouped, sigma), repeat)
    return {
        "benchmark": "target_set_fit",
        "n": int(grouped.shape[0]),
        "ours_s": targets,
        "circle_fit_s": circle,
        "ratio": targets / circle,
        "note": "3 reflectors, 700 stops (joint 4 both sweeps) vs one reflector's circle fit",
    }


def run(quick: bool, seeds: int | None = None) -> list[Row]:
    n_seeds = seeds or (2 if quick else 40)
    cases = [
        ("kr500", 0.0, 0.0, False),
        ("kr500", 0.03, 0.0, False),
        ("kr500", 0.03, 8.0, False),
        ("hp20d", 0.0, 0.0, False),
        ("hp20d", 0.03, 0.0, False),
        ("kr500", 0.03, 0.0, True),
        ("hp20d", 0.03, 0.0, True),
    ]
    if quick:
        cases = [cases[0], cases[-1]]
    rows: list[Row] = []
    for preset, ecc, hyst, gears in cases:
        rows += _accuracy_rows(preset, ecc, hyst, range(n_seeds), gears)
    if not quick:
        rows += detection_rows("kr500", (0.005, 0.01, 0.02, 0.05), range(20))
        rows += short_arc_rows((4.0, 20.0, 90.0, 470.0), (1, 3), range(1000))
    rows.append(target_set_speed_row(1 if quick else 5))
    desc = load_robot("kr500")
    cell = TrueCell.create(desc, 1, eccentricity_mm=0.03)
    t0 = time.perf_counter()
    camp = run_campaign(cell)
    t_gen = time.perf_counter() - t0
    repeat = 1 if quick else 5
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        calibrate_campaign(camp, desc)
        best = min(best, time.perf_counter() - t0)
    n = int(camp.sweep_joint.size)
    rows.append(
        {
            "benchmark": "calibrate_6_joints",
            "preset": "kr500",
            "n": n,
            "ours_s": best,
            "note": "n = stops of both sweeps, all joints; best of repeats",
        }
    )
    rows.append({"benchmark": "generate_campaign", "preset": "kr500", "n": n, "ours_s": t_gen})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_scale")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seeds", type=int, default=None)
    args = parser.parse_args(argv)
    from benchmarks import format_table

    print(format_table(run(args.quick, args.seeds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
