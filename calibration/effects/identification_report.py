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

This module builds report.json's document and the per-set errors
(:func:`build_report`); :mod:`calibration.effects.report_rendering` renders the Markdown
and the figures and writes the files.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
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
        # the sd's widening by the validation poses (0: their z RMS was at most 1 already)
        "extra_sd_mm": stage.extra_sd_mm,
        "validate_z_rms_before_extra_sd": _opt(stage.validate_z_rms),
        "elapsed_s": stage.fit_s,  # a timing: twin run strips it (bit-identical files)
    }


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
        "cross_validation": "leave one pose out"
        if loop.settings.leave_one_out
        else f"{loop.settings.folds} folds",
        # what a held-out pose is scored by (candidate_scoring.pose_deviance / pose_press)
        "cross_validation_score": "predictive deviance"
        if loop.settings.leave_one_out and loop.settings.loo_deviance
        else "squared error",
        "penalty_per_parameter_sigma2": loop.penalty_per_parameter,
        "n_candidates": loop.n_candidates,
        "candidate_kinds": list(loop.kinds),
        "elapsed_s": loop.elapsed_s,
        "stages": stages,
        "added": [s["effect"]["label"] for s in stages if "effect" in s],
        "set_aside": [r.as_dict() for r in loop.rejected],
        "stopped": _stopped(loop),
        "second_search": None if loop.second_search is None else loop.second_search.as_dict(),
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
