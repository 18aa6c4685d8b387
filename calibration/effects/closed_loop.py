"""The closed loop: residual → missing effect → extended model → before/after.

After the geometric identification, the residuals are searched for structure the tracker
noise cannot explain. Each candidate of :mod:`calibration.effects.effect_candidates` (the physical
library, then the generic search) is scored on the identification poses
(:mod:`calibration.effects.candidate_scoring`):

* **cross-validation**: each pose is left out in turn, the current model plus the
  candidate refitted without it predicts it (exact, by the hat matrix; K folds with
  ``LoopSettings(leave_one_out=False)``). The score is the drop of the held-out poses'
  predictive deviance (each miss weighed against the refitted model's uncertainty there,
  :func:`~calibration.effects.candidate_scoring.pose_deviance`; the PRESS, the squared
  misses, with ``loo_deviance=False``), in units of the noise variance σ̂², minus a penalty
  of ``ln(3m)`` per added parameter (BIC-like, m poses);
* **significance**: the partial F-test of the candidate's parameters on all identification
  poses, Bonferroni-corrected over the candidates of the round (``p·N < α``, α = 1e-3).
  A harmonic's orders are scanned (1..K, K from the joint's coverage and the number of
  poses): the best order is the scan's candidate, its p Šidák-corrected for the K orders.
  Beside an order of a joint in the model, only the orders the coverage resolves from it
  are scanned (:func:`~calibration.effects.effect_candidates.resolved_beside`).

A candidate is significant when both hold. A drift candidate is also tried as a
first-order lag, its time constant profiled (:mod:`calibration.effects.effect_shapes`). Of the
significant candidates the best penalized CV score is added, unless the data cannot tell
it from a significant candidate of a more physical kind (its columns lie within that
one's, principal angles after the model is projected out): then the physical priority
decides (a gravity term before a harmonic on a joint gravity loads). All parameters
(geometry and every effect so far) are then re-identified together by the LM of
:mod:`calibration.identify.identification`. The gravity term is scored in both its forms,
each on its own parameter count (:mod:`calibration.effects.gravity_form`): the physical one
(shared moments, compliance ratios profiled) and the linear one; added, it is kept in the
physical form unless the linear form is significant itself and significantly better. A step
that makes the validation error worse is undone and its candidate set aside. The search
repeats until no candidate is significant, the maximum number of effects is in, or too many
candidates were set aside; the result says which (:class:`StopReason`) and names the best
candidate left. Candidate columns a combination of the current model's are dropped first (a
constant tracker scale, for one, is exactly a scaling of every length and the base position:
it is reported as not identifiable rather than scored).

Refits inside the scoring are linear least squares on the model linearized at the current
solution (effects are sub-mm, the linearization error is far below the noise); only the
chosen model is refitted by the LM. The validation poses take no part in the choice of a
candidate; they give the before/after numbers of every stage and the evidence plots, and
they veto a step that made them worse.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.candidate_scoring import (
    CandidateScore,
    Competitor,
    LinearizedModel,
    choose,
    competitors,
)
from calibration.effects.effect_base import (
    EffectContext,
    EffectSpec,
    Evidence,
    ModelAtPoses,
)
from calibration.effects.effect_bending import bending_candidates
from calibration.effects.effect_candidates import (
    candidate_effects,
    resolved_candidates,
)
from calibration.effects.effect_coupling import (
    JointCoupling,
    coupling_candidates,
)
from calibration.effects.effect_kinds import (
    KINDS,
    regressor_matrix,
    split_values,
    to_descriptions,
)
from calibration.effects.gravity_form import (
    CouplingColumns,
    gravity_step,
    refit_physical_form,
)
from calibration.effects.loop_problem import LoopProblem, validation_set_name
from calibration.effects.loop_problem import LoopSettings as LoopSettings
from calibration.effects.loop_problem import campaign_effect_data as campaign_effect_data
from calibration.effects.loop_stop import Rejected, ScoredRound, StopReason, stop_reason
from calibration.effects.round_scoring import score_round
from calibration.effects.second_search import (
    GRAVITY_FIRST_REASON,
    SecondSearch,
    branch_point,
    gravity_shown,
    has_gravity,
    round_name,
)
from calibration.errors import IdentificationError
from calibration.identify.campaign_files import Campaign
from calibration.identify.identification import (
    IdentificationResult,
    LMSettings,
    ProgressCallback,
    base_start_from_registration,
)
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]
DEFAULT_SETTINGS = LoopSettings()
#: A tried step: the model's effects, its identification and the gravity form's decision,
#: or why the step failed.
_Tried = tuple[tuple[EffectSpec, ...], IdentificationResult, dict[str, Any]] | str

CRITERION = (
    "a candidate is added when its cross-validated error reduction on the "
    "identification poses (each pose left out in turn, exactly), in units of the "
    "noise variance, exceeds ln(3m) per parameter, "
    "and the partial F-test of its parameters, Bonferroni-corrected over the candidates of "
    "the round (a harmonic's best order Šidák-corrected for the orders scanned first), is "
    "significant (p·N < α); the best such candidate by penalized CV score "
    "is added (unless the data cannot tell it from a significant candidate of a more "
    "physical kind: then that one), everything is re-identified, and a step that makes the "
    "validation error worse is undone"
)


@dataclass(frozen=True, eq=False)
class EvidencePlot:
    """Validation residuals (``tracker − twin``) in the added effect's coordinate, each
    ``(m,)``: before it (the previous stage's), with it added back (this stage's residual
    plus the effect's own term: what the effect explains, the geometry refitted), and
    after it; ``model`` is the effect's term in the same coordinate."""

    x: FloatArray
    x_label: str
    y_label: str
    before: FloatArray
    partial: FloatArray
    after: FloatArray
    model: FloatArray


@dataclass(frozen=True, eq=False)
class Stage:
    """One row of the stage table: a model and its errors ``tracker − twin`` per set."""

    name: str  # "nominal", "geometric" or "effect"
    label: str
    model: KinematicModel
    specs: tuple[EffectSpec, ...] = ()
    effect_values: FloatArray = field(default_factory=lambda: np.zeros(0))
    result: IdentificationResult | None = None
    errors_mm: dict[str, FloatArray] = field(default_factory=dict)  # set -> (m, 3)
    added: CandidateScore | None = None
    round_scores: tuple[CandidateScore, ...] = ()
    evidence: EvidencePlot | None = None
    reason: str = ""  # why this candidate was chosen
    competitors: tuple[Competitor, ...] = ()
    shape: dict[str, Any] = field(default_factory=dict)  # profiled shape parameters

    def values_of(self, spec: EffectSpec) -> FloatArray:
        return split_values(self.specs, self.effect_values)[self.specs.index(spec)]

    def standard_errors_of(self, spec: EffectSpec) -> FloatArray:
        """Standard errors of one effect's parameters (NaN: held, not identified)."""
        assert self.result is not None
        se = self.result.standard_errors()[self.result.n_geometric :]
        return split_values(self.specs, se)[self.specs.index(spec)]

    def mean_ap(self, set_name: str) -> float:
        return mean_ap_mm(self.errors_mm[set_name])


#: A step whose identification points' RMS rises by more than this factor has failed.
_FAILED_FIT = 1.5
_FAILED_FIT_REASON = "the re-identification failed"


def _rms_mm(errors_mm: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.sum(errors_mm**2, axis=1))))


