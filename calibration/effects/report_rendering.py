"""The identification report rendered: Markdown for people, PNG figures, and the files.

:func:`markdown_report` renders report.json's document (:mod:`calibration.effects.
identification_report` builds it) as report.md: summary, Table 3 per set, parameters,
the closed loop's stages and effects, why it stopped, the learned residual. The figures:
per-pose errors per set, the error histogram, one evidence figure per added effect.
:func:`write_report` writes them all into a directory.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from calibration.effects.closed_loop import ClosedLoopResult, Stage
from calibration.effects.identification_report import (
    COMPONENTS,
    STATISTICS,
    SetErrors,
    evidence_file,
)


def _f(v: float | None, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}f}"


def markdown_report(doc: Mapping[str, Any]) -> str:
    """The report for people: summary, Table 3 per set, parameters, dropped parameters."""
    lines = [f"# Identification report: {doc['robot']['name']}", ""]
    lines += _summary_markdown(doc)
    if doc.get("closed_loop"):
        lines += _closed_loop_markdown(doc["closed_loop"])
    if doc.get("learned_residual"):
        lines += _learned_markdown(doc["learned_residual"])
    for set_name, s in doc["sets"].items():
        lines += _set_markdown(set_name, s)
    lines += [
        "## Identified parameters",
        "",
        "| parameter | start | identified | deviation | standard error |",
        "|---|---|---|---|---|",
    ]
    for p in doc["parameters"]:
        if not p["identified_from_data"]:
            continue
        lines.append(
            f"| {p['name']} | {_f(p['start'], 5)} | {_f(p['identified'], 5)} | "
            f"{_f(p['deviation'], 5)} | {_f(p['standard_error'], 5)} |"
        )
    if doc.get("encoder_minus_grating_deg"):
        lines += [
            "",
            "## Motor encoders minus gratings (deg)",
            "",
            "| joint | mean | std | max abs |",
            "|---|---|---|---|",
        ]
        lines += [
            f"| {e['joint']} | {_f(e['mean'], 5)} | {_f(e['std'], 5)} | {_f(e['max_abs'], 5)} |"
            for e in doc["encoder_minus_grating_deg"]
        ]
    lines += ["", "## Dropped parameters (held at their start values)", ""]
    dropped = doc["identifiability"]["dropped"]
    lines += [f"- `{d['name']}`: {d['reason']}" for d in dropped] or ["- none"]
    skipped = doc["data"]["skipped"]
    if skipped:
        lines += ["", "## Skipped rows", ""]
        lines += [
            f"- line {s['line']}"
            + (f" (pose {s['pose']})" if s["pose"] else "")
            + f": {s['reason']}"
            for s in skipped
        ]
    return "\n".join(lines) + "\n"


def _summary_markdown(doc: Mapping[str, Any]) -> list[str]:
    """The report's opening list: robot, data, solver, identifiability, noise, outliers."""
    data = doc["data"]
    solver = doc["solver"]
    ident = doc["identifiability"]
    return [
        f"- Robot description: `{doc['robot']['source']}`",
        f"- Data: `{data['source']}`: {data['n_identify']} identification poses, "
        f"{data['n_validate']} validation poses, {data['skipped_rows']} bad row(s) skipped",
        f"- Start of the base pose: {doc['start']}",
        f"- Solver: {solver['method']}, {solver['iterations']} iterations, "
        f"{solver['function_evaluations']} evaluations, {solver['elapsed_s']:.3f} s: "
        f"{solver['message']}; loss {solver['loss']}",
        f"- Identified {ident['n_identified']} of {ident['n_parameters']} parameters, "
        f"condition number of the scaled Jacobian {ident['condition_number']:.1f}",
        f"- Residual noise σ (per axis): {doc['noise_sigma_mm'] * 1000:.1f} µm"
        + (
            f" (stated by the point weights: {doc['reference_sigma_mm'] * 1000:.1f} µm)"
            if doc.get("reference_sigma_mm")
            else ""
        ),
        f"- Point weights: {solver.get('point_weights', 'none')}",
        f"- Outlier poses: {', '.join(doc['outlier_poses']) or 'none'}",
        f"- Before = {doc['before_definition']}",
        "",
    ]


