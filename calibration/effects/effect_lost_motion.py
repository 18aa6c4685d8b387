"""``lost_motion``: a joint standing off by a half-width in the direction of its last move;
see :mod:`calibration.effects.effect_base` for the library."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from calibration.effects.effect_base import (
    DEG,
    EffectContext,
    EffectKind,
    EffectSpec,
    Evidence,
    FloatArray,
    ModelAtPoses,
    check_keys,
    param_joint,
    param_number,
)
from calibration.errors import EffectLibraryError
from calibration.model.description import EffectValue


class LostMotion(EffectKind):
    kind = "lost_motion"
    needs_direction = True
    description = "direction-dependent lost motion after the grating ring"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("half_width_deg",)

    def _direction(self, spec: EffectSpec, ctx: EffectContext, sel: slice) -> FloatArray:
        if ctx.data.direction is None:
            raise EffectLibraryError("lost_motion needs the approach directions of the poses")
        return ctx.data.direction[sel, spec.joint - 1]

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        d = self._direction(spec, ctx, sel)
        return (kin.joint_axis(spec.joint) * DEG * d[:, None])[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        return f"lost motion of joint {spec.joint}"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {"joint": float(spec.joint), "half_width_deg": float(values[0])}

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        check_keys(params, {"joint", "half_width_deg"}, self.kind)
        spec = EffectSpec(self.kind, joint=param_joint(params, self.kind, n_joints))
        return spec, np.array([param_number(params, "half_width_deg", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        d = self._direction(spec, ctx, sel)
        return Evidence(
            x=d,
            x_label=f"joint {spec.joint} approach direction",
            y_label=f"joint {spec.joint} angle error (deg)",
            coordinate_mm=kin.joint_axis(spec.joint) * DEG,
        )
