"""The closed loop: residual → missing effect → extended model → before/after.

After the geometric identification, the residuals are searched for structure the tracker
noise cannot explain. Each candidate of :mod:`calibration.effect_library` (the physical
library, then the generic search) is scored on the identification poses:

* **cross-validation**: the poses are split into K folds (5); the current model plus the
  candidate is refitted on K − 1 folds and predicts the held-out one. The score is the drop
  of the held-out sum of squared errors, in units of the noise variance σ̂², minus a
  penalty of ``ln(3m)`` per added parameter (BIC-like, m poses);
* **significance**: the partial F-test of the candidate's parameters on all identification
  poses, Bonferroni-corrected over the candidates of the round (``p·N < α``, α = 1e-3).

A candidate is significant when both hold (a positive penalized CV score and the corrected
F-test); the one with the best penalized CV score is added, all parameters (geometry and
every effect so far) are re-identified together by the LM of
:mod:`calibration.identification`, and the search repeats until no candidate is
significant. Candidate columns a combination of the current model's are dropped first (a
constant tracker scale, for one, is exactly a scaling of every length and the base
position: it is reported as not identifiable rather than scored).

Refits inside the scoring are linear least squares on the model linearized at the current
solution (effects are sub-mm, the linearization error is far below the noise); only the
chosen model is refitted by the LM. The validation poses take no part in the choice: they
give the before/after numbers of every stage and the evidence plots.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import f as f_distribution

from calibration.campaign_files import Campaign
from calibration.description import RobotDescription
from calibration.effect_library import (
    KINDS,
    EffectContext,
    EffectData,
    EffectSpec,
    Evidence,
    Kinematics,
    candidate_effects,
    check_kinds,
    effect_offsets_mm,
    effect_terms,
    regressor_matrix,
    split_values,
    to_descriptions,
)
from calibration.identification import (
    IdentificationError,
    IdentificationResult,
    LMSettings,
    ProgressCallback,
    base_start_from_registration,
    identify,
    stacked_jacobian,
)
from calibration.kinematics import KinematicModel, tcp_positions

FloatArray = NDArray[np.float64]

CRITERION = (
    "a candidate is added when its 5-fold cross-validated error reduction on the "
    "identification poses, in units of the noise variance, exceeds ln(3m) per parameter, "
    "and the partial F-test of its parameters, Bonferroni-corrected over the candidates of "
    "the round, is significant (p·N < α); the best such candidate by penalized CV score "
    "is added and everything is re-identified"
)


@dataclass(frozen=True)
class LoopSettings:
    """How the loop searches (see the module docstring for the criterion)."""

    folds: int = 5
    alpha: float = 1e-3  # family-wise false-positive probability per round
    penalty_per_parameter: float | None = None  # σ² per parameter; None: ln(3m)
    max_effects: int = 6
    kinds: tuple[str, ...] | None = None  # candidate kinds offered (None: all)
    fold_seed: int = 0
    rtol: float = 1e-6  # a candidate column this close to the model's span is dropped

    def __post_init__(self) -> None:
        if self.folds < 2:
            raise IdentificationError("the closed loop needs at least 2 folds")
        if not 0.0 < self.alpha < 1.0:
            raise IdentificationError("alpha must be in (0, 1)")
        if self.kinds is not None:
            check_kinds(self.kinds)


@dataclass(frozen=True)
class CandidateScore:
    """How one candidate did in one round."""

    spec: EffectSpec
    n_parameters: int  # identifiable parameters (columns not redundant with the model)
    cv_gain: float  # held-out SSE reduction / σ̂²
    score: float  # cv_gain − penalty · n_parameters
    f_statistic: float
    p_value: float
    p_adjusted: float  # Bonferroni: p · number of candidates (at most 1)
    significant: bool
    note: str = ""

    @property
    def label(self) -> str:
        return self.spec.label

    @property
    def generic(self) -> bool:
        return self.spec.generic

    def as_dict(self) -> dict[str, object]:
        return {
            "effect": self.label,
            "kind": self.spec.kind,
            "generic": self.generic,
            "n_parameters": self.n_parameters,
            "cv_gain_sigma2": _finite(self.cv_gain),
            "score": _finite(self.score),
            "f_statistic": _finite(self.f_statistic),
            "p_value": self.p_value,
            "p_adjusted": self.p_adjusted,
            "significant": self.significant,
            "note": self.note,
        }


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


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

    def values_of(self, spec: EffectSpec) -> FloatArray:
        return split_values(self.specs, self.effect_values)[self.specs.index(spec)]

    def standard_errors_of(self, spec: EffectSpec) -> FloatArray:
        """Standard errors of one effect's parameters (NaN: held, not identified)."""
        assert self.result is not None
        se = self.result.standard_errors()[self.result.n_geometric :]
        return split_values(self.specs, se)[self.specs.index(spec)]


