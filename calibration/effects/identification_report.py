"""The identification report: the source's Table 3 and more, as JSON, Markdown and PNG.

Errors are ``tracker − twin`` per pose. For the 3-D distance AP and for each axis (AP_X,
AP_Y, AP_Z, absolute values) the report gives max, min, mean, standard deviation and
``mean + 3·std`` (the source's "accuracy ±" figure), for the identification and the
validation set, before and after calibration. *Before* is the nominal geometry and tool
with the base pose from a rigid registration on the identification points (the best the
uncalibrated robot can do in the tracker frame); *after* is the identified model.

Improvement factors are given twice: ``before / after`` and the source's definition
``(before − after) / after`` (its "4.97× better" for a mean of 0.8672 → 0.1452 mm).

With the closed loop (:mod:`calibration.effects.closed_loop`) *after* is the final model with its
effect terms, and the report adds the stage table (nominal → geometric calibration → +
each added effect: max, min, mean and standard deviation of AP and per axis on each set),
every added effect's parameters with their standard errors and the evidence that gave it
away (residuals against its regressor on the validation set, before and after, as PNG),
one sentence per stage in the Markdown, and why the search stopped.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.closed_loop import CRITERION, ClosedLoopResult, Stage
from calibration.effects.effect_kinds import KINDS
from calibration.effects.learned_residual import CRITERION as LEARNED_CRITERION
from calibration.effects.learned_residual import LearnedStage
from calibration.identify.campaign_files import Campaign
from calibration.identify.identification import (
    IdentificationResult,
    base_start_from_registration,
    effect_unit,
)
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel, tcp_positions

FloatArray = NDArray[np.float64]

STATISTICS = ("max", "min", "mean", "std", "mean_plus_3std")
COMPONENTS = ("AP", "AP_X", "AP_Y", "AP_Z")
REPORT_FILES = (
    "report.json",
    "report.md",
    "errors_identify.png",
    "errors_validate.png",
    "error_histogram.png",
)


def accuracy_statistics(errors_mm: ArrayLike) -> dict[str, dict[str, float]]:
    """Table-3 statistics of per-pose errors ``(m, 3)`` mm: AP (3-D) and |AP_X|, |AP_Y|, |AP_Z|."""
    e = np.atleast_2d(np.asarray(errors_mm, dtype=float))
    comps = {
        "AP": np.linalg.norm(e, axis=1),
        "AP_X": np.abs(e[:, 0]),
        "AP_Y": np.abs(e[:, 1]),
        "AP_Z": np.abs(e[:, 2]),
    }
    out = {}
    for name, v in comps.items():
        std = float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
        out[name] = {
            "max": float(v.max()),
            "min": float(v.min()),
            "mean": float(v.mean()),
            "std": std,
            "mean_plus_3std": float(v.mean() + 3.0 * std),
        }
    return out


def improvement_factors(
    before: Mapping[str, Mapping[str, float]], after: Mapping[str, Mapping[str, float]]
) -> dict[str, dict[str, dict[str, float | None]]]:
    """Per component and statistic: ``ratio`` (before/after) and ``source`` ((b − a)/a)."""
    out: dict[str, dict[str, dict[str, float | None]]] = {}
    for comp in COMPONENTS:
        out[comp] = {}
        for stat in STATISTICS:
            b, a = before[comp][stat], after[comp][stat]
            ratio = b / a if a > 0 else None
            out[comp][stat] = {
                "ratio": ratio,
                "source": (b - a) / a if a > 0 else None,
            }
    return out


@dataclass(frozen=True)
class SetErrors:
    """Per-pose errors ``(m, 3)`` mm of one set, before and after calibration."""

    name: str
    pose: tuple[str, ...]
    before_mm: FloatArray
    after_mm: FloatArray


def before_model(nominal: KinematicModel, q_rad: ArrayLike, points_mm: ArrayLike) -> KinematicModel:
    """The uncalibrated reference: nominal geometry and tool, base registered on the points."""
    return base_start_from_registration(nominal, q_rad, points_mm)


def set_errors(
    campaign: Campaign, reference: KinematicModel, identified: KinematicModel
) -> list[SetErrors]:
    """Errors of the identify and validate sets (sets with no rows are left out)."""
    out = []
    for name in ("identify", "validate"):
        mask = campaign.mask(name)
        if not mask.any():
            continue
        q = campaign.q_rad[mask]
        pts = campaign.xyz_mm[mask]
        out.append(
            SetErrors(
                name=name,
                pose=tuple(p for p, m in zip(campaign.pose, mask, strict=True) if m),
                before_mm=pts - tcp_positions(reference, q),
                after_mm=pts - tcp_positions(identified, q),
            )
        )
    return out


def encoder_statistics(campaign: Campaign) -> list[dict[str, float]] | None:
    """Per joint: mean, standard deviation and max |·| of encoder − grating angle (deg).

    What the gratings correct: backlash, torsion and lost counts seen by the motor encoders.
    None when the campaign has no encoder columns.
    """
    if campaign.encoder_deg is None:
        return None
    diff = campaign.encoder_deg - campaign.q_deg
    return [
        {
            "joint": i + 1,
            "mean": float(d.mean()),
            "std": float(d.std(ddof=1)) if len(d) > 1 else 0.0,
            "max_abs": float(np.abs(d).max()),
        }
        for i, d in enumerate(diff.T)
    ]


def build_report(
    result: IdentificationResult,
    description: RobotDescription,
    campaign: Campaign,
    *,
    robot_source: str,
    calibrated_path: str | None = None,
    closed_loop: ClosedLoopResult | None = None,
    learned: LearnedStage | None = None,
) -> tuple[dict[str, Any], list[SetErrors]]:
    """The JSON document of the report and the per-set errors it was made from.

    With ``closed_loop``, ``result`` is its final identification and *after* is the final
    model with its effect terms; the document gains a ``closed_loop`` section. With
    ``learned`` (the learned residual stage's decision) a ``learned_residual`` section:
    the "unexplained residual (learned)", kept apart from the traced effects.
    """
    nominal = KinematicModel.from_description(description)
    idm = campaign.mask("identify")
    reference = before_model(nominal, campaign.q_rad[idm], campaign.xyz_mm[idm])
    if closed_loop is None:
        errors = set_errors(campaign, reference, result.model)
    else:
        errors = _loop_errors(campaign, closed_loop)
    id_poses = [p for p, m in zip(campaign.pose, idm, strict=True) if m]
    doc: dict[str, Any] = {
        "robot": {"name": description.name, "source": robot_source},
        "data": _data_section(campaign),
        "encoder_minus_grating_deg": encoder_statistics(campaign),
        "calibrated_model": calibrated_path,
        "before_definition": (
            "nominal geometry and tool, base pose from a rigid registration of the nominal "
            "TCPs onto the identification points"
        ),
        "start": result.start_method,
        "solver": _solver_section(result),
        "noise_sigma_mm": result.sigma_mm,
        "reference_sigma_mm": result.reference_sigma_mm,
        "identifiability": result.identifiability.as_dict(),
        "parameters": result.parameter_table(),
        "outlier_poses": [id_poses[i] for i in np.flatnonzero(result.outliers)],
        "sets": _set_sections(errors),
    }
    if closed_loop is not None:
        doc["closed_loop"] = closed_loop_document(closed_loop, description.n_joints)
    if learned is not None:
        doc["learned_residual"] = learned_residual_document(learned)
    return doc, errors


def learned_residual_document(stage: LearnedStage) -> dict[str, Any]:
    """The learned stage's section: the decision, its share of the traced model's error
    (leave-one-out on the identification poses), the validation before/after."""
    h = stage.hyper
    return {
        "name": "unexplained residual (learned)",
        "accepted": stage.accepted,
        "reason": stage.reason,
        "criterion": LEARNED_CRITERION,
        "share_of_traced_mean_square": stage.share,
        "p_value": stage.p_value,
        "identify_mean_AP_mm": {"traced": stage.identify_mean_mm, "learned_loo": stage.loo_mean_mm},
        "validate_mean_AP_mm": {
            "traced": _opt(stage.validate_before_mm),
            "learned": _opt(stage.validate_after_mm),
        },
        "kernel": {
            "length_scales_rad": list(h.length_scales),
            "signal_sd_mm": h.signal_sd_mm,
            "noise_sd_mm": h.noise_sd_mm,
        },
        "elapsed_s": stage.fit_s,  # a timing: twin run strips it (bit-identical files)
    }


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
        "",
        f"Criterion: {sec['criterion']}.",
        "",
    ]
    return lines


def _loop_errors(campaign: Campaign, closed_loop: ClosedLoopResult) -> list[SetErrors]:
    """Per set: the loop's nominal stage's errors before, its final model's after."""
    return [
        SetErrors(
            name=name,
            pose=tuple(p for p, m in zip(campaign.pose, campaign.mask(name), strict=True) if m),
            before_mm=closed_loop.stages[0].errors_mm[name],
            after_mm=closed_loop.final.errors_mm[name],
        )
        for name in ("identify", "validate")
        if name in closed_loop.final.errors_mm
    ]


def _set_sections(errors: list[SetErrors]) -> dict[str, Any]:
    """Per set: its poses, the statistics before and after, and the improvement."""
    sets: dict[str, Any] = {}
    for se in errors:
        before = accuracy_statistics(se.before_mm)
        after = accuracy_statistics(se.after_mm)
        sets[se.name] = {
            "n_poses": len(se.pose),
            "before": before,
            "after": after,
            "improvement": improvement_factors(before, after),
        }
    return sets


def _data_section(campaign: Campaign) -> dict[str, Any]:
    return {
        "source": campaign.source,
        "n_rows": len(campaign),
        "n_identify": int(campaign.mask("identify").sum()),
        "n_validate": int(campaign.mask("validate").sum()),
        "skipped_rows": len(campaign.skipped),
        "skipped": [{"line": s.line, "pose": s.pose, "reason": s.reason} for s in campaign.skipped],
    }


def _solver_section(result: IdentificationResult) -> dict[str, Any]:
    opt = result.optimize_result
    return {
        "method": "Levenberg-Marquardt (analytic Jacobian, column-scaled damping)",
        "iterations": int(opt.nit),
        "function_evaluations": int(opt.nfev),
        "jacobian_evaluations": int(opt.njev),
        "status": int(opt.status),
        "message": opt.message,
        "success": bool(opt.success),
        "final_cost_mm2": float(opt.cost),
        "final_damping": float(opt.mu),
        "loss": result.loss,
        "f_scale_mm": result.f_scale_mm,
        "irls_iterations": result.irls_iterations,
        "elapsed_s": result.elapsed_s,
        "history": [
            {"iteration": i, "error_norm_mm": n, "damping": m} for i, n, m in result.history
        ],
    }


# -- the closed loop -----------------------------------------------------------------------
def _opt(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def evidence_file(index: int, stage: Stage) -> str:
    assert stage.added is not None
    return f"effect_{index}_{stage.added.spec.kind}.png"


def _effect_parameters(stage: Stage) -> list[dict[str, Any]]:
    assert stage.added is not None
    spec = stage.added.spec
    values, se = stage.values_of(spec), stage.standard_errors_of(spec)
    return [
        {
            "name": name,
            "unit": effect_unit(name),
            "value": float(v),
            "standard_error": _opt(e),
        }
        for name, v, e in zip(spec.parameter_names(), values, se, strict=True)
    ]


def _sentence(stage: Stage, previous: Stage | None, n_parameters: int, n_free: int) -> str:
    ap = {k: float(np.linalg.norm(e, axis=1).mean()) for k, e in stage.errors_mm.items()}
    set_name = "validate" if "validate" in ap else "identify"
    set_word = "validation" if set_name == "validate" else "identification"
    now = ap[set_name]
    if previous is None:
        return (
            f"Nominal geometry and tool with the base registered on the identification points: "
            f"{set_word} mean AP {now:.4f} mm."
        )
    before = float(np.linalg.norm(previous.errors_mm[set_name], axis=1).mean())
    gain = f"{set_word} mean AP {before:.4f} → {now:.4f} mm ({before / now:.2f}×)"
    if stage.added is None:
        return f"Geometric calibration ({n_free} of {n_parameters} parameters identified): {gain}."
    c = stage.added
    params = ", ".join(
        f"{p['name']} = {p['value']:.4g}"
        + (f" ± {p['standard_error']:.2g}" if p["standard_error"] is not None else "")
        for p in _effect_parameters(stage)
    )
    what = (
        "structure outside the physical library, modelled by an empirical term"
        if c.generic
        else KINDS[c.spec.kind].description
    )
    return (
        f"Added {c.label}: {what}; it lowered the cross-validated error by {c.cv_gain:.0f} σ² "
        f"(F = {c.f_statistic:.1f}, corrected p = {c.p_adjusted:.2g}); {params}; {gain}."
    )


def closed_loop_document(loop: ClosedLoopResult, n_joints: int) -> dict[str, Any]:
    """The ``closed_loop`` section of report.json."""
    stages = []
    previous: Stage | None = None
    for i, stage in enumerate(loop.stages):
        stages.append(_stage_entry(i, stage, previous))
        previous = stage
    return {
        "criterion": CRITERION,
        "alpha": loop.settings.alpha,
        "folds": loop.settings.folds,
        "penalty_per_parameter_sigma2": loop.penalty_per_parameter,
        "n_candidates": loop.n_candidates,
        "candidate_kinds": list(loop.kinds),
        "elapsed_s": loop.elapsed_s,
        "stages": stages,
        "added": [s["effect"]["label"] for s in stages if "effect" in s],
        "set_aside": [r.as_dict() for r in loop.rejected],
        "stopped": _stopped(loop),
    }


def _stage_entry(i: int, stage: Stage, previous: Stage | None) -> dict[str, Any]:
    """One stage of the ``closed_loop`` section: its errors per set, its sentence, and the
    effect it added."""
    n_par = n_free = 0
    if stage.result is not None:
        n_par = len(stage.result.parameter_names)
        n_free = stage.result.identifiability.rank
    entry: dict[str, Any] = {
        "stage": stage.name,
        "label": stage.label,
        "n_parameters": n_par,
        "n_identified": n_free,
        "sets": {
            name: {"n_poses": len(e), **accuracy_statistics(e)}
            for name, e in stage.errors_mm.items()
        },
        "sentence": _sentence(stage, previous, n_par, n_free),
    }
    if stage.added is not None:
        entry["effect"] = {
            "kind": stage.added.spec.kind,
            "label": stage.added.label,
            "generic": stage.added.generic,
            "parameters": _effect_parameters(stage),
            "selection": stage.added.as_dict(),
            "why_chosen": stage.reason,
            "competitors": [c.as_dict() for c in stage.competitors],
            "shape": stage.shape,
            "runners_up": [c.as_dict() for c in stage.round_scores[1:6]],
            "evidence_plot": evidence_file(i - 1, stage),
            "evidence_regressor": stage.evidence.x_label if stage.evidence else None,
        }
    return entry


def _stopped(loop: ClosedLoopResult) -> dict[str, Any]:
    """Why the search stopped (``code``, ``reason``), its best remaining candidate, the
    ones not identifiable."""
    return {
        **loop.stop.as_dict(),
        "not_identifiable": [
            {"effect": c.label, "note": c.note} for c in loop.last_round if c.n_parameters == 0
        ],
    }


# -- writers ----------------------------------------------------------------------------
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
    lines = [
        "## Closed loop: what the geometric model lacked",
        "",
        f"Criterion: {loop['criterion']} (α = {loop['alpha']:g}, {loop['folds']} folds, "
        f"penalty {loop['penalty_per_parameter_sigma2']:.1f} σ² per parameter, "
        f"{loop['n_candidates']} candidates, {loop['elapsed_s']:.2f} s).",
        "",
    ]
    lines += _stage_tables(stages)
    lines += ["### Stages", ""]
    lines += [f"{i}. {st['sentence']}" for i, st in enumerate(stages, start=1)]
    lines += _stopped_markdown(loop["stopped"])
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


def _evidence_figure(stage: Stage, path: Path) -> None:
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


def _error_figure(se: SetErrors, path: Path) -> None:
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


def _histogram(errors: list[SetErrors], path: Path) -> None:
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
        _error_figure(se, path)
        written.append(path)
    path = out / "error_histogram.png"
    _histogram(errors, path)
    written.append(path)
    if closed_loop is not None:
        for i, stage in enumerate(closed_loop.stages[2:], start=1):
            if stage.evidence is not None:
                path = out / evidence_file(i, stage)
                _evidence_figure(stage, path)
                written.append(path)
    return written
