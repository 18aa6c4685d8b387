"""Report of a grating-scale calibration: Markdown table, JSON, residual plots (PNG).

One row per joint: zero (and its spread), scale (and the effective strip radius), terms
kept, residual RMS (deg and arc-seconds), hysteresis, the common circle's radius, normal
and residual, and how the two sweep circles agree. The JSON carries the same numbers plus
every selection test; the plots show the relation's residuals per stop.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from calibration.scales.chain_scale import ChainCorrection
from calibration.scales.circle_fit import CircleFit
from calibration.scales.joint_scale_result import JointScaleResult, TermTest
from calibration.scales.scale_relation import ARCSEC_PER_DEG


def _radius_std_mm(fit: Any) -> float:
    """Standard deviation of a circle's radius (of the first target for a target set)."""
    if isinstance(fit, CircleFit):
        return float(fit.parameter_std[5])
    return float(fit.parameter_std[list(fit.parameter_names).index("radius_0_mm")])


def chain_summary(c: ChainCorrection | None, r: JointScaleResult) -> dict[str, Any]:
    """What the whole-chain fit removed from one joint's map, beside the circle-only fit."""
    if c is None:
        return {
            "whole_chain": False,
            "circle_only_residual_rms_arcsec": r.residual_rms_arcsec,
            "circle_only_terms": list(r.scale.terms),
        }
    out: dict[str, Any] = {
        "whole_chain": True,
        "circle_only_residual_rms_arcsec": c.circle_only_residual_arcsec,
        "circle_only_terms": list(c.circle_only.scale.terms),
        "upstream_motion_max_arcsec": {str(k): v for k, v in c.max_upstream_arcsec.items()},
        "upstream_uncalibrated": list(c.missing),
    }
    if c.own_deflection_arcsec is not None:
        out["modelled_own_deflection_rms_arcsec"] = c.own_deflection_arcsec[0]
        out["modelled_own_deflection_max_arcsec"] = c.own_deflection_arcsec[1]
        out["modelled_upstream_deflection_max_arcsec"] = {
            str(k): v for k, v in (c.upstream_deflection_arcsec or {}).items()
        }
    return out


def joint_summary(
    r: JointScaleResult, counts_per_mm: float = 1000.0, chain: ChainCorrection | None = None
) -> dict[str, Any]:
    """Plain numbers describing one joint's calibration (units in the key names)."""
    s = r.scale
    c = r.circle
    hyst = r.test("hysteresis")
    std_stops = s.angle_std_deg(r.stop_counts)
    crb_stops = r.crb_angle_std_deg
    return {
        "joint": r.joint,
        "zero_counts": s.zero_counts,
        "zero_spread_counts": r.home.spread_counts,
        "zero_std_counts": s.zero_std_counts,
        "zero_readings": r.home.n,
        "zero_source": r.home.source,
        "scale_deg_per_count": s.scale_deg_per_count,
        "scale_std_ppm": 1e6 * math.sqrt(s.covariance_deg2[0, 0]) / abs(s.scale_deg_per_count),
        "counts_per_deg": s.counts_per_deg,
        "effective_radius_mm": s.effective_radius_mm(counts_per_mm),
        "strip_direction": r.strip_direction,
        "terms": list(s.terms),
        "coefficients": dict(s.coefficients),
        "residual_rms_deg": r.residual_rms_deg,
        "residual_rms_arcsec": r.residual_rms_arcsec,
        "hysteresis_counts": s.hysteresis_counts,
        "hysteresis_arcsec": s.hysteresis_deg * ARCSEC_PER_DEG,
        "hysteresis_p_value": hyst.p_value if hyst else None,
        "angle_std_rms_arcsec": ARCSEC_PER_DEG * float(np.sqrt(np.mean(std_stops**2))),
        "angle_std_max_arcsec": ARCSEC_PER_DEG * float(std_stops.max()),
        "crb_angle_rms_arcsec": ARCSEC_PER_DEG * float(np.sqrt(np.mean(crb_stops**2))),
        "tracker_sigma_um": r.tracker_sigma_um,
        "circle": {
            "radius_mm": c.radius_mm,
            "radius_std_mm": _radius_std_mm(c),
            "centre_mm": [float(v) for v in c.centre_mm],
            "normal": [float(v) for v in c.normal],
            "residual_rms_um": 1e3 * c.residual_rms_mm,
            "points_used": c.n_inliers,
        },
        "targets": getattr(c, "n_targets", 1),
        "chain": chain_summary(chain, r),
        "pass_circles": {name: _pass_circle(pc) for name, pc in r.pass_circles.items()},
        "pass_agreement": _pass_agreement(r),
        "tests": [_test_row(t) for t in r.tests],
        "stops": int(r.used.size),
        "stops_used": int(r.used.sum()),
        "dropped": [{"stop": i, "reason": why} for i, why in r.dropped],
        "notes": list(r.notes),
    }