@dataclass(frozen=True, eq=False)
class ClosedLoopResult:
    """Every stage (nominal, geometric, + each added effect), and the round that stopped."""

    stages: tuple[Stage, ...]
    last_round: tuple[CandidateScore, ...]
    settings: LoopSettings
    n_candidates: int
    penalty_per_parameter: float
    elapsed_s: float
    kinds: tuple[str, ...] = ()  # the candidate kinds offered

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


def campaign_effect_data(description: RobotDescription, campaign: Campaign) -> EffectData:
    """Effect data of a whole campaign: directions from its pose sequence (from Home)."""
    return EffectData.from_sequence(campaign.q_rad, campaign.t_s, np.radians(description.home))


def predict(
    stage_model: KinematicModel,
    specs: tuple[EffectSpec, ...],
    values: FloatArray,
    ctx: EffectContext,
) -> FloatArray:
    """Predicted tracker points ``(m, 3)`` mm of a model with effects at ``ctx``'s poses."""
    tcp = tcp_positions(stage_model, ctx.data.q_rad)
    if not specs:
        return tcp
    return tcp + effect_offsets_mm(specs, values, ctx, stage_model)


# -- scoring --------------------------------------------------------------------------------
def _scaled(a: FloatArray) -> FloatArray:
    s = np.sqrt(np.mean(a * a, axis=0))
    s[s == 0.0] = 1.0
    return a / s


def _keep_columns(basis_q: FloatArray, cols: FloatArray, rtol: float) -> NDArray[np.bool_]:
    """Which columns of ``cols`` ``(N, k)`` add a direction to the orthonormal ``basis_q``
    and to the columns kept before them (relative residual > rtol)."""
    q = basis_q
    keep = np.zeros(cols.shape[1], dtype=bool)
    for i in range(cols.shape[1]):
        c = cols[:, i]
        norm = float(np.linalg.norm(c))
        if norm == 0.0:
            continue
        r = c - q @ (q.T @ c)
        r = r - q @ (q.T @ r)
        rn = float(np.linalg.norm(r))
        if rn > rtol * norm:
            keep[i] = True
            q = np.column_stack([q, r / rn])
    return keep


def _cv_sse(residual: FloatArray, design: FloatArray, tests: list[NDArray[np.intp]]) -> float:
    """Held-out sum of squared errors of the least-squares fit of ``residual`` on
    ``design`` ``(N, q)``, each fold refitted without its test rows.

    The training normal equations are the full ones minus the test rows', so a fold costs
    ``O(N_test·q²)`` whatever the number of poses; a ``(q, q)`` least-squares solve keeps
    nearly dependent columns harmless.
    """
    gram = design.T @ design
    rhs = design.T @ residual
    total = 0.0
    for test in tests:
        a, r = design[test], residual[test]
        coef, *_ = np.linalg.lstsq(gram - a.T @ a, rhs - a.T @ r, rcond=None)
        e = r - a @ coef
        total += float(e @ e)
    return total