def mean_ap_mm(errors_mm: FloatArray) -> float:
    """Mean absolute positioning error of point errors ``(m, 3)`` mm."""
    return float(np.linalg.norm(errors_mm, axis=1).mean())


@dataclass(frozen=True, eq=False)
class ClosedLoopResult:
    """Every stage (nominal, geometric, + each added effect), the round that stopped and
    why it stopped."""

    stages: tuple[Stage, ...]
    last_round: tuple[CandidateScore, ...]
    settings: LoopSettings
    n_candidates: int
    penalty_per_parameter: float
    elapsed_s: float
    kinds: tuple[str, ...] = ()  # the candidate kinds offered
    rejected: tuple[Rejected, ...] = ()
    stop: StopReason = field(
        default_factory=lambda: StopReason("no_candidate_left", "no candidate is left to try")
    )
    second_search: SecondSearch | None = None  # made again with gravity first

    @property
    def final(self) -> Stage:
        return self.stages[-1]

    @property
    def geometric(self) -> Stage:
        return self.stages[1]

    @property
    def added(self) -> tuple[EffectSpec, ...]:
        return self.final.specs

    @property
    def result(self) -> IdentificationResult:
        assert self.final.result is not None
        return self.final.result

    def calibrated_description(self, template: RobotDescription) -> RobotDescription:
        """``template`` with the final geometry, base, tool and ``[[effect]]`` tables."""
        final = self.final
        desc = final.model.to_description(template)
        effects = to_descriptions(final.specs, final.effect_values, template.n_joints)
        return replace(desc, effects=effects)