def _test_row(t: TermTest) -> dict[str, Any]:
    return {
        "term": t.term,
        "kept": t.kept,
        "f_statistic": t.f_statistic,
        "dof_term": t.dof_term,
        "dof_residual": t.dof_residual,
        "p_value": t.p_value,
        "threshold": t.threshold,
    }


def _pass_circle(pc: Any) -> dict[str, Any]:
    """One sweep's own circle (or target set)."""
    return {
        "radius_mm": pc.radius_mm,
        "radius_std_mm": _radius_std_mm(pc),
        "normal": [float(v) for v in pc.normal],
        "residual_rms_um": 1e3 * pc.residual_rms_mm,
        "points": pc.n_points,
        "wild_points": list(pc.outliers),
    }


def _pass_agreement(r: JointScaleResult) -> dict[str, float]:
    """How the forward and backward sweeps' circles agree (empty with one sweep)."""
    if len(r.pass_circles) != 2:
        return {}
    f, b = r.pass_circles["forward"], r.pass_circles["backward"]
    d_r = f.radius_mm - b.radius_mm
    return {
        "radius_difference_um": 1e3 * d_r,
        "radius_difference_sigma": d_r / math.hypot(_radius_std_mm(f), _radius_std_mm(b)),
        "normal_angle_arcsec": math.degrees(math.acos(min(1.0, abs(float(f.normal @ b.normal)))))
        * ARCSEC_PER_DEG,
        "centre_distance_um": 1e3 * float(np.linalg.norm(f.centre_mm - b.centre_mm)),
    }


def _markdown(rows: Sequence[Mapping[str, Any]], robot: str | None) -> str:
    out = [f"# Grating-scale calibration{f' — {robot}' if robot else ''}", ""]
    out += _joint_table(rows)
    out += ["", "## What the whole chain removed", ""]
    out += _chain_table(rows)
    out += ["", "## Term selection (nested F-tests)", ""]
    out += ["| joint | term | kept | F | dof | p | threshold |", "|---" * 7 + "|"]
    for r in rows:
        for t in r["tests"]:
            out.append(
                f"| {r['joint']} | {t['term']} | {'yes' if t['kept'] else 'no'} | "
                f"{t['f_statistic']:.2f} | {t['dof_term']}, {t['dof_residual']} | "
                f"{t['p_value']:.3g} | {t['threshold']:.3g} |"
            )
    out += ["", "## Uncertainty and circles", ""]
    out += _uncertainty_table(rows)
    notes = [(r["joint"], n) for r in rows for n in r["notes"]]
    notes += [
        (r["joint"], f"dropped stop {d['stop']}: {d['reason']}") for r in rows for d in r["dropped"]
    ]
    if notes:
        out += ["", "## Notes", ""] + [f"- joint {j}: {n}" for j, n in notes]
    return "\n".join(out) + "\n"


