"""The tracker's effects: ``instrument_scale`` (a distance-proportional scale error) and
``instrument_scale_drift`` (that scale drifting with time); see
:mod:`calibration.effects.effect_base` for the library."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from calibration.effects.effect_base import (
    EffectContext,
    EffectKind,
    EffectSpec,
    Evidence,
    FloatArray,
    ModelAtPoses,
    check_keys,
    check_t0,
    param_number,
    param_span,
    span_parameters,
)
from calibration.model.description import EffectValue


class InstrumentScale(EffectKind):
    kind = "instrument_scale"
    description = "distance-proportional scale error of the tracker"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("scale_ppm",)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        return (kin.tcp_mm * 1e-6)[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        return "tracker scale"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {"scale_ppm": float(values[0])}

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        check_keys(params, {"scale_ppm"}, self.kind)
        return EffectSpec(self.kind), np.array([param_number(params, "scale_ppm", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        return Evidence(
            x=np.linalg.norm(kin.tcp_mm, axis=1) / 1000.0,
            x_label="distance from the tracker (m)",
            y_label="scale error (ppm)",
            coordinate_mm=kin.tcp_mm * 1e-6,
        )


class InstrumentScaleDrift(EffectKind):
    kind = "instrument_scale_drift"
    needs_time = True
    description = "the tracker's scale drifting with time (air temperature)"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("rate_ppm_per_h",)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        t = ctx.times_h(sel, span_s=spec.span_s)
        return (kin.tcp_mm * 1e-6 * t[:, None])[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        return "tracker scale drift"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {"rate_ppm_per_h": float(values[0]), "t0_s": 0.0, **span_parameters(spec)}

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        check_keys(params, {"rate_ppm_per_h", "t0_s", "t_min_s", "t_max_s"}, self.kind)
        check_t0(params, self.kind)
        spec = EffectSpec(self.kind, span_s=param_span(params, self.kind))
        return spec, np.array([param_number(params, "rate_ppm_per_h", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        t = ctx.times_h(sel)
        return Evidence(
            x=t,
            x_label="time since the start of the campaign (h)",
            y_label="scale error (ppm)",
            coordinate_mm=kin.tcp_mm * 1e-6,
        )