def run_closed_loop(
    description: RobotDescription,
    campaign: Campaign,
    *,
    start: str = "description",
    loss: str = "linear",
    f_scale_mm: float | None = None,
    point_sigma_mm: ArrayLike | None = None,
    lm_settings: LMSettings | None = None,
    settings: LoopSettings = DEFAULT_SETTINGS,
    geometric: IdentificationResult | None = None,
    progress: ProgressCallback | None = None,
    say: Callable[[str], None] | None = None,
    kinds: Collection[str] | None = None,
    sweep_referenced: bool = False,
    sweep_configurations: ArrayLike | None = None,
) -> ClosedLoopResult:
    """Run the loop on a campaign (identification rows fit, validation rows report).

    ``point_sigma_mm`` ``(m_identify,)`` weights the identification poses as in
    :func:`~calibration.identify.identification.identify`; ``geometric`` reuses an existing
    geometric identification of the same poses. ``kinds`` (or ``settings.kinds``)
    restricts the candidate kinds. ``sweep_referenced`` and ``sweep_configurations``
    ``(n, n)`` rad: see :func:`campaign_effect_data` (the gravity term then models the
    deflection relative to each sweep's configuration). Long for its keyword options.
    """
    started = time.perf_counter()
    tell = say or (lambda _text: None)
    id_kwargs = dict(
        start=start,
        loss=loss,
        f_scale_mm=f_scale_mm,
        settings=lm_settings or LMSettings(),
        point_sigma_mm=point_sigma_mm,
        progress=progress,
    )
    problem = LoopProblem.of_campaign(
        description, campaign, id_kwargs, point_sigma_mm, sweep_referenced=sweep_referenced,
        sweep_configurations=sweep_configurations,
    )  # fmt: skip
    allowed = kinds if kinds is not None else settings.kinds
    span = _campaign_span(campaign)
    library = [_with_span(s, span) for s in candidate_effects(problem.ctx, allowed)]
    penalty = settings.penalty_per_parameter
    if penalty is None:
        penalty = math.log(3 * problem.m)
    stages = _first_stages(problem, geometric)
    tell(f"closed loop: {len(library)} candidate effects")
    refine = [allowed is None or k in allowed for k in ("link_bending", "joint_coupling")]
    search = _Search(problem, library, penalty, span, settings, tell, *refine)
    last_round, rejected, stop = search.run(stages)
    tell(f"closed loop: stopped: {stop.text}")
    second = _second_search(search, stages, last_round)
    if second is not None and second[0].kept:
        stages, (last_round, rejected, stop) = second[1], second[2]
    return ClosedLoopResult(
        stages=tuple(stages),
        last_round=tuple(last_round),
        settings=settings,
        n_candidates=len(library),
        penalty_per_parameter=penalty,
        elapsed_s=time.perf_counter() - started,
        kinds=tuple(KINDS) if allowed is None else tuple(allowed),
        rejected=tuple(rejected),
        stop=stop,
        second_search=None if second is None else second[0],
    )


_SearchEnd = tuple[list[CandidateScore], list[Rejected], StopReason]