def score_candidates(
    residual: FloatArray,
    jacobian: FloatArray,
    candidates: list[tuple[EffectSpec, FloatArray]],
    n_poses: int,
    settings: LoopSettings,
    penalty: float,
) -> list[CandidateScore]:
    """Scores of candidates against the current model linearized at its solution.

    ``residual`` ``(3m,)`` and ``jacobian`` ``(3m, p)`` (free columns) are weighted like
    the fit; each candidate comes with its weighted regressor ``(3m, k)``.
    """
    n_rows = len(residual)
    j = _scaled(jacobian)
    q_basis, _ = np.linalg.qr(j)
    fit0 = residual - q_basis @ (q_basis.T @ residual)
    sse0 = float(fit0 @ fit0)
    p = j.shape[1]
    sigma2 = sse0 / max(n_rows - p, 1)
    pose_fold = np.random.default_rng(settings.fold_seed).permutation(n_poses) % settings.folds
    row_fold = np.repeat(pose_fold, 3)
    folds = [np.flatnonzero(row_fold == f) for f in range(settings.folds)]
    cv0 = _cv_sse(residual, j, folds)
    n_cand = max(len(candidates), 1)
    out = []
    for spec, cols in candidates:
        cs = _scaled(cols)
        keep = _keep_columns(q_basis, cs, settings.rtol)
        k = int(keep.sum())
        if k == 0:
            out.append(
                CandidateScore(
                    spec,
                    0,
                    0.0,
                    0.0,
                    0.0,
                    1.0,
                    1.0,
                    False,
                    "a combination of the parameters already in the model",
                )
            )
            continue
        ck = cs[:, keep]
        perp = ck - q_basis @ (q_basis.T @ ck)
        coef, *_ = np.linalg.lstsq(perp, fit0, rcond=None)
        e1 = fit0 - perp @ coef
        sse1 = float(e1 @ e1)
        dof = n_rows - p - k
        f_stat = ((sse0 - sse1) / k) / (sse1 / dof) if dof > 0 and sse1 > 0 else math.inf
        p_value = float(f_distribution.sf(f_stat, k, dof)) if dof > 0 else 1.0
        p_adj = min(1.0, p_value * n_cand)
        cv1 = _cv_sse(residual, np.hstack([j, ck]), folds)
        gain = (cv0 - cv1) / sigma2
        score = gain - penalty * k
        note = "" if k == cols.shape[1] else f"{cols.shape[1] - k} parameter(s) redundant"
        out.append(
            CandidateScore(
                spec,
                k,
                gain,
                score,
                f_stat,
                p_value,
                p_adj,
                bool(p_adj < settings.alpha and score > 0.0),
                note,
            )
        )
    return out


# -- the loop ---------------------------------------------------------------------------------
def _weighted_problem(
    result: IdentificationResult,
    model: KinematicModel,
    specs: tuple[EffectSpec, ...],
    values: FloatArray,
    ctx: EffectContext,
    meas: FloatArray,
    prior: FloatArray,
) -> tuple[FloatArray, FloatArray, NDArray[np.float64], Kinematics]:
    terms = effect_terms(specs, ctx) if specs else None
    q = ctx.data.q_rad
    sw = np.sqrt(prior * result.pose_weights)
    pred = predict(model, specs, values, ctx)
    residual = ((pred - meas) * sw[:, None]).ravel()
    jac = stacked_jacobian(model, q, terms)[:, :, result.free] * sw[:, None, None]
    return residual, jac.reshape(-1, jac.shape[-1]), sw, Kinematics.of(model, q)


def _errors(
    model: KinematicModel,
    specs: tuple[EffectSpec, ...],
    values: FloatArray,
    contexts: dict[str, EffectContext],
    points: dict[str, FloatArray],
) -> dict[str, FloatArray]:
    return {s: points[s] - predict(model, specs, values, contexts[s]) for s in contexts}


