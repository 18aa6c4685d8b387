"""Effect terms applied after the geometric model when the twin predicts TCP points.

A calibrated description may carry ``[[effect]]`` tables (non-geometric terms identified by
the closed loop, :mod:`calibration.closed_loop`). Each ``kind`` is applied by a function
registered in :data:`EFFECTS`; ``twin predict`` runs the geometric model, then adds every
effect of the description in file order. Every kind of :mod:`calibration.effect_library`
is registered, with the same regressors the identification used (so a calibrated model
predicts exactly what the loop fitted). An unknown kind fails with a clear error rather
than being predicted without it.

Effects may use the joint readings, the times ``t_s`` (drift terms: on the campaign's
clock) and the approach direction of each joint, taken from the pose sequence in time order
starting at Home (lost motion).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.description import EffectDescription, RobotDescription
from calibration.effect_library import (
    KINDS,
    EffectContext,
    EffectData,
    EffectLibraryError,
    Kinematics,
    from_description,
)
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

    @cached_property
    def effect_context(self) -> EffectContext:
        """The poses as effect data: directions from the sequence in time order, from Home."""
        data = EffectData.from_sequence(self.q_rad, self.t_s, np.radians(self.description.home))
        return EffectContext(self.description, data)

    @cached_property
    def kinematics(self) -> Kinematics:
        return Kinematics.of(self.model, self.q_rad)


#: An effect term: (its description, context, TCP points (N, 3) mm) -> corrected points.
EffectTerm = Callable[[EffectDescription, PredictionContext, FloatArray], FloatArray]

#: Effect kind -> term (every kind of the effect library, see the bottom of this module).
EFFECTS: dict[str, EffectTerm] = {}


def register_effect(kind: str, term: EffectTerm) -> None:
    """Make ``kind`` applicable by :func:`predict_tcp` (later registrations replace)."""
    EFFECTS[kind] = term


def library_term(
    effect: EffectDescription, context: PredictionContext, points_mm: FloatArray
) -> FloatArray:
    """Add a library effect's ``R·c`` (its regressor at the geometric model) to the points."""
    try:
        spec, values = from_description(effect, context.model.n_joints)
        ctx = context.effect_context
        sel = slice(0, len(context.q_rad))
        offsets = KINDS[spec.kind].regressor(spec, ctx, sel, context.kinematics) @ values
    except EffectLibraryError as exc:
        raise ModelEffectError(f"[[effect]] kind {effect.kind!r}: {exc}") from exc
    return points_mm + offsets


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


for _kind in KINDS:
    register_effect(_kind, library_term)
