"""A calibrated description's effects applied when the twin predicts TCP points.

A calibrated description may carry ``[[effect]]`` tables (non-geometric terms identified by
the closed loop, :mod:`calibration.effects.closed_loop`). Every ``kind`` is one of the effect
library's (:data:`calibration.effects.effect_library.KINDS`, the one registry), and the points come
from the one predictor the identification and the loop use
(:func:`calibration.effects.effect_library.predict_points`), so a calibrated model predicts exactly
what the loop fitted. An unknown kind or a bad parameter fails with an error naming the
``[[effect]]`` table, rather than being predicted without it; ``twin robot`` checks a
description with the same function (:func:`description_effects`).

Effects may use the joint readings, the times ``t_s`` (drift terms: on the campaign's
clock; a polynomial in time is held at the campaign's span, see :func:`times_outside_span`)
and the approach direction of each joint, taken from the pose sequence in time order
starting at Home (lost motion).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.effect_library import (
    KINDS,
    EffectContext,
    EffectData,
    EffectSpec,
    from_description,
    predict_points,
)
from calibration.errors import EffectLibraryError, ModelEffectError
from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]


def description_effects(
    description: RobotDescription,
) -> tuple[tuple[EffectSpec, ...], FloatArray]:
    """The description's effects as specs and one stacked value vector; errors name the
    ``[[effect]]`` table (its position in the file) and the key."""
    specs: list[EffectSpec] = []
    values: list[FloatArray] = []
    for i, effect in enumerate(description.effects):
        if effect.kind not in KINDS:
            raise ModelEffectError(
                f"[[effect]] #{i + 1}: unknown effect kind {effect.kind!r} "
                f"(known: {', '.join(sorted(KINDS))})"
            )
        try:
            spec, v = from_description(effect, description.n_joints)
        except EffectLibraryError as exc:
            raise ModelEffectError(f"[[effect]] #{i + 1} kind {effect.kind!r}: {exc}") from exc
        specs.append(spec)
        values.append(np.asarray(v, dtype=float))
    return tuple(specs), (np.concatenate(values) if values else np.zeros(0))


def load_checked_robot(name_or_path: str | Path) -> RobotDescription:
    """:func:`~calibration.model.description.load_robot`, with its ``[[effect]]`` tables checked
    as :func:`predict_tcp` reads them (so every command refuses the same files); errors
    name the file."""
    desc = load_robot(name_or_path)
    try:
        description_effects(desc)
    except ModelEffectError as exc:
        raise ModelEffectError(f"{name_or_path}: {exc}") from None
    return desc


def predict_tcp(
    description: RobotDescription, q_rad: ArrayLike, t_s: ArrayLike | None = None
) -> FloatArray:
    """TCP points ``(N, 3)`` mm in the tracker frame with every modelled effect applied."""
    specs, values = description_effects(description)
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    t = None if t_s is None else np.asarray(t_s, dtype=float)
    data = EffectData.from_sequence(q, t, np.radians(description.home))
    ctx = EffectContext(description, data)
    model = KinematicModel.from_description(description)
    try:
        return predict_points(model, specs, values, ctx)
    except EffectLibraryError as exc:
        raise ModelEffectError(f"[[effect]]: {exc}") from exc


def times_outside_span(
    description: RobotDescription, t_s: ArrayLike | None
) -> tuple[int, tuple[float, float] | None]:
    """How many times ``t_s`` fall outside the span of the description's polynomial time
    terms (where those terms are held at the span's ends), and that span."""
    specs, _ = description_effects(description)
    spans = [s.span_s for s in specs if len(s.span_s) == 2]
    if t_s is None or not spans:
        return 0, None
    lo, hi = min(s[0] for s in spans), max(s[1] for s in spans)
    t = np.asarray(t_s, dtype=float)
    return int(np.count_nonzero((t < lo) | (t > hi))), (lo, hi)
