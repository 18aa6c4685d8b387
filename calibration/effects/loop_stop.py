"""Why the closed loop's search stopped (:class:`StopReason`) and the best candidate left;
a round's scores (:class:`ScoredRound`) and the candidates set aside (:class:`Rejected`)."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.effects.candidate_scoring import CandidateScore, LinearizedModel, choose
from calibration.effects.effect_base import EffectSpec
from calibration.effects.effect_shapes import PhysicalGravityFit, TimeConstantProfile

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class ScoredRound:
    """One round of the search: the model linearized at its solution, and every offered
    candidate's weighted columns ``(3m, k)`` and score (significant first, then best CV
    score first); a drift's time-constant profile; the gravity term's physical form fitted
    from the linear form's columns (its spec → the fit of its compliance ratios)."""

    lin: LinearizedModel
    scores: list[CandidateScore]
    columns: dict[EffectSpec, FloatArray]
    profiles: dict[EffectSpec, TimeConstantProfile]
    gravity_fits: dict[EffectSpec, PhysicalGravityFit] = field(default_factory=dict)


@dataclass(frozen=True)
class Rejected:
    """A candidate set aside: chosen, but the step made the validation error worse (or its
    re-identification failed)."""

    label: str
    reason: str

    def as_dict(self) -> dict[str, str]:
        return {"effect": self.label, "reason": self.reason}


#: Why the search stopped (:attr:`StopReason.code`).
STOP_CODES = ("max_effects", "set_aside", "none_significant", "no_candidate_left")


@dataclass(frozen=True)
class StopReason:
    """Why the search stopped, in words and as a ``code`` of :data:`STOP_CODES`, and the
    best candidate left (the last round's best by significance, then penalized CV score,
    that is neither in the model nor set aside; None: no identifiable candidate left)."""

    code: str
    text: str
    best_remaining: CandidateScore | None = None

    def as_dict(self) -> dict[str, Any]:
        best = self.best_remaining
        return {
            "code": self.code,
            "reason": self.text,
            "best_remaining": None if best is None else best.as_dict(),
        }


def stop_reason(
    code: str,
    max_effects: int,
    max_rejected: int,
    scored: ScoredRound | None,
    rejected: list[Rejected],
    set_aside: Collection[EffectSpec],
) -> StopReason:
    """The stop in words, and the best candidate left in the round that ended the search
    (``scored``): the one the loop would add next when any is significant (the physical
    priority applied, :func:`~calibration.effects.candidate_scoring.choose`), else the best
    score."""
    undone = len(rejected)
    if code == "max_effects":
        text = f"the maximum number of effects ({max_effects}) is reached"
    elif code == "set_aside":
        text = (
            f"{undone} significant candidate(s) were undone by the validation re-check "
            f"(at most {max_rejected} are tried)"
        )
    elif code == "none_significant":
        text = "no remaining candidate is significant"
    else:
        text = "no candidate is left to try"
    if undone and code != "set_aside":
        text += f" ({undone} set aside by the validation re-check)"
    scores = [] if scored is None else scored.scores
    left = [c for c in scores if c.n_parameters > 0 and c.spec not in set_aside]
    if not left:
        return StopReason(code, text)
    if scored is not None and left[0].significant:
        return StopReason(code, text, choose(scored.lin, left, scored.columns)[0])
    return StopReason(code, text, left[0])