def _second_search(
    search: _Search,
    stages: list[Stage],
    last_round: list[CandidateScore],
) -> tuple[SecondSearch, list[Stage], _SearchEnd] | None:
    """The search made again with the gravity term first
    (:mod:`~calibration.effects.second_search`) from the first round that showed the term
    with a larger cross-validated gain than the effect the search by score added there
    (:func:`branch_point`), when a validation set can judge the two: what it found, its stages
    and its end; None when it was not made."""
    problem, settings, tell = search.problem, search.settings, search.tell
    set_name = validation_set_name(problem.contexts)
    branch = (
        branch_point(stages, last_round, settings.alpha, settings.max_effects)
        if settings.gravity_first_search
        else None
    )
    if branch is None or set_name != "validate":
        return None
    k, shown = branch
    again = replace(search, tell=lambda t: tell(t.replace("closed loop:", "closed loop, again:")))
    at = round_name(k - 1)
    tell(f"closed loop: {shown.label} was shown in {at}: searching again from there with it first")
    alt = stages[:k]
    # the linear form, shown but not significant on its count, is the last resort of a
    # search that ended without gravity; beside a physical term the search found later,
    # 20 validation poses do not tell the two apart (docs/closed-loop.md)
    end = again.run(alt, gravity_first=True, linear_first=not has_gravity(stages[-1].specs))
    before, after = stages[-1].mean_ap(set_name), alt[-1].mean_ap(set_name)
    with_gravity = has_gravity(alt[-1].specs)
    undone = next((r.reason for r in end[1] if r.label == shown.label), "")
    second = SecondSearch(
        f"{shown.label} (corrected p {shown.p_adjusted:.2g}, CV gain {shown.cv_gain:.1f} σ²)",
        tuple(s.label for s in stages[-1].specs), tuple(s.label for s in alt[-1].specs),
        before, after, with_gravity, with_gravity and after < before, k - 1, undone,
    )  # fmt: skip
    tell(f"closed loop: {second.text}")
    return second, alt, end


