"""The gravity term's physical form: shared compliance-weighted moments and compliance
ratios fitted from the linear candidate's columns (:func:`physical_gravity`), kept unless
the linear form is significantly better (:func:`form_decision`, an F-test)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import f as f_distribution

from calibration.effects.candidate_scoring import LinearizedModel
from calibration.effects.effect_base import EffectContext, EffectSpec
from calibration.effects.effect_gravity import counterbalance_term, joint_moment
from calibration.effects.effect_shapes import PhysicalGravityFit, fit_physical_gravity
from calibration.identify.identification import IdentificationResult

FloatArray = NDArray[np.float64]

#: Significance of the linear gravity form's extra freedom over the physical form.
PHYSICAL_FORM_ALPHA = 0.01


def physical_gravity(
    ctx: EffectContext,
    m: int,
    spec: EffectSpec,
    lin: LinearizedModel,
    cols: FloatArray,
) -> tuple[EffectSpec, PhysicalGravityFit] | None:
    """The physical form's spec and fit from the linear candidate's columns."""
    base = ctx.base_moments
    names = base.names
    blocks: dict[int, FloatArray] = {}
    own: list[int] = []  # counterbalance terms: a joint's own torque profile, not shared
    n_joints = ctx.description.n_joints
    for c, term in enumerate(spec.names):
        if counterbalance_term(term) is not None:
            own.append(c)
            continue
        j, moment = joint_moment(term, spec.kind, n_joints)
        block = blocks.setdefault(j, np.zeros((cols.shape[0], len(names))))
        block[:, names.index(moment)] = cols[:, c]
    if len(blocks) < 1:
        return None
    if own:  # fitted freely beside the shared moments: part of the model for the profile
        lin = LinearizedModel.build(  # (folds unused by the profile)
            lin.residual, np.hstack([lin.jacobian, cols[:, own]]), m, len(lin.folds), 0
        )
    fit = fit_physical_gravity(lin, blocks)
    if not fit.success or not np.all(np.isfinite(fit.ratios)):
        return None
    phys = EffectSpec(
        "gravity_deflection",
        parameter="physical",
        joints=fit.joints,
        names=names + tuple(spec.names[c] for c in own),
        shape=tuple(float(r) for r in fit.ratios),
    )
    return phys, fit


def form_decision(
    ctx: EffectContext,
    m: int,
    linear: IdentificationResult,
    phys: IdentificationResult,
    spec: EffectSpec,
    phys_spec: EffectSpec,
    fit: PhysicalGravityFit,
) -> dict[str, Any]:
    """Keep the physical form unless the linear one is significantly better (F-test)."""
    sse_lin = weighted_sse(linear)
    sse_phys = weighted_sse(phys)
    k_lin = len(spec.names)
    k_phys = len(phys_spec.names) + len(phys_spec.joints) - 1  # moments, own terms, ratios
    dof = 3 * m - int(np.count_nonzero(linear.free))
    d1 = max(k_lin - k_phys, 1)
    f_stat = ((sse_phys - sse_lin) / d1) / max(sse_lin / max(dof, 1), 1e-300)
    p = float(f_distribution.sf(max(f_stat, 0.0), d1, max(dof, 1)))
    kept = "physical" if p >= PHYSICAL_FORM_ALPHA else "linear"
    reason = (
        f"physical form kept ({k_phys} parameters against {k_lin}; the linear form's extra "
        f"freedom: F = {f_stat:.2f}, p = {p:.2g})"
        if kept == "physical"
        else f"linear form kept: the joints do not share the same moments (F = {f_stat:.2f}, "
        f"p = {p:.2g} < {PHYSICAL_FORM_ALPHA})"
    )
    stated = ctx.description.base is not None and (ctx.description.base.gravity is not None)
    return {
        "gravity_form": {
            "kept": kept,
            "reason": reason,
            "gravity_direction": [float(v) for v in ctx.gravity],
            "gravity_source": "the description's [base] gravity"
            if stated
            else "−z of the robot base frame (floor mounting, the default)",
            "f_statistic": float(f_stat),
            "p_value": p,
            "reference_joint": fit.reference,
            "joints": list(fit.joints),
            "compliance_ratio": [float(r) for r in fit.ratios],
            "compliance_ratio_se": [float(r) for r in fit.ratio_se],
            "moments": list(phys_spec.names[: len(fit.moments)]),
            "weighted_moment_urad": [float(w) for w in fit.moments],
            "weighted_moment_se_urad": [float(w) for w in fit.moment_se],
        }
    }


def weighted_sse(result: IdentificationResult) -> float:
    """The LM's weighted residual sum of squares at its solution."""
    r = np.asarray(result.optimize_result.fun, dtype=float)
    return float(r @ r)
