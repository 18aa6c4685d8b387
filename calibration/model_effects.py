"""Effect terms applied after the geometric model when the twin predicts TCP points.

A calibrated description may carry ``[[effect]]`` tables (non-geometric terms identified by
the closed loop: joint compliance, backlash, thermal drift, ...). Each ``kind`` is applied by
a function registered in :data:`EFFECTS`; ``twin predict`` runs the geometric model, then
every effect of the description in file order. No kind is known yet: a description naming
one fails with a clear error rather than being predicted without it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.description import EffectDescription, RobotDescription
from calibration.errors import CalibrationError
from calibration.kinematics import KinematicModel, tcp_positions

FloatArray = NDArray[np.float64]


class ModelEffectError(CalibrationError, ValueError):
    """A description names an effect kind the twin cannot apply, or its parameters are bad."""


@dataclass(frozen=True)
class PredictionContext:
    """What an effect term may use: the description, its geometric model, the joint
    angles ``(N, n)`` rad and their times ``(N,)`` s (None when unknown)."""

    description: RobotDescription
    model: KinematicModel
    q_rad: FloatArray
    t_s: FloatArray | None


#: An effect term: (its description, context, TCP points (N, 3) mm) -> corrected points.
EffectTerm = Callable[[EffectDescription, PredictionContext, FloatArray], FloatArray]

#: Effect kind -> term. Empty until the closed loop registers its kinds.
EFFECTS: dict[str, EffectTerm] = {}


def register_effect(kind: str, term: EffectTerm) -> None:
    """Make ``kind`` applicable by :func:`predict_tcp` (later registrations replace)."""
    EFFECTS[kind] = term


def apply_effects(context: PredictionContext, points_mm: FloatArray) -> FloatArray:
    """Apply every effect of the description, in order, to geometric TCP points."""
    out = points_mm
    for i, effect in enumerate(context.description.effects):
        term = EFFECTS.get(effect.kind)
        if term is None:
            known = ", ".join(sorted(EFFECTS)) or "none yet"
            raise ModelEffectError(
                f"[[effect]] #{i + 1}: unknown effect kind {effect.kind!r} (known: {known})"
            )
        out = term(effect, context, out)
    return out


def predict_tcp(
    description: RobotDescription, q_rad: ArrayLike, t_s: ArrayLike | None = None
) -> FloatArray:
    """TCP points ``(N, 3)`` mm in the tracker frame with every modelled effect applied."""
    model = KinematicModel.from_description(description)
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    t = None if t_s is None else np.asarray(t_s, dtype=float)
    context = PredictionContext(description=description, model=model, q_rad=q, t_s=t)
    return apply_effects(context, tcp_positions(model, q))