def _set_markdown(set_name: str, s: Mapping[str, Any]) -> list[str]:
    """One set's Table 3: each component's statistics before and after, and the gains."""
    lines = [
        f"## {set_name.capitalize()} set ({s['n_poses']} poses), errors in mm",
        "",
        "| | max | min | mean | std | mean+3std |",
        "|---|---|---|---|---|---|",
    ]
    for comp in COMPONENTS:
        for when in ("before", "after"):
            st = s[when][comp]
            lines.append(f"| {comp} {when} | " + " | ".join(_f(st[k]) for k in STATISTICS) + " |")
        imp = s["improvement"][comp]
        lines.append(
            f"| {comp} improvement (before/after) | "
            + " | ".join(_f(imp[k]["ratio"], 2) for k in STATISTICS)
            + " |"
        )
    lines.append("")
    ap = s["improvement"]["AP"]["mean"]
    lines += [
        f"Mean AP improved {_f(ap['ratio'], 2)}× (before/after), "
        f"{_f(ap['source'], 2)}× by the source's (before − after)/after.",
        "",
    ]
    return lines


def _closed_loop_markdown(loop: Mapping[str, Any]) -> list[str]:
    stages = loop["stages"]
    scored = loop.get("cross_validation_score")  # absent from reports before 2026-11-28
    lines = [
        "## Closed loop: what the geometric model lacked",
        "",
        f"Criterion: {loop['criterion']} (α = {loop['alpha']:g}, "
        f"{loop.get('cross_validation', str(loop['folds']) + ' folds')}"
        f"{', each scored by its ' + scored if scored else ''}, "
        f"penalty {loop['penalty_per_parameter_sigma2']:.1f} σ² per parameter, "
        f"{loop['n_candidates']} candidates, {loop['elapsed_s']:.2f} s).",
        "",
    ]
    lines += _stage_tables(stages)
    lines += ["### Stages", ""]
    lines += [f"{i}. {st['sentence']}" for i, st in enumerate(stages, start=1)]
    lines += _stopped_markdown(loop["stopped"])
    if loop.get("second_search"):
        lines += ["", f"Searched again with gravity first: {loop['second_search']['text']}."]
    for st in stages:
        if st.get("effect"):
            lines += _effect_markdown(st["label"], st["effect"])
    if loop.get("set_aside"):
        lines += ["", "Set aside (chosen, then undone):"]
        lines += [f"- {r['effect']}: {r['reason']}" for r in loop["set_aside"]]
    lines.append("")
    return lines


def _stage_tables(stages: list[Mapping[str, Any]]) -> list[str]:
    """Per component, every stage's errors on the validation set (else identification)."""
    set_name = "validate" if "validate" in stages[0]["sets"] else "identify"
    lines: list[str] = []
    for comp in COMPONENTS:
        lines += [
            f"**{comp}, {set_name} set ({stages[0]['sets'][set_name]['n_poses']} poses), mm**",
            "",
            "| stage | max | min | mean | std |",
            "|---|---|---|---|---|",
        ]
        for st in stages:
            v = st["sets"][set_name][comp]
            lines.append(
                f"| {st['label']} | "
                + " | ".join(_f(v[k]) for k in ("max", "min", "mean", "std"))
                + " |"
            )
        lines.append("")
    return lines


def _stopped_markdown(stop: Mapping[str, Any]) -> list[str]:
    best = stop["best_remaining"]
    text = f"Stopped: {stop['reason']}"
    if best:
        significant = "significant" if best["significant"] else "not significant"
        text += (
            f" (best remaining: {best['effect']}, {significant}: CV score "
            f"{_f(best['score'], 1)} σ², CV gain {_f(best['cv_gain_sigma2'], 1)} σ², "
            f"corrected p {best['p_adjusted']:.2g})"
        )
    else:
        text += " (no identifiable candidate remains)"
    lines = ["", text + "."]
    if stop["not_identifiable"]:
        lines += [
            "Not identifiable from these data: "
            + "; ".join(f"{c['effect']} ({c['note']})" for c in stop["not_identifiable"])
            + "."
        ]
    return lines


