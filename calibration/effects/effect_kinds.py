"""The one registry of effect kinds (:data:`KINDS`: the ``kind`` of an ``[[effect]]`` table),
the effects' terms for the identification, their ``[[effect]]`` tables, and the one
predictor (:func:`predict_points`)."""

from __future__ import annotations

from collections.abc import Collection, Sequence

import numpy as np
from numpy.typing import ArrayLike

from calibration.effects.effect_base import KINDS as KINDS
from calibration.effects.effect_base import (
    EffectContext,
    EffectSpec,
    FloatArray,
    ModelAtPoses,
)
from calibration.effects.effect_bending import LinkBending
from calibration.effects.effect_coupling import JointCoupling
from calibration.effects.effect_gravity import GravityCompliance, GravityDeflection
from calibration.effects.effect_harmonics import CartesianHarmonic, JointHarmonic, LinkHarmonic
from calibration.effects.effect_lost_motion import LostMotion
from calibration.effects.effect_thermal import (
    InstrumentScaleTemperature,
    LengthTemperature,
    ThermalExpansion,
)
from calibration.effects.effect_time import CartesianTime, LengthDrift
from calibration.effects.effect_tracker import InstrumentScale, InstrumentScaleDrift
from calibration.errors import EffectLibraryError
from calibration.identify.identification import EffectTerms, predicted_points
from calibration.model.description import EffectDescription
from calibration.model.kinematics import KinematicModel

# The registry (defined in effect_base, where a spec looks its kind up), in this order.
KINDS.update(
    {
        k.kind: k
        for k in (
            GravityDeflection(),
            GravityCompliance(),
            LinkBending(),
            JointCoupling(),
            JointHarmonic(),
            LostMotion(),
            LengthDrift(),
            ThermalExpansion(),
            LengthTemperature(),
            InstrumentScale(),
            InstrumentScaleDrift(),
            InstrumentScaleTemperature(),
            CartesianHarmonic(),
            LinkHarmonic(),
            CartesianTime(),
        )
    }
)
LIBRARY_KINDS = tuple(k for k, v in KINDS.items() if not v.generic)
GENERIC_KINDS = tuple(k for k, v in KINDS.items() if v.generic)


def check_kinds(kinds: Collection[str]) -> None:
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise EffectLibraryError(f"unknown effect kind {unknown[0]!r} (valid: {', '.join(KINDS)})")


def regressor_matrix(
    specs: Sequence[EffectSpec], ctx: EffectContext, sel: slice, kin: ModelAtPoses
) -> FloatArray:
    """The regressors of several effects side by side ``(r, 3, Σk)``."""
    r = len(kin.tcp_mm)
    blocks = [KINDS[s.kind].regressor(s, ctx, sel, kin) for s in specs]
    return np.concatenate(blocks, axis=2) if blocks else np.zeros((r, 3, 0))


def effect_terms(
    specs: Sequence[EffectSpec], ctx: EffectContext, start: ArrayLike | None = None
) -> EffectTerms:
    """:class:`~calibration.identify.identification.EffectTerms` of ``specs`` on ``ctx``'s poses."""
    names = tuple(f"{s.kind}[{_tag(s)}].{p}" for s in specs for p in s.parameter_names())
    q = ctx.data.q_rad

    def regressor(model: KinematicModel, sel: slice) -> FloatArray:
        return regressor_matrix(specs, ctx, sel, ModelAtPoses.of(model, q[sel]))

    return EffectTerms(
        names=names,
        regressor=regressor,
        start=None if start is None else tuple(float(v) for v in np.asarray(start)),
    )


def _tag(spec: EffectSpec) -> str:
    if spec.kind in ("gravity_compliance", "thermal_expansion", "joint_coupling"):
        return "joints " + ",".join(str(j) for j in spec.joints)
    if spec.kind == "gravity_deflection":
        return spec.parameter or "linear"
    if spec.kind == "cartesian_time":
        return f"frame{spec.joint} order{spec.order}"
    parts = []
    if spec.joint:
        parts.append(f"joint{spec.joint}")
    if spec.parameter:
        parts.append(spec.parameter)
    if spec.order:
        parts.append(f"order{spec.order}")
    return " ".join(parts)


def split_values(specs: Sequence[EffectSpec], values: ArrayLike) -> list[FloatArray]:
    """The stacked effect parameter vector cut per effect."""
    v = np.asarray(values, dtype=float)
    sizes = [len(s.parameter_names()) for s in specs]
    if sum(sizes) != len(v):
        raise EffectLibraryError(f"{len(v)} values for effects with {sum(sizes)} parameters")
    return list(np.split(v, np.cumsum(sizes)[:-1])) if specs else []


def to_descriptions(
    specs: Sequence[EffectSpec], values: ArrayLike, n_joints: int
) -> tuple[EffectDescription, ...]:
    """``[[effect]]`` tables (units in the keys) of identified effects."""
    return tuple(
        EffectDescription(s.kind, KINDS[s.kind].to_parameters(s, v, n_joints))
        for s, v in zip(specs, split_values(specs, values), strict=True)
    )


def from_description(effect: EffectDescription, n_joints: int) -> tuple[EffectSpec, FloatArray]:
    """Spec and parameter values of an ``[[effect]]`` table (errors name the key)."""
    kind = KINDS.get(effect.kind)
    if kind is None:
        raise EffectLibraryError(
            f"unknown effect kind {effect.kind!r} (known: {', '.join(sorted(KINDS))})"
        )
    return kind.from_parameters(effect.parameters, n_joints)


def predict_points(
    model: KinematicModel,
    specs: Sequence[EffectSpec],
    values: ArrayLike,
    ctx: EffectContext,
) -> FloatArray:
    """Tracker points ``(m, 3)`` mm of a geometric model with effects at ``ctx``'s poses.

    The one way the twin predicts: the identification's own
    :func:`~calibration.identify.identification.predicted_points` with the effects' terms.
    """
    terms = effect_terms(specs, ctx) if specs else None
    return predicted_points(model, ctx.data.q_rad, terms, np.asarray(values, dtype=float))