def _joint_table(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """One row per joint: zero, scale, terms, residual, hysteresis, circle."""
    out = [
        "| joint | zero counts (spread, n, source) | deg/count | counts/deg | R_eff mm | "
        "terms | rms deg | rms ″ | hysteresis counts (″, p) | circle R mm | normal | "
        "circle rms µm | dropped |",
        "|---" * 13 + "|",
    ]
    for r in rows:
        c = r["circle"]
        hp = r["hysteresis_p_value"]
        hyst = (
            f"{r['hysteresis_counts']:.2f} ({r['hysteresis_arcsec']:.2f}″, "
            f"{'-' if hp is None else f'{hp:.2g}'})"
        )
        normal = "(" + ", ".join(f"{v:+.5f}" for v in c["normal"]) + ")"
        out.append(
            f"| {r['joint']} | {r['zero_counts']:.1f} ({r['zero_spread_counts']:.2f}, "
            f"{r['zero_readings']}, {r['zero_source']}) | {r['scale_deg_per_count']:.6e} | "
            f"{r['counts_per_deg']:.3f} | {r['effective_radius_mm']:.4f} | "
            f"{', '.join(r['terms']) or '—'} | {r['residual_rms_deg']:.6f} | "
            f"{r['residual_rms_arcsec']:.2f} | {hyst} | {c['radius_mm']:.4f} | {normal} | "
            f"{c['residual_rms_um']:.1f} | {len(r['dropped'])} |"
        )
    return out


def _chain_table(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Per joint: the circle-only map beside the whole-chain one, and what moved upstream."""
    out = [
        "| joint | targets | circle-only rms ″ (terms) | whole-chain rms ″ (terms) | "
        "upstream joints moved (max ″) | modelled deflection taken out: own rms/max ″, "
        "upstream max ″ |",
        "|---" * 6 + "|",
    ]
    for r in rows:
        ch = r["chain"]
        moved = ", ".join(
            f"{k}: {v:.1f}" for k, v in ch.get("upstream_motion_max_arcsec", {}).items()
        )
        defl = "—"
        if "modelled_own_deflection_rms_arcsec" in ch:
            up = ", ".join(
                f"{k}: {v:.1f}" for k, v in ch["modelled_upstream_deflection_max_arcsec"].items()
            )
            defl = (
                f"{ch['modelled_own_deflection_rms_arcsec']:.1f}/"
                f"{ch['modelled_own_deflection_max_arcsec']:.1f}; {up or '—'}"
            )
        out.append(
            f"| {r['joint']} | {r['targets']} | {ch['circle_only_residual_rms_arcsec']:.2f} "
            f"({', '.join(ch['circle_only_terms']) or '—'}) | {r['residual_rms_arcsec']:.2f} "
            f"({', '.join(r['terms']) or '—'}) | {moved or '—'} | {defl} |"
        )
    return out


def _uncertainty_table(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Per joint: the stop angles' standard deviation and bound, the sweeps' agreement."""
    out = [
        "| joint | angle std rms ″ | angle std max ″ | CRB rms ″ | tracker σ µm | "
        "sweep circles ΔR µm (σ) | normals ∠ ″ |",
        "|---" * 7 + "|",
    ]
    for r in rows:
        a = r["pass_agreement"]
        agree = (
            f"{a['radius_difference_um']:.1f} ({a['radius_difference_sigma']:+.1f}) | "
            f"{a['normal_angle_arcsec']:.1f}"
            if a
            else "— | —"
        )
        out.append(
            f"| {r['joint']} | {r['angle_std_rms_arcsec']:.3f} | {r['angle_std_max_arcsec']:.3f}"
            f" | {r['crb_angle_rms_arcsec']:.3f} | {r['tracker_sigma_um']:.1f} | {agree} |"
        )
    return out


def plot_residuals(results: Sequence[JointScaleResult], path: str | Path) -> Path:
    """One panel per joint: relation residual (″) against the angle from Home, per sweep."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, axes = plt.subplots(n, 1, figsize=(9, 2.2 * n + 0.5), squeeze=False)
    for ax, r in zip(axes[:, 0], results, strict=True):
        std = ARCSEC_PER_DEG * r.stop_angle_std_deg
        for name, marker in (("forward", "v"), ("backward", "^")):
            m = (r.pass_name == name) & r.used
            ax.plot(
                r.stop_angle_deg[m],
                ARCSEC_PER_DEG * r.residual_deg[m],
                marker,
                ms=3,
                label=name,
            )
        order = np.argsort(r.stop_angle_deg)
        ax.fill_between(
            r.stop_angle_deg[order],
            -2 * std[order],
            2 * std[order],
            color="0.85",
            label="±2σ",
            zorder=0,
        )
        ax.axhline(0.0, color="0.4", lw=0.6)
        ax.set_ylabel(f"joint {r.joint}\nresidual ″")
        ax.set_title(
            f"joint {r.joint}: terms {', '.join(r.kept_terms) or 'none'}, "
            f"rms {r.residual_rms_arcsec:.2f}″",
            fontsize=9,
        )
    axes[-1, 0].set_xlabel("angle from Home (deg)")
    axes[0, 0].legend(loc="upper right", fontsize=7, ncols=3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def write_report(
    results: Sequence[JointScaleResult],
    out_dir: str | Path,
    *,
    robot: str | None = None,
    metadata: Mapping[str, Any] | None = None,
    counts_per_mm: float = 1000.0,
) -> dict[str, Path]:
    """Write ``report.md``, ``report.json`` and ``residuals.png`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    chain = getattr(results, "chain", {})
    rows = [joint_summary(r, counts_per_mm, chain.get(r.joint)) for r in results]
    paths = {"markdown": out / "report.md", "json": out / "report.json"}
    paths["markdown"].write_text(_markdown(rows, robot), encoding="utf-8")
    doc = {"robot": robot, "calibration": dict(metadata or {}), "joints": rows}
    paths["json"].write_text(json.dumps(doc, indent=2, default=_json_default), encoding="utf-8")
    if results:
        paths["plot"] = plot_residuals(results, out / "residuals.png")
    return paths


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serializable: {type(value).__name__}")
