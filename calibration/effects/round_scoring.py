"""One round of the closed loop's search scored (:func:`score_round`): every offered
candidate's columns at the model's solution, a drift's time constant profiled, the gravity
term's physical form fitted beside its linear one, a harmonic's orders scanned, and each
candidate's cross-validated score and partial F-test
(:func:`~calibration.effects.candidate_scoring.score_candidate`)."""

from __future__ import annotations

from dataclasses import replace

from calibration.effects.candidate_scoring import LinearizedModel, best_of_scan, score_candidate
from calibration.effects.effect_base import EffectSpec, FloatArray, ModelAtPoses
from calibration.effects.effect_candidates import scan_key
from calibration.effects.effect_shapes import (
    PhysicalGravityFit,
    TimeConstantProfile,
    profile_time_constant,
)
from calibration.effects.gravity_form import physical_gravity, physical_parameter_count
from calibration.effects.loop_problem import LoopProblem, LoopSettings
from calibration.effects.loop_stop import ScoredRound
from calibration.identify.identification import IdentificationResult


def score_round(
    problem: LoopProblem,
    result: IdentificationResult,
    specs: tuple[EffectSpec, ...],
    offered: list[EffectSpec],
    settings: LoopSettings,
    penalty: float,
    span: tuple[float, ...],
    physical: bool = True,
    coupled: bool = True,
) -> ScoredRound:
    """Score every offered candidate against the model ``result`` with ``specs``; a drift
    is offered as a lag when the data says so; the gravity term's linear form also in its
    physical form (``physical``: unless that was set aside), scored on its own parameters
    (the compliance ratios but the reference joint's charged like a lag's τ)."""
    lin, sw, kin = problem.linearized(result, specs, settings)
    columns: dict[EffectSpec, FloatArray] = {}
    profiles: dict[EffectSpec, TimeConstantProfile] = {}
    extra: dict[EffectSpec, int] = {}
    for spec in offered:
        if spec.kind == "length_drift" and len(span) == 2 and span[1] > span[0]:
            profile = _profile_lag(problem, spec, sw, kin, lin, span)
            if profile.tau_s is not None:
                lag = replace(spec, shape=(profile.tau_s,), span_s=())
                profiles[lag] = profile
                extra[lag] = 1
                spec = lag
            else:
                profiles[spec] = profile
        columns[spec] = problem.columns(spec, sw, kin)
    fits: dict[EffectSpec, PhysicalGravityFit] = {}
    linear = [s for s in columns if s.kind == "gravity_deflection" and s.parameter == "linear"]
    form = None
    if linear and physical:
        coupling = problem.coupling_columns(sw, kin) if coupled else None
        form = physical_gravity(
            problem.ctx, problem.m, linear[0], lin, columns[linear[0]], coupling
        )
    if form is not None:
        phys_spec, fits[phys_spec] = form
        columns[phys_spec] = problem.columns(phys_spec, sw, kin)
        extra[phys_spec] = physical_parameter_count(phys_spec) - len(phys_spec.names)
    scanned = _scan_orders(lin, columns)
    n = len(columns)
    scores = [
        score_candidate(
            lin, spec, cols, n_candidates=n, alpha=settings.alpha, penalty=penalty,
            rtol=settings.rtol, extra_parameters=extra.get(spec, 0),
            scanned=scanned.get(spec, 1),
        )
        for spec, cols in columns.items()
    ]  # fmt: skip
    scores.sort(key=lambda c: (not c.significant, c.n_parameters == 0, -c.score))
    return ScoredRound(lin, scores, columns, profiles, fits)


def _scan_orders(
    lin: LinearizedModel, columns: dict[EffectSpec, FloatArray]
) -> dict[EffectSpec, int]:
    """Keep the best order of each harmonic scan in ``columns`` (in place, the others
    dropped: one candidate per scan in the round); how many orders each winner beat."""
    scans: dict[tuple[str, int], list[EffectSpec]] = {}
    for spec in columns:
        key = scan_key(spec)
        if key is not None:
            scans.setdefault(key, []).append(spec)
    scanned: dict[EffectSpec, int] = {}
    for specs in scans.values():
        best = specs[best_of_scan(lin, [columns[s] for s in specs])]
        for s in specs:
            if s != best:
                del columns[s]
        scanned[best] = len(specs)
    return scanned


def _profile_lag(
    problem: LoopProblem,
    spec: EffectSpec,
    sw: FloatArray,
    kin: ModelAtPoses,
    lin: LinearizedModel,
    span: tuple[float, ...],
) -> TimeConstantProfile:
    """A drift's time constant profiled over the campaign's ``span`` (s)."""

    def column_at(tau: float | None) -> FloatArray:
        s = replace(spec, shape=() if tau is None else (tau,), span_s=())
        return problem.columns(s, sw, kin)[:, 0]

    return profile_time_constant(lin, column_at, span[1] - span[0])