def _effect_markdown(label: str, eff: Mapping[str, Any]) -> list[str]:
    """An added effect: its parameters, why it was chosen, its shape, its competitors and
    its evidence."""
    lines = [
        "",
        f"### {label}",
        "",
        "| parameter | value | standard error |",
        "|---|---|---|",
    ]
    lines += [
        f"| {p['name']} | {p['value']:.6g} | "
        + (f"{p['standard_error']:.3g}" if p["standard_error"] is not None else "–")
        + " |"
        for p in eff["parameters"]
    ]
    lines += ["", f"Why this effect: {eff.get('why_chosen') or 'best score'}."]
    lines += _shape_markdown(eff.get("shape") or {})
    if eff.get("competitors"):
        lines += [
            "",
            "| closest competitor | principal cosines | what separated them |",
            "|---|---|---|",
        ]
        lines += [
            f"| {c['effect']} | {', '.join(f'{x:.3f}' for x in c['principal_cosines'])} | "
            f"{c['separated_by']} |"
            for c in eff["competitors"]
        ]
    lines += [
        "",
        f"Evidence: `{eff['evidence_plot']}` (residuals against "
        f"{eff['evidence_regressor']}, before and after). Runners-up in that round: "
        + (
            ", ".join(f"{c['effect']} ({_f(c['score'], 1)})" for c in eff["runners_up"][:3])
            or "none"
        )
        + " (penalized CV score, σ²).",
    ]
    return lines


def _shape_markdown(shape: Mapping[str, Any]) -> list[str]:
    """The profiled shape parameters of an effect, for people."""
    lines: list[str] = []
    form = shape.get("gravity_form")
    if form:
        ratios = ", ".join(
            f"joint {j}: {r:.3g} ± {e:.2g}"
            for j, r, e in zip(
                form["joints"], form["compliance_ratio"], form["compliance_ratio_se"], strict=True
            )
        )
        moments = ", ".join(
            f"{m}: {w:.3g} ± {e:.2g}"
            for m, w, e in zip(
                form["moments"],
                form["weighted_moment_urad"],
                form["weighted_moment_se_urad"],
                strict=True,
            )
        )
        lines += [
            "",
            f"Gravity form: {form['reason']}. Gravity along "
            f"({', '.join(f'{v:g}' for v in form.get('gravity_direction', ()))}) of the robot "
            f"base frame: {form.get('gravity_source', '')}. Compliance ratios (joint "
            f"{form['reference_joint']} = 1): {ratios}. Compliance-weighted moments (µrad: "
            f"the reference joint's deflection from that moment alone, lever horizontal): "
            f"{moments}.",
        ]
    tau = shape.get("time_constant")
    if tau:
        lo, hi = tau["interval_s"]
        hi_text = "∞" if hi is None else f"{hi / 60.0:.1f}"
        lines += [
            "",
            f"Time constant: {tau['decision']}; profile minimum "
            f"{tau['profile_minimum_s'] / 60.0:.1f} min, {tau['confidence']:.0%} interval "
            f"[{lo / 60.0:.1f}, {hi_text}] min.",
        ]
    return lines


def _learned_markdown(sec: Mapping[str, Any]) -> list[str]:
    """The learned stage, apart from the traced effects."""
    verdict = "kept" if sec["accepted"] else "not kept"
    val = sec["validate_mean_AP_mm"]
    k = sec["kernel"]
    lines = [
        "## Unexplained residual (learned)",
        "",
        f"What the traced model (geometry and named effects) leaves, as a Gaussian process "
        f"over the joint angles: **{verdict}**, {sec['reason']}. It explains "
        f"{100 * sec['share_of_traced_mean_square']:.1f} % of the traced model's mean square "
        "error (leave-one-out on the identification poses): identification mean AP "
        f"{_f(sec['identify_mean_AP_mm']['traced'])} mm traced, "
        f"{_f(sec['identify_mean_AP_mm']['learned_loo'])} mm with it (left out).",
    ]
    if val["traced"] is not None:
        lines.append(
            f"Validation mean AP {_f(val['traced'])} mm traced, {_f(val['learned'])} mm with it."
        )
    lengths = ", ".join(f"{v:.3g}" for v in k["length_scales_rad"])
    lines += [
        "",
        f"Kernel: length scales {lengths} rad (joints 1–{len(k['length_scales_rad'])}), "
        f"signal {_f(k['signal_sd_mm'])} mm, noise {_f(k['noise_sd_mm'])} mm. "
        "It names no cause: whatever it models is still unexplained physics.",
    ]
    z = sec.get("validate_z_rms_before_extra_sd")
    if z is not None:
        extra = float(sec.get("extra_sd_mm", 0.0))
        lines.append(
            f"Its sd on the validation poses: z RMS {z:.2f} with the fitted noise; "
            + (
                f"widened by {_f(extra)} mm in quadrature to z RMS 1."
                if extra > 0
                else "not widened (never narrowed)."
            )
        )
    lines += [
        "",
        f"Criterion: {sec['criterion']}.",
        "",
    ]
    return lines


