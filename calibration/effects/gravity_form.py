"""The gravity term's physical form: shared compliance-weighted moments and compliance
ratios fitted from the linear candidate's columns (:func:`physical_gravity`), kept unless
the linear form is significantly better (:func:`form_decision`, an F-test) and significant
on its own parameter count in the round; the re-identification of a chosen gravity term in
the form the data supports (:func:`gravity_step`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import f as f_distribution

from calibration.effects.candidate_scoring import LinearizedModel
from calibration.effects.effect_base import EffectContext, EffectSpec
from calibration.effects.effect_coupling import COUPLED_JOINTS, JointCoupling
from calibration.effects.effect_gravity import (
    counterbalance_term,
    gravity_groups,
    group_moment_name,
    joint_moment,
)
from calibration.effects.effect_kinds import split_values
from calibration.effects.effect_shapes import PhysicalGravityFit, fit_physical_gravity
from calibration.errors import IdentificationError
from calibration.identify.identification import IdentificationResult

FloatArray = NDArray[np.float64]
#: Re-identify with these effects from these start values (the closed loop's LM).
Identify = Callable[[tuple[EffectSpec, ...], FloatArray], IdentificationResult]

#: Significance of the linear gravity form's extra freedom over the physical form.
PHYSICAL_FORM_ALPHA = 0.01


#: The shoulder pair's coupling per base moment (:func:`coupling_moment_columns` with the
#: loop's weighted regressor), for a physical form fitted beside it.
CouplingColumns = Callable[[tuple[str, ...]], FloatArray]


def physical_gravity(
    ctx: EffectContext,
    m: int,
    spec: EffectSpec,
    lin: LinearizedModel,
    cols: FloatArray,
    coupling: CouplingColumns | None = None,
    beside_coupling: bool = False,
) -> tuple[EffectSpec, PhysicalGravityFit] | None:
    """The physical form's spec and fit from the linear candidate's columns.
    ``beside_coupling``: fitted with the coupling's κ beside from the start (the model
    holds the coupling already; :func:`refit_physical_form`).

    When the one-ratio-per-joint form cannot be fitted and ``coupling`` is given (the
    loop may add the shoulder's coupled compliance), it is fitted again with the
    coupling's κ beside it: a shoulder whose joints share compliance loads each joint
    with the other's torque, which no set of ratios holds (docs/closed-loop.md, "A
    coupled shoulder"). The form offered is still the gravity term alone, its ratios
    and moments from that fit; the coupling is offered on its own once it is in."""
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
    own_names = tuple(spec.names[c] for c in own)
    profile = _Profile(lin, blocks, m, cols[:, own], coupling, names, own_names)
    if beside_coupling and coupling is not None:
        fit = replace(profile.fit(True), beside_why="the coupling is in the model")
    else:
        fit = profile.fit(False)
    # the fit with the coupling beside is made once: not again when it did not converge
    if not (beside_coupling or _converged(fit)) and coupling is not None and _couples(ctx, blocks):
        fit = replace(profile.fit(True), beside_why="one ratio per joint alone did not converge")
    if not _converged(fit):
        return None
    if fit.groups:  # the limit form: a moment a named group owns loads its joints alone
        names = tuple(
            n if g == 0 else group_moment_name(fit.groups[g], n)
            for n, g in zip(names, fit.moment_group, strict=True)
        )
    phys = EffectSpec(
        "gravity_deflection",
        parameter="physical",
        joints=fit.joints,
        names=names + own_names,
        shape=tuple(float(r) for r in fit.ratios),
    )
    return phys, fit


@dataclass(frozen=True)
class _Profile:
    """The physical form's profile on the linearized model ``lin``: the joints' ``blocks``
    per base moment (``names``), the counterbalance terms' columns ``own`` ``(3m, c)``
    (``own_names``) fitted freely beside, and the shoulder's ``coupling`` columns."""

    lin: LinearizedModel
    blocks: dict[int, FloatArray]
    m: int
    own: FloatArray
    coupling: CouplingColumns | None
    names: tuple[str, ...]
    own_names: tuple[str, ...]

    def fit(self, beside_coupling: bool) -> PhysicalGravityFit:
        """The profile, with the coupling's κ beside (``beside_coupling``) or not.

        Beside it, the counterbalance's torque on the pair is coupled as gravity's is
        where the data show it: each term's coupled column joins its own, free (κ times
        its torque, a product the linear fit leaves apart), kept when the SSE drop is
        significant on their count (F-test at :data:`PHYSICAL_FORM_ALPHA`), and the
        torque the coupling carries is read back from it (``coupled_counterbalance``)."""
        if not beside_coupling or self.coupling is None:
            return fit_physical_gravity(self._beside(self.own), self.blocks)
        d = self.coupling(self.names)
        fit = fit_physical_gravity(self._beside(self.own), self.blocks, d)
        pair = [c for c, n in enumerate(self.own_names) if _term_joint(n) in COUPLED_JOINTS]
        if not pair or fit.groups:
            return fit
        extra = np.hstack([self.own, self.coupling(tuple(self.own_names[c] for c in pair))])
        both = fit_physical_gravity(self._beside(extra), self.blocks, d)
        kappa = both.coupling_ratio
        if kappa is None or kappa == 0.0 or both.groups or not both.success:
            return fit
        dof = len(self.lin.residual) - extra.shape[1] - self.lin.jacobian.shape[1]
        dof -= len(both.ratios) + len(both.moments)  # the ratios but the reference's, and κ
        if not _sse_drop_test(fit.sse, both.sse, len(pair), dof)[1] < PHYSICAL_FORM_ALPHA:
            return fit
        # the free columns' coefficients at the profile's solution (Frisch–Waugh: the
        # same as fitting them jointly with the form), over κ: the coupled torque
        w = both.moments
        form = sum(both.ratios[n] * self.blocks[j] @ w for n, j in enumerate(both.joints))
        y = -self.lin.residual - form - kappa * (d @ w)
        coef = np.linalg.lstsq(np.hstack([self.lin.jacobian, extra]), y, rcond=None)[0]
        torque = np.zeros(len(self.own_names))
        torque[pair] = coef[-len(pair) :] / kappa
        return replace(both, coupled_counterbalance=torque)

    def _beside(self, extra: FloatArray) -> LinearizedModel:
        """``lin`` with the columns ``extra`` fitted freely as part of the model."""
        if extra.shape[1] == 0:
            return self.lin
        return LinearizedModel.build(  # (folds unused by the profile)
            self.lin.residual, np.hstack([self.lin.jacobian, extra]), self.m, len(self.lin.folds), 0
        )


def _term_joint(name: str) -> int | None:
    """The joint a counterbalance term acts on (None: not such a term)."""
    cb = counterbalance_term(name)
    return None if cb is None else cb[0]


def _converged(fit: PhysicalGravityFit) -> bool:
    return fit.success and bool(np.all(np.isfinite(fit.ratios)))


def _couples(ctx: EffectContext, blocks: dict[int, FloatArray]) -> bool:
    """Whether the loop could add the shoulder pair's coupling beside this form
    (:func:`~calibration.effects.effect_coupling.coupling_candidates`)."""
    return ctx.data.sweep_reference is None and set(COUPLED_JOINTS) <= set(blocks)


def form_decision(
    ctx: EffectContext,
    m: int,
    linear: IdentificationResult,
    phys: IdentificationResult,
    spec: EffectSpec,
    phys_spec: EffectSpec,
    fit: PhysicalGravityFit,
    *,
    linear_eligible: bool = True,
) -> dict[str, Any]:
    """Keep the physical form unless the linear one is significantly better (F-test) and,
    ``linear_eligible``, significant on its own parameter count in the round."""
    sse_lin = weighted_sse(linear)
    sse_phys = weighted_sse(phys)
    k_lin = len(spec.names)
    k_phys = physical_parameter_count(phys_spec)
    dof = 3 * m - int(np.count_nonzero(linear.free))
    f_stat, p = _sse_drop_test(sse_phys, sse_lin, max(k_lin - k_phys, 1), dof)
    rejects = p < PHYSICAL_FORM_ALPHA
    kept = "linear" if rejects and linear_eligible else "physical"
    test = f"F = {f_stat:.2f}, p = {p:.2g}"
    if sse_lin > sse_phys:  # the linear form contains the physical one: its LM stopped short
        reason = (
            f"physical form kept ({k_phys} parameters against {k_lin}): the linear form, "
            f"which contains it, ended with a larger weighted SSE ({sse_lin:.1f} against "
            f"{sse_phys:.1f}: its fit did not converge), so nothing shows its extra freedom"
        )
        return _form_info(ctx, "physical", reason, phys_spec, fit, float(f_stat), p)
    if kept == "linear":
        reason = (
            f"linear form kept: the joints do not share the same moments ({test} < "
            f"{PHYSICAL_FORM_ALPHA})"
        )
    elif rejects:
        reason = (
            f"physical form kept ({k_phys} parameters against {k_lin}): the linear form's "
            f"extra freedom is significant ({test}) but the linear form is not significant "
            f"on its own {k_lin} parameters on these poses"
        )
    else:
        reason = (
            f"physical form kept ({k_phys} parameters against {k_lin}; the linear form's "
            f"extra freedom: {test})"
        )
    return _form_info(ctx, kept, reason, phys_spec, fit, float(f_stat), p)


def physical_parameter_count(phys_spec: EffectSpec) -> int:
    """The physical form's parameters: moments, counterbalance terms and the compliance
    ratios but each group's reference joint's (one group but in the limit form)."""
    return len(phys_spec.names) + len(phys_spec.joints) - max(len(gravity_groups(phys_spec)), 1)


def _form_info(
    ctx: EffectContext,
    kept: str,
    reason: str,
    phys_spec: EffectSpec,
    fit: PhysicalGravityFit,
    f_stat: float | None,
    p: float | None,
) -> dict[str, Any]:
    """The gravity form decision as the report keeps it (``f_stat``, ``p``: the linear
    form's extra freedom; None when the linear form could not be identified)."""
    stated = ctx.description.base is not None and (ctx.description.base.gravity is not None)
    if fit.groups:
        apart = "; ".join("+".join(str(j) for j in g) for g in fit.groups[1:])
        reason += (
            f"; limit form: these poses do not bound the compliance ratios between joint "
            f"groups {'+'.join(str(j) for j in fit.groups[0])} and {apart}, so each group "
            "shares its own moments"
        )
    if fit.coupling_ratio is not None:
        reason += (
            f"; ratios fitted with the shoulder's coupled compliance beside (κ "
            f"{fit.coupling_ratio:.3g}): {fit.beside_why}"
        )
    return {
        "gravity_form": {
            "kept": kept,
            "reason": reason,
            "gravity_direction": [float(v) for v in ctx.gravity],
            "gravity_source": "the description's [base] gravity"
            if stated
            else "−z of the robot base frame (floor mounting, the default)",
            "f_statistic": f_stat,
            "p_value": p,
            "reference_joint": fit.reference,
            "joints": list(fit.joints),
            "compliance_ratio": [float(r) for r in fit.ratios],
            "compliance_ratio_se": [float(r) for r in fit.ratio_se],
            "moments": list(phys_spec.names[: len(fit.moments)]),
            "weighted_moment_urad": [float(w) for w in fit.moments],
            "weighted_moment_se_urad": [float(w) for w in fit.moment_se],
            "groups": [list(g) for g in fit.groups] or [list(fit.joints)],
            "fitted_with_coupling_ratio": fit.coupling_ratio,
        }
    }


def gravity_step(
    ctx: EffectContext,
    specs: tuple[EffectSpec, ...],
    values: FloatArray,
    linear_spec: EffectSpec,
    physical: tuple[EffectSpec, PhysicalGravityFit] | None,
    linear_eligible: bool,
    identify: Identify,
    tell: Callable[[str], None],
) -> tuple[tuple[EffectSpec, ...], IdentificationResult, dict[str, Any]] | str:
    """Re-identify the model ``specs`` (effect values ``values``) with the gravity term
    added in the form the data supports; a string says why the step failed.

    Both forms are identified (the linear one for the F-test): the physical form
    (``physical``, None when it could not be fitted or was set aside) is kept unless the
    linear form is ``linear_eligible`` (significant on its own parameter count in the
    round) and significantly better (:func:`form_decision`). A form that fails to identify
    leaves the other, the linear one only when eligible.
    """
    m = len(ctx.data)
    failed: list[str] = []
    linear: IdentificationResult | None = None
    try:
        start = np.zeros(len(linear_spec.parameter_names()))
        linear = identify((*specs, linear_spec), np.concatenate([values, start]))
    except IdentificationError as exc:
        failed.append(f"linear form: {exc}")
    phys: IdentificationResult | None = None
    if physical is not None:
        phys_spec, fit = physical
        own = np.zeros(len(phys_spec.names) - len(fit.moments))
        try:
            phys = identify((*specs, phys_spec), np.concatenate([values, fit.moments, own]))
        except IdentificationError as exc:
            failed.append(f"physical form: {exc}")
            tell(f"closed loop: physical gravity form not kept: {exc}")
    if phys is None or physical is None:
        if linear is None or not linear_eligible:
            return "re-identification failed: " + "; ".join(failed or ["no gravity form"])
        info = {} if not failed else {"gravity_form": {"kept": "linear", "reason": failed[-1]}}
        return (*specs, linear_spec), linear, info
    phys_spec, fit = physical
    if linear is None:
        reason = f"physical form kept (the linear form could not be identified: {failed[0]})"
        info = _form_info(ctx, "physical", reason, phys_spec, fit, None, None)
    else:
        info = form_decision(
            ctx, m, linear, phys, linear_spec, phys_spec, fit, linear_eligible=linear_eligible
        )
    tell(f"closed loop: gravity deflection, {info['gravity_form']['reason']}")
    if info["gravity_form"]["kept"] == "physical":
        return (*specs, phys_spec), phys, info
    assert linear is not None
    return (*specs, linear_spec), linear, info


def _sse_drop_test(sse_reduced: float, sse_full: float, d1: int, dof: int) -> tuple[float, float]:
    """F statistic and p-value of a nested model's weighted SSE drop ``sse_reduced →
    sse_full`` on ``d1`` more parameters, ``dof`` the full model's residual degrees of
    freedom (at least 1). F is negative when the full model's fit stopped short."""
    dof = max(dof, 1)
    f_stat = ((sse_reduced - sse_full) / d1) / max(sse_full / dof, 1e-300)
    return float(f_stat), float(f_distribution.sf(max(f_stat, 0.0), d1, dof))


def weighted_sse(result: IdentificationResult) -> float:
    """The LM's weighted residual sum of squares at its solution."""
    r = np.asarray(result.optimize_result.fun, dtype=float)
    return float(r @ r)


#: The model's weighted linearisation at a result of ``specs``, the linear gravity
#: candidate's weighted columns ``(3m, k)`` there and the coupling's per base moment
#: (the closed loop's).
Linearize = Callable[
    [IdentificationResult, tuple[EffectSpec, ...]],
    tuple[LinearizedModel, FloatArray, CouplingColumns],
]


def refit_physical_form(
    ctx: EffectContext,
    specs: tuple[EffectSpec, ...],
    result: IdentificationResult,
    linear_spec: EffectSpec,
    identify: Identify,
    linearize: Linearize,
    coupling_on_profile: bool = True,
) -> tuple[tuple[EffectSpec, ...], IdentificationResult, dict[str, Any]] | None:
    """The model ``specs`` (fitted: ``result``) with its physical gravity term's compliance
    ratios fitted again beside the model's other effects, and the form's record for the
    report; None when it holds no physical term or the refit's SSE drop is not
    significant.

    The ratios are a shape the LM holds, profiled when the term is added on the residual
    of the model then, which a later effect (a cyclic error) was part of. With it in the
    model they are profiled again (:func:`physical_gravity` on the residual of the model
    without the term), the model re-identified from there and kept when the SSE drop is
    significant on the ratios' count (F-test at :data:`PHYSICAL_FORM_ALPHA`); the
    parameter count may not grow (a limit form splitting more groups is the loop's choice
    to score). Beside the shoulder's coupling the ratios are profiled with its κ beside on
    the residual of the model without both (its torques from the profile's own moments:
    the joint model), and re-identified from two starts, the coupling as it was added (its
    moments frozen then) and rebuilt on the profile (``coupling_on_profile``,
    :func:`_coupling_on_profile`): the lower SSE is the refit."""
    at = [i for i, s in enumerate(specs) if s.kind == "gravity_deflection"]
    if len(at) != 1 or specs[at[0]].parameter != "physical":
        return None
    i = at[0]
    coupled = [k for k, s in enumerate(specs) if s.kind == JointCoupling.kind]
    parts = split_values(specs, result.effect_values)
    keep = [k for k in range(len(specs)) if k != i and k not in coupled]
    others, rest = tuple(specs[k] for k in keep), [parts[k] for k in keep]
    try:
        without = identify(others, np.concatenate(rest) if rest else np.zeros(0))
    except IdentificationError:
        return None
    lin, cols, coupling = linearize(without, others)
    form = physical_gravity(
        ctx, len(ctx.data), linear_spec, lin, cols, coupling, beside_coupling=bool(coupled)
    )
    if form is None:
        return None
    phys_spec, fit = form
    if len(phys_spec.parameter_names()) > len(specs[i].parameter_names()):
        return None
    parts[i] = np.concatenate([fit.moments, np.zeros(len(phys_spec.names) - len(fit.moments))])
    start = (tuple(phys_spec if k == i else s for k, s in enumerate(specs)), parts)
    more = _coupling_on_profile(start, i, coupled, fit) if coupling_on_profile else []
    best = _lowest_sse([start, *more], identify)
    if best is None:
        return None
    new_specs, refit = best
    f_stat, p = _ratio_test(len(ctx.data), result, refit, phys_spec)
    if not p < PHYSICAL_FORM_ALPHA:
        return None
    rebuilt = fit if new_specs is not start[0] else None
    reason = _refit_reason(specs[-1].label, bool(coupled), rebuilt, f_stat, p)
    return new_specs, refit, _form_info(ctx, "physical", reason, phys_spec, fit, None, None)


def _refit_reason(
    beside: str, coupled: bool, rebuilt: PhysicalGravityFit | None, f_stat: float, p: float
) -> str:
    """The report's words for a refit kept beside the effect labelled ``beside``;
    ``rebuilt``: the profile the coupling was rebuilt on, when that start won."""
    return (
        f"physical form, its compliance ratios refitted beside {beside}"
        + (", profiled with the coupling's κ" if coupled else "")
        + (", the coupling rebuilt on the profile's moments" if rebuilt is not None else "")
        + (
            " and the counterbalance's torque"
            if rebuilt is not None and rebuilt.coupled_counterbalance is not None
            else ""
        )
        + f" (F = {f_stat:.2f}, p = {p:.2g})"
    )


def _lowest_sse(
    starts: list[tuple[tuple[EffectSpec, ...], list[FloatArray]]], identify: Identify
) -> tuple[tuple[EffectSpec, ...], IdentificationResult] | None:
    """The model identified from each start (its effects, their values per effect) of the
    lowest weighted SSE; None when no identification succeeded."""
    fits = []
    for specs, values in starts:
        try:
            fits.append((specs, identify(specs, np.concatenate(values))))
        except IdentificationError:
            continue
    return min(fits, key=lambda f: weighted_sse(f[1])) if fits else None


def _coupling_on_profile(
    start: tuple[tuple[EffectSpec, ...], list[FloatArray]],
    i: int,
    coupled: list[int],
    fit: PhysicalGravityFit,
) -> list[tuple[tuple[EffectSpec, ...], list[FloatArray]]]:
    """The refit's start ``start`` (its gravity term ``specs[i]``, profiled: ``fit``) with
    its coupling (``specs[k]``, ``coupled`` ``[k]``) rebuilt on the profile's moments and
    κ: the joint model the profile fitted, the coupling's torques from the term's own
    moments and the counterbalance's torque the profile read (``fit.coupled_counterbalance``);
    none when the model holds no coupling, the profile no κ, or it split the limit form."""
    if not coupled or fit.coupling_ratio is None or fit.groups:
        return []
    k = coupled[0]
    specs, parts = start
    names, shape = specs[i].names[: len(fit.moments)], tuple(float(w) for w in fit.moments)
    if fit.coupled_counterbalance is not None:
        names += specs[i].names[len(fit.moments) :]
        shape += tuple(float(w) for w in fit.coupled_counterbalance)
    rebuilt = EffectSpec(JointCoupling.kind, joints=COUPLED_JOINTS, names=names, shape=shape)
    values = [np.array([fit.coupling_ratio]) if n == k else v for n, v in enumerate(parts)]
    return [(tuple(rebuilt if n == k else s for n, s in enumerate(specs)), values)]


def _ratio_test(
    m: int, held: IdentificationResult, refit: IdentificationResult, phys_spec: EffectSpec
) -> tuple[float, float]:
    """F statistic and p-value of the refit's SSE drop on the ratios' count. The ratios
    move only when the data say they are off: a look-alike added after the term, taking
    part of the deflection itself, would otherwise pull them to itself."""
    sse_held, sse_refit = weighted_sse(held), weighted_sse(refit)
    d1 = max(physical_parameter_count(phys_spec) - len(phys_spec.names), 1)
    return _sse_drop_test(sse_held, sse_refit, d1, 3 * m - int(np.count_nonzero(refit.free)) - d1)