@dataclass(frozen=True, eq=False)
class _Search:
    """The search's fixed inputs: the problem, the candidate library, the penalty per
    parameter (σ²), the campaign's time span (s), the settings and where to tell."""

    problem: LoopProblem
    library: list[EffectSpec]
    penalty: float
    span: tuple[float, ...]
    settings: LoopSettings
    tell: Callable[[str], None]
    bending: bool = True  # offer a link's bending once a physical gravity term is in
    coupling: bool = True  # and the shoulder joints' shared compliance

    def offered(
        self, specs: tuple[EffectSpec, ...], values: FloatArray, set_aside: set[EffectSpec]
    ) -> list[EffectSpec]:
        """The round's candidates: the library's not in the model or set aside (a joint's
        harmonic only at orders resolved from its orders in the model, unless the data
        carry scale maps from sweeps: there the loop's harmonics are corrections of maps
        measured over the joint's whole range, which the joint fit rounds fold into them,
        not terms extrapolated beyond the poses' angles), and the bending of
        the links and the shoulder's coupling from the model's gravity term
        (:func:`bending_candidates`, :func:`coupling_candidates`)."""
        offered = [s for s in self.library if s not in specs and s not in set_aside]
        offered = [s for s in offered if not _same_slot(s, specs)]
        offered = resolved_candidates(offered, specs, self.problem.ctx.data)
        parts = split_values(specs, values)
        if self.bending:
            offered += bending_candidates(self.problem.ctx, specs, parts, set_aside)
        if self.coupling:
            offered += coupling_candidates(self.problem.ctx, specs, parts, set_aside)
        return offered

    def stop(
        self,
        code: str,
        scored: ScoredRound | None,
        rejected: list[Rejected],
        set_aside: Collection[EffectSpec],
    ) -> StopReason:
        """Why the search stopped (``code``) and the best candidate left in ``scored``."""
        max_effects, max_rejected = self.settings.max_effects, self.settings.max_rejected
        return stop_reason(code, max_effects, max_rejected, scored, rejected, set_aside)

    def attempt(
        self,
        chosen: CandidateScore,
        result: IdentificationResult,
        specs: tuple[EffectSpec, ...],
        scored: ScoredRound,
        previous: Stage,
        linear_first: bool = False,
        guard: bool = True,
    ) -> _Step | str:
        """The step adding ``chosen``, guarded (:func:`_guarded`; ``guard``: by the
        validation set too). A re-identification that failed from the nominal start is
        tried once more from ``previous``'s geometry: on an emulated UR10, whose base start
        was ~66 mm off, the gravity term's fit stalled from the nominal start though the
        geometric fit had converged from it.
        ``linear_first``: the second search's gravity step may keep the linear form when the
        physical one cannot be fitted (:func:`_try_step`)."""

        def from_start(start: LoopProblem) -> _Step | str:
            tried = _try_step(start, result, specs, chosen.spec, scored, self.tell, linear_first)
            return _guarded(self.refit(tried), self.problem, previous, self.settings, guard)

        step = from_start(self.problem)
        if not (isinstance(step, str) and step.startswith(_FAILED_FIT_REASON)):
            return step
        self.tell(f"closed loop: {chosen.label}: {step}; identified again from the last stage")
        return from_start(self.problem.started_at(previous.model))

    def refit(self, step: _Tried) -> _Tried:
        """``step`` with its physical gravity term's ratios refitted beside an effect added
        after it (:func:`refit_physical_form`), when that lowers the SSE significantly;
        beside the shoulder's coupling too (``refit_beside_coupling``). Not beside a link's
        bending (its shape is the term's moments at the time, and would no longer mean
        what it says)."""
        linear = [s for s in self.library if s.kind == "gravity_deflection"]
        if isinstance(step, str) or not linear or not self.settings.refit_gravity_form:
            return step
        specs, result, _form = step
        on_gravity = any(
            KINDS[s.kind].built_on_gravity
            and (s.kind != JointCoupling.kind or not self.settings.refit_beside_coupling)
            for s in specs
        )
        if specs[-1].kind == "gravity_deflection" or on_gravity:
            return step
        problem = self.problem

        def linearize(
            res: IdentificationResult, model: tuple[EffectSpec, ...]
        ) -> tuple[LinearizedModel, FloatArray, CouplingColumns]:
            lin, sw, kin = problem.linearized(res, model, self.settings)
            return lin, problem.columns(linear[0], sw, kin), problem.coupling_columns(sw, kin)

        # from the step's own geometry: from the nominal start the UR10's refit stalled as
        # its steps did (_Search.attempt), and kept ratios fitted beside no cyclic error
        refit = refit_physical_form(
            problem.ctx, specs, result, linear[0], problem.started_at(result.model).identify,
            linearize, self.settings.coupling_on_profile,
        )  # fmt: skip
        if refit is None:
            return step
        self.tell(f"closed loop: gravity deflection, {refit[2]['gravity_form']['reason']}")
        return refit

    def run(
        self, stages: list[Stage], gravity_first: bool = False, linear_first: bool = False
    ) -> tuple[list[CandidateScore], list[Rejected], StopReason]:
        """Add effects round by round to ``stages`` (in place) from the last stage's
        identified model until no candidate is significant, the maximum number of effects
        is in or too many were set aside: the last round's scores, the candidates set aside
        and why it stopped. The maximum reached, one more round names the best one left.
        ``gravity_first``: its first round adds the gravity term it shows, penalized score
        or not (the second search); ``linear_first``: the linear form if need be."""
        problem, settings, tell = self.problem, self.settings, self.tell
        specs, result = stages[-1].specs, stages[-1].result
        assert result is not None  # the geometric stage and each effect's hold theirs
        rejected: list[Rejected] = []
        set_aside: set[EffectSpec] = set()
        while True:
            offered = self.offered(specs, result.effect_values, set_aside)
            if not offered:
                return [], rejected, self.stop("no_candidate_left", None, rejected, ())
            physical = not any(_is_physical(s) for s in set_aside)
            scored = score_round(
                problem, result, specs, offered, settings, self.penalty, self.span, physical,
                self.coupling,
            )  # fmt: skip
            scores = scored.scores
            if len(specs) >= settings.max_effects:
                stop = self.stop("max_effects", scored, rejected, set_aside)
                return scores, rejected, stop
            forced = gravity_shown(scores, settings.alpha) if gravity_first else None
            gravity_first = False
            if forced is None and not scores[0].significant:
                best = scores[0]
                tell(
                    f"closed loop: nothing significant left (best: {best.label}, "
                    f"CV gain {best.cv_gain:.1f} σ², corrected p {best.p_adjusted:.2g})"
                )
                stop = self.stop("none_significant", scored, rejected, set_aside)
                return scores, rejected, stop
            chosen, reason = (
                (forced, GRAVITY_FIRST_REASON)
                if forced is not None
                else choose(scored.lin, scores, scored.columns)
            )
            linear = forced is not None and linear_first
            # a forced gravity step is judged by the second search's end on the validation set:
            # a real term can raise it while a larger effect is unmodelled (closed-loop.md)
            step = self.attempt(chosen, result, specs, scored, stages[-1], linear, forced is None)
            if isinstance(step, str):
                rejected.append(Rejected(chosen.label, step))
                set_aside.add(chosen.spec)
                tell(f"closed loop: set aside {chosen.label}: {step}")
                if len(rejected) >= settings.max_rejected:
                    stop = self.stop("set_aside", scored, rejected, set_aside)
                    return scores, rejected, stop
                continue
            specs, result = step.specs, step.result
            stages.append(_effect_stage(step, chosen, reason, scored, stages[-1], problem))
            tell(
                f"closed loop: added {specs[-1].label} (CV gain {chosen.cv_gain:.1f} σ², "
                f"F {chosen.f_statistic:.1f}, corrected p {chosen.p_adjusted:.2g}; {reason})"
            )