def evidence_figure(stage: Stage, path: Path) -> None:
    """Residuals in the added effect's coordinate against the regressor that gave it away:
    before it, with its own term added back (and the model), and after it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ev = stage.evidence
    assert ev is not None
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5), sharey=True)
    panels = (
        (axes[0], ev.before, "before: residual of the previous stage", "#d08770"),
        (axes[1], ev.partial, "the effect: residual + its term", "#8a6d2e"),
        (axes[2], ev.after, "after: residual of this stage", "#2e5c8a"),
    )
    for ax, values, title, color in panels:
        ok = np.isfinite(values)
        ax.scatter(ev.x[ok], values[ok], s=12, color=color, label="residual")
        ax.axhline(0.0, color="black", linewidth=0.5)
        ax.grid(alpha=0.3)
        ax.set_xlabel(ev.x_label)
        ax.set_title(title, fontsize=10)
    ok = np.isfinite(ev.model)
    axes[1].scatter(ev.x[ok], ev.model[ok], s=5, color="black", label="identified effect")
    axes[1].legend(loc="best", fontsize=8)
    axes[0].set_ylabel(ev.y_label)
    fig.suptitle(stage.label.removeprefix("+ "))
    fig.subplots_adjust(left=0.07, right=0.99, top=0.86, bottom=0.13, wspace=0.06)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def error_figure(se: SetErrors, path: Path) -> None:
    """Per-pose errors X, Y, Z and 3-D; before (left) and after (right), each on its own
    scale (after a good calibration the errors are far too small to see on the other)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 2, figsize=(13, 10), sharex=True)
    x = np.arange(len(se.pose))
    rows = [
        ("X", se.before_mm[:, 0], se.after_mm[:, 0]),
        ("Y", se.before_mm[:, 1], se.after_mm[:, 1]),
        ("Z", se.before_mm[:, 2], se.after_mm[:, 2]),
        ("3-D", np.linalg.norm(se.before_mm, axis=1), np.linalg.norm(se.after_mm, axis=1)),
    ]
    for r, (label, before, after) in enumerate(rows):
        for c, (values, color) in enumerate(((before, "#d08770"), (after, "#2e5c8a"))):
            ax = axes[r, c]
            # bars as a line collection: one Rectangle patch per bar is slow for 1000s
            ax.vlines(x, 0.0, values, color=color, linewidth=2.0)
            ax.axhline(0.0, color="black", linewidth=0.5)
            ax.grid(axis="y", alpha=0.3)
        axes[r, 0].set_ylabel(f"{label} error (mm)")
    axes[0, 0].set_title(f"before calibration ({se.name} set)")
    axes[0, 1].set_title(f"after calibration ({se.name} set)")
    for c in range(2):
        axes[-1, c].set_xlabel("pose (order in the campaign)")
    fig.suptitle("Per-pose position error, tracker − twin")
    fig.subplots_adjust(left=0.07, right=0.98, top=0.92, bottom=0.06, hspace=0.12, wspace=0.18)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def error_histogram(errors: list[SetErrors], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(errors), figsize=(5.5 * len(errors), 6.5), squeeze=False)
    for c, se in enumerate(errors):
        for r, (when, err, color) in enumerate(
            (("before", se.before_mm, "#d08770"), ("after", se.after_mm, "#2e5c8a"))
        ):
            ax = axes[r, c]
            ax.hist(np.linalg.norm(err, axis=1), bins=25, color=color)
            ax.set_xlabel("3-D error AP (mm)")
            ax.set_ylabel("poses")
            ax.set_title(f"{se.name} set, {when} calibration")
    fig.subplots_adjust(left=0.08, right=0.98, top=0.94, bottom=0.09, hspace=0.45, wspace=0.25)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_report(
    directory: str | Path,
    doc: Mapping[str, Any],
    errors: list[SetErrors],
    closed_loop: ClosedLoopResult | None = None,
) -> list[Path]:
    """Write report.json, report.md and the PNG figures into ``directory``; their paths.

    With ``closed_loop``, one evidence figure per added effect (``effect_<i>_<kind>.png``).
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "report.json", out / "report.md"]
    written[0].write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    written[1].write_text(markdown_report(doc), encoding="utf-8")
    for se in errors:
        path = out / f"errors_{se.name}.png"
        error_figure(se, path)
        written.append(path)
    path = out / "error_histogram.png"
    error_histogram(errors, path)
    written.append(path)
    if closed_loop is not None:
        for i, stage in enumerate(closed_loop.stages[2:], start=1):
            if stage.evidence is not None:
                path = out / evidence_file(i, stage)
                evidence_figure(stage, path)
                written.append(path)
    return written