def run_closed_loop(
    description: RobotDescription,
    campaign: Campaign,
    *,
    start: str = "description",
    loss: str = "linear",
    f_scale_mm: float | None = None,
    point_sigma_mm: ArrayLike | None = None,
    lm_settings: LMSettings | None = None,
    settings: LoopSettings = LoopSettings(),
    geometric: IdentificationResult | None = None,
    progress: ProgressCallback | None = None,
    say: Callable[[str], None] | None = None,
    kinds: Collection[str] | None = None,
) -> ClosedLoopResult:
    """Run the loop on a campaign (identification rows fit, validation rows report).

    ``point_sigma_mm`` ``(m_identify,)`` weights the identification poses as in
    :func:`~calibration.identification.identify`; ``geometric`` reuses an existing
    geometric identification of the same poses. ``kinds`` (or ``settings.kinds``)
    restricts the candidate kinds.
    """
    started = time.perf_counter()
    tell = say or (lambda _text: None)
    nominal = KinematicModel.from_description(description)
    data = campaign_effect_data(description, campaign)
    masks = {s: campaign.mask(s) for s in ("identify", "validate")}
    masks = {s: m for s, m in masks.items() if m.any()}
    if "identify" not in masks:
        raise IdentificationError("the campaign has no identification poses")
    contexts = {s: EffectContext(description, data.subset(m)) for s, m in masks.items()}
    points = {s: campaign.xyz_mm[m] for s, m in masks.items()}
    ctx_id = contexts["identify"]
    q_id, meas = ctx_id.data.q_rad, points["identify"]
    m = len(q_id)
    prior = np.ones(m)
    if point_sigma_mm is not None:
        ps = np.broadcast_to(np.asarray(point_sigma_mm, dtype=float), (m,))
        prior = (1.0 / np.sqrt(np.mean(1.0 / ps**2)) / ps) ** 2
    id_kwargs = dict(
        start=start,
        loss=loss,
        f_scale_mm=f_scale_mm,
        settings=lm_settings or LMSettings(),
        point_sigma_mm=point_sigma_mm,
        progress=progress,
    )
    allowed = kinds if kinds is not None else settings.kinds
    library = candidate_effects(ctx_id, allowed)
    penalty = (
        math.log(3 * m)
        if settings.penalty_per_parameter is None
        else settings.penalty_per_parameter
    )

    reference = base_start_from_registration(nominal, q_id, meas)
    stages = [
        Stage(
            "nominal",
            "nominal",
            reference,
            errors_mm=_errors(reference, (), np.zeros(0), contexts, points),
        )
    ]
    result = geometric or identify(nominal, q_id, meas, **id_kwargs)  # type: ignore[arg-type]
    stages.append(
        Stage(
            "geometric",
            "geometric calibration",
            result.model,
            result=result,
            errors_mm=_errors(result.model, (), np.zeros(0), contexts, points),
        )
    )
    specs: tuple[EffectSpec, ...] = ()
    values = np.zeros(0)
    last_round: list[CandidateScore] = []
    tell(f"closed loop: {len(library)} candidate effects")
    while len(specs) < settings.max_effects:
        offered = [s for s in library if s not in specs]
        if not offered:
            last_round = []
            break
        residual, jac, sw, kin = _weighted_problem(
            result, result.model, specs, values, ctx_id, meas, prior
        )
        sel = slice(0, m)
        cols = [
            (
                s,
                (KINDS[s.kind].regressor(s, ctx_id, sel, kin) * sw[:, None, None]).reshape(
                    3 * m, -1
                ),
            )
            for s in offered
        ]
        scores = score_candidates(residual, jac, cols, m, settings, penalty)
        scores.sort(key=lambda c: (not c.significant, c.n_parameters == 0, -c.score))
        best = scores[0]
        if not best.significant:
            last_round = scores
            tell(
                f"closed loop: nothing significant left (best: {best.label}, "
                f"CV gain {best.cv_gain:.1f} σ², corrected p {best.p_adjusted:.2g})"
            )
            break
        specs = (*specs, best.spec)
        start_values = np.concatenate([values, np.zeros(len(best.spec.parameter_names()))])
        terms = effect_terms(specs, ctx_id, start=start_values)
        result = identify(nominal, q_id, meas, effects=terms, **id_kwargs)  # type: ignore[arg-type]
        values = result.effect_values
        previous = stages[-1]
        stage = Stage(
            "effect",
            f"+ {best.label}",
            result.model,
            specs=specs,
            effect_values=values,
            result=result,
            errors_mm=_errors(result.model, specs, values, contexts, points),
            added=best,
            round_scores=tuple(scores),
        )
        stages.append(replace(stage, evidence=_evidence(stage, previous, best.spec, contexts)))
        tell(
            f"closed loop: added {best.label} (CV gain {best.cv_gain:.1f} σ², "
            f"F {best.f_statistic:.1f}, corrected p {best.p_adjusted:.2g})"
        )
    return ClosedLoopResult(
        stages=tuple(stages),
        last_round=tuple(last_round),
        settings=settings,
        n_candidates=len(library),
        penalty_per_parameter=penalty,
        elapsed_s=time.perf_counter() - started,
        kinds=tuple(KINDS) if allowed is None else tuple(allowed),
    )


def _evidence(
    stage: Stage, previous: Stage, spec: EffectSpec, contexts: dict[str, EffectContext]
) -> EvidencePlot | None:
    """The added effect's evidence on the validation set (identification set without one)."""
    set_name = "validate" if "validate" in contexts else "identify"
    ctx = contexts[set_name]
    kin = Kinematics.of(stage.model, ctx.data.q_rad)
    values = stage.values_of(spec)
    ev: Evidence = KINDS[spec.kind].evidence(spec, values, ctx, slice(0, len(ctx.data)), kin)
    term = effect_offsets_mm((spec,), values, ctx, stage.model)
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


def regressors_for(
    specs: tuple[EffectSpec, ...], ctx: EffectContext, model: KinematicModel
) -> FloatArray:
    """Regressors ``(m, 3, k)`` of ``specs`` at ``ctx``'s poses (for tests and reports)."""
    return regressor_matrix(
        specs, ctx, slice(0, len(ctx.data)), Kinematics.of(model, ctx.data.q_rad)
    )