def _first_stages(problem: LoopProblem, geometric: IdentificationResult | None) -> list[Stage]:
    """The nominal stage (its base registered on the points) and the geometric one (
    ``geometric``, or identified here)."""
    reference = base_start_from_registration(problem.nominal, problem.ctx.data.q_rad, problem.meas)
    nominal = Stage(
        "nominal", "nominal", reference, errors_mm=problem.errors(reference, (), np.zeros(0))
    )
    result = geometric or problem.identify((), None)
    return [
        nominal,
        Stage(
            "geometric",
            "geometric calibration",
            result.model,
            result=result,
            errors_mm=problem.errors(result.model, (), np.zeros(0)),
        ),
    ]


@dataclass(frozen=True, eq=False)
class _Step:
    """A re-identification with one more effect that the validation set accepted."""

    specs: tuple[EffectSpec, ...]  # the model's effects, the new one last
    result: IdentificationResult
    form: dict[str, Any]  # the gravity form decision (empty for other kinds)
    errors_mm: dict[str, FloatArray]  # set -> (m, 3) tracker − twin


def _guarded(
    step: _Tried,
    problem: LoopProblem,
    previous: Stage,
    settings: LoopSettings,
    guard: bool = True,
) -> _Step | str:
    """The step of :func:`_try_step` with its errors per set, or why it is undone: it
    failed, or (with the validation guard and ``guard``) it made the validation mean AP
    worse."""
    if isinstance(step, str):
        return step
    new_specs, new_result, form_info = step
    errors = problem.errors(new_result.model, new_specs, new_result.effect_values)
    fit_before, fit_after = (_rms_mm(e["identify"]) for e in (previous.errors_mm, errors))
    if fit_after > _FAILED_FIT * fit_before:
        # one more effect cannot fit its own points worse: the solver ended far from the
        # optimum (seen on an emulated UR10, its gravity term started off: 0.06 -> 58 mm)
        return (
            f"{_FAILED_FIT_REASON}: the identification points' RMS rose from "
            f"{fit_before:.4f} to {fit_after:.4f} mm: step undone"
        )
    set_name = validation_set_name(problem.contexts)
    before = previous.mean_ap(set_name)
    after = mean_ap_mm(errors[set_name])
    if guard and settings.validation_guard and set_name == "validate" and after > before:
        return f"the validation mean AP rose from {before:.4f} to {after:.4f} mm: step undone"
    return _Step(new_specs, new_result, form_info, errors)


