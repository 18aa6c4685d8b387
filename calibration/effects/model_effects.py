"""A calibrated description's effects applied when the twin predicts TCP points.

A calibrated description may carry ``[[effect]]`` tables (non-geometric terms identified by
the closed loop, :mod:`calibration.effects.closed_loop`). Every ``kind`` is one of the effect
library's (:data:`calibration.effects.effect_kinds.KINDS`, the one registry), and the points come
from the one predictor the identification and the loop use
(:func:`calibration.effects.effect_kinds.predict_points`), so a calibrated model predicts exactly
what the loop fitted. An unknown kind or a bad parameter fails with an error naming the
``[[effect]]`` table, rather than being predicted without it; ``twin robot`` checks a
description with the same function (:func:`description_effects`).

Effects may use the joint readings, the times ``t_s`` (drift terms: on the campaign's
clock; a polynomial in time is held at the campaign's span, see :func:`times_outside_span`),
the temperature ``temp_c`` (°C: thermal expansion and the tracker's scale with the air;
without one those terms are 0, the prediction at their ``t_ref_c``, see
:func:`temperature_terms`) and the approach direction of each joint, taken from the pose
sequence in time order starting at Home (lost motion).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec
from calibration.effects.effect_kinds import KINDS, from_description, predict_points
from calibration.errors import EffectLibraryError, ModelEffectError
from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel

if TYPE_CHECKING:  # scipy loads only for a model that has a learned stage
    from calibration.effects.learned_residual import LearnedResidual

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
    description: RobotDescription,
    q_rad: ArrayLike,
    t_s: ArrayLike | None = None,
    *,
    temp_c: ArrayLike | None = None,
) -> FloatArray:
    """TCP points ``(N, 3)`` mm in the tracker frame with every modelled effect applied
    (at the times ``t_s`` ``(N,)`` s and temperatures ``temp_c`` ``(N,)`` °C where given),
    and the learned residual stage's correction where the description has one (within
    the data's reach: :func:`predict_tcp_sd`)."""
    points = traced_tcp(description, q_rad, t_s, temp_c=temp_c)
    learned = _learned(description)
    if learned is None:
        return points
    return points + learned.predict(np.atleast_2d(np.asarray(q_rad, dtype=float))).mean_mm


@dataclass(frozen=True)
class TcpPrediction:
    """Points ``(N, 3)`` mm; their predictive standard deviation ``sd_mm`` ``(N,)`` per axis
    (NaN: the description states none); ``beyond_reach`` ``(N,)``: the learned stage did
    not apply (outside its data's reach: the traced model and its standard deviation)."""

    points_mm: FloatArray
    sd_mm: FloatArray
    beyond_reach: NDArray[np.bool_]


def predict_tcp_sd(
    description: RobotDescription,
    q_rad: ArrayLike,
    t_s: ArrayLike | None = None,
    *,
    temp_c: ArrayLike | None = None,
) -> TcpPrediction:
    """:func:`predict_tcp` with each point's predictive standard deviation: the learned
    stage's where it applies, else the traced model's (``[residual] traced_sd_mm``)."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    points = traced_tcp(description, q, t_s, temp_c=temp_c)
    residual = description.residual
    learned = _learned(description)
    if learned is not None:
        pred = learned.predict(q)
        return TcpPrediction(points + pred.mean_mm, pred.sd_mm, ~pred.within_reach)
    sd = np.nan if residual is None else residual.traced_sd_mm
    return TcpPrediction(points, np.full(len(q), sd), np.zeros(len(q), dtype=bool))


def _learned(description: RobotDescription) -> LearnedResidual | None:
    residual = description.residual
    if residual is None or residual.learned is None:
        return None
    from calibration.effects.learned_residual import model_of

    return model_of(residual.learned, residual.traced_sd_mm)


def traced_tcp(
    description: RobotDescription,
    q_rad: ArrayLike,
    t_s: ArrayLike | None = None,
    *,
    temp_c: ArrayLike | None = None,
) -> FloatArray:
    """TCP points ``(N, 3)`` mm of the traced model: geometry and the named effects."""
    specs, values = description_effects(description)
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    t = None if t_s is None else np.asarray(t_s, dtype=float)
    temp = None if temp_c is None else np.asarray(temp_c, dtype=float).reshape(len(q))
    data = EffectData.from_sequence(q, t, np.radians(description.home), temp_c=temp)
    ctx = EffectContext(description, data)
    model = KinematicModel.from_description(description)
    try:
        return predict_points(model, specs, values, ctx)
    except EffectLibraryError as exc:
        raise ModelEffectError(f"[[effect]]: {exc}") from exc


def temperature_terms(description: RobotDescription) -> tuple[float, ...]:
    """The reference temperatures ``t_ref_c`` (°C) of the description's terms driven by a
    measured temperature, one per term (empty: the model has none, a temperature changes
    nothing); without a temperature such a term predicts at its ``t_ref_c``."""
    specs, _ = description_effects(description)
    return tuple(float(s.t_ref_c or 0.0) for s in specs if KINDS[s.kind].needs_temperature)


def missing_temperature_warning(description: RobotDescription, temp_c: object) -> str | None:
    """The warning a command prints when the model has temperature-driven terms and its
    input gave no temperature (``temp_c`` None): they predict at their ``t_ref_c``."""
    refs = temperature_terms(description)
    if temp_c is not None or not refs:
        return None
    at = ", ".join(f"{t:g}" for t in sorted(set(refs)))
    return (
        f"the model has {len(refs)} term(s) driven by a measured temperature and the input "
        f"has no temp_c column: predicted at their reference temperature ({at} °C)"
    )


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