def _effect_stage(
    step: _Step,
    chosen: CandidateScore,
    reason: str,
    scored: ScoredRound,
    previous: Stage,
    problem: LoopProblem,
) -> Stage:
    """The stage of an accepted step: its round's scores, competitors, shape and evidence."""
    shape: dict[str, Any] = {}
    if chosen.spec in scored.profiles:
        shape["time_constant"] = scored.profiles[chosen.spec].as_dict()
    shape.update(step.form)
    added_spec = step.specs[-1]
    own = [s for s in scored.scores if s.spec == added_spec]  # a gravity form's own score
    stage = Stage(
        "effect",
        f"+ {added_spec.label}",
        step.result.model,
        specs=step.specs,
        effect_values=step.result.effect_values,
        result=step.result,
        errors_mm=step.errors_mm,
        added=own[0] if own else replace(chosen, spec=added_spec),
        round_scores=tuple(scored.scores),
        reason=reason,
        competitors=competitors(scored.lin, chosen, scored.scores, scored.columns),
        shape=shape,
    )
    return replace(stage, evidence=_evidence(stage, previous, added_spec, problem.contexts))


def _campaign_span(campaign: Campaign) -> tuple[float, ...]:
    t = campaign.t_s
    if t is None or len(t) == 0 or not np.all(np.isfinite(t)):
        return ()
    return (float(np.min(t)), float(np.max(t)))


def _with_span(spec: EffectSpec, span: tuple[float, ...]) -> EffectSpec:
    """Polynomial time terms carry the campaign's span (held outside it when predicting)."""
    if KINDS[spec.kind].needs_time and not spec.shape:
        return replace(spec, span_s=span)
    return spec


def _same_slot(spec: EffectSpec, specs: tuple[EffectSpec, ...]) -> bool:
    """Whether the model already has this term in another form (a lag for a drift, the
    physical form of a gravity term)."""
    slot = KINDS[spec.kind].slot(spec)
    return any(KINDS[s.kind].slot(s) == slot for s in specs)


def _try_step(
    problem: LoopProblem,
    result: IdentificationResult,
    specs: tuple[EffectSpec, ...],
    spec: EffectSpec,
    scored: ScoredRound,
    tell: Callable[[str], None],
    linear_first: bool = False,
) -> _Tried:
    """Re-identify with ``spec`` added (a gravity term in the form the data supports,
    :func:`~calibration.effects.gravity_form.gravity_step`); a string says why the step
    failed. The linear gravity form may be kept when it is significant on its own
    parameter count, or, ``linear_first`` (the second search's gravity step, shown by the
    round's F-test and cross-validation), when the physical form could not be fitted."""
    if spec.kind == "gravity_deflection":
        forms = [s for s in scored.scores if s.spec.kind == spec.kind]
        linear = [s for s in forms if s.spec.parameter == "linear"]
        physical = [
            (s.spec, scored.gravity_fits[s.spec]) for s in forms if s.spec in scored.gravity_fits
        ]
        if linear:
            return gravity_step(
                problem.ctx, specs, result.effect_values, linear[0].spec,
                physical[0] if physical else None,
                linear[0].significant or (linear_first and not physical),
                problem.identify, tell,
            )  # fmt: skip
    new_specs = (*specs, spec)
    start = np.concatenate([result.effect_values, np.zeros(len(spec.parameter_names()))])
    try:
        return new_specs, problem.identify(new_specs, start), {}
    except IdentificationError as exc:
        return f"re-identification failed: {exc}"


def _is_physical(spec: EffectSpec) -> bool:
    return spec.kind == "gravity_deflection" and spec.parameter == "physical"


def _evidence(
    stage: Stage, previous: Stage, spec: EffectSpec, contexts: dict[str, EffectContext]
) -> EvidencePlot | None:
    """The added effect's evidence on the validation set (identification set without one)."""
    set_name = validation_set_name(contexts)
    ctx = contexts[set_name]
    kin = ModelAtPoses.of(stage.model, ctx.data.q_rad)
    values = stage.values_of(spec)
    sel = slice(0, len(ctx.data))
    ev: Evidence = KINDS[spec.kind].evidence(spec, values, ctx, sel, kin)
    term = regressor_matrix((spec,), ctx, sel, kin) @ values
    after = stage.errors_mm[set_name]
    return EvidencePlot(
        x=ev.x,
        x_label=ev.x_label,
        y_label=ev.y_label + f" ({set_name} set)",
        before=ev.project(previous.errors_mm[set_name]),
        partial=ev.project(after + term),
        after=ev.project(after),
        model=ev.project(term),
    )
