"""Effects that change with time: ``length_drift`` (a link length drifting linearly or as a
first-order lag: thermal growth) and the generic ``cartesian_time`` (an error vector
polynomial in time); see :mod:`calibration.effects.effect_base` for the library."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from calibration.effects.effect_base import (
    AXES,
    HOUR_S,
    EffectContext,
    EffectKind,
    EffectSpec,
    Evidence,
    FloatArray,
    ModelAtPoses,
    check_keys,
    check_t0,
    param_joint,
    param_number,
    param_span,
    param_vector,
    span_parameters,
)
from calibration.errors import EffectLibraryError
from calibration.model.description import EffectValue


class LengthDrift(EffectKind):
    """A link length changing with time (temperature): linear, ``rate·t`` (held at the
    campaign's span outside it), or a first-order lag ``A·(1 − e^(−t/τ))`` from the start
    of the campaign (``shape = (τ,)``: ``A`` is the final growth)."""

    kind = "length_drift"
    needs_time = True
    description = "a link length changing with time (temperature)"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        if spec.shape:
            return (f"{spec.parameter}_final_mm",)
        return (f"{spec.parameter}_rate_mm_per_h",)

    def time_function(self, spec: EffectSpec, ctx: EffectContext, sel: slice) -> FloatArray:
        """``(r,)``: hours (linear form) or ``1 − e^(−t/τ)`` (lag)."""
        if spec.shape:
            t = ctx.times_h(sel) * HOUR_S
            return -np.expm1(-np.maximum(t, 0.0) / spec.shape[0])
        return ctx.times_h(sel, span_s=spec.span_s)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        f = self.time_function(spec, ctx, sel)
        return (kin.length_axis(spec.joint, spec.parameter) * f[:, None])[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        base = f"thermal drift of joint {spec.joint} length {spec.parameter}"
        if spec.shape:
            return f"{base} (first-order lag, τ = {spec.shape[0] / 60.0:.1f} min)"
        return base

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        out: dict[str, EffectValue] = {"joint": float(spec.joint)}
        if spec.shape:
            out[f"{spec.parameter}_final_mm"] = float(values[0])
            out["time_constant_s"] = float(spec.shape[0])
        else:
            out[f"{spec.parameter}_rate_mm_per_h"] = float(values[0])
        out["t0_s"] = 0.0
        out.update(span_parameters(spec))
        return out

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        names = ("a_rate_mm_per_h", "d_rate_mm_per_h", "a_final_mm", "d_final_mm")
        keys = [k for k in names if k in params]
        if len(keys) != 1:
            raise EffectLibraryError(f"effect {self.kind!r}: exactly one of {', '.join(names)}")
        lag = keys[0].endswith("_final_mm")
        allowed = {"joint", keys[0], "t0_s", "t_min_s", "t_max_s"}
        check_keys(params, allowed | ({"time_constant_s"} if lag else set()), self.kind)
        check_t0(params, self.kind)
        shape: tuple[float, ...] = ()
        if lag:
            tau = param_number(params, "time_constant_s", self.kind)
            if not tau > 0:
                raise EffectLibraryError(f"effect {self.kind!r}: time_constant_s must be > 0")
            shape = (tau,)
        spec = EffectSpec(
            self.kind,
            joint=param_joint(params, self.kind, n_joints),
            parameter=keys[0][0],
            shape=shape,
            span_s=param_span(params, self.kind),
        )
        return spec, np.array([param_number(params, keys[0], self.kind)])

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
            y_label=f"joint {spec.joint} {spec.parameter} error (mm)",
            coordinate_mm=kin.length_axis(spec.joint, spec.parameter),
        )


class CartesianTime(EffectKind):
    kind = "cartesian_time"
    generic = True
    needs_time = True
    description = (
        "an error vector fixed in the tracker frame or in a link's frame, polynomial in time"
    )

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        names = [f"{a}_mm_per_h" for a in AXES]
        if spec.order >= 2:
            names += [f"{a}_mm_per_h2" for a in AXES]
        return tuple(names)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        t = ctx.times_h(sel, span_s=spec.span_s)
        axes = kin.frame_axes(spec.joint)
        out = np.zeros((len(t), 3, 3 * spec.order))
        for p in range(spec.order):
            out[:, :, 3 * p : 3 * p + 3] = axes * (t ** (p + 1))[:, None, None]
        return out

    def _frame(self, spec: EffectSpec) -> str:
        return "the tracker frame" if spec.joint == 0 else f"the frame of link {spec.joint}"

    def label(self, spec: EffectSpec) -> str:
        return f"unexplained structure in time (order {spec.order}, in {self._frame(spec)})"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        out: dict[str, EffectValue] = {
            "frame": float(spec.joint),
            "rate_mm_per_h": tuple(float(v) for v in values[:3]),
        }
        if spec.order >= 2:
            out["acceleration_mm_per_h2"] = tuple(float(v) for v in values[3:6])
        out["t0_s"] = 0.0
        out.update(span_parameters(spec))
        return out

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        allowed = {"frame", "rate_mm_per_h", "acceleration_mm_per_h2", "t0_s", "t_min_s", "t_max_s"}
        check_keys(params, allowed, self.kind)
        check_t0(params, self.kind)
        frame = param_number(params, "frame", self.kind) if "frame" in params else 0.0
        if frame != int(frame) or not 0 <= frame <= n_joints:
            raise EffectLibraryError(f"effect {self.kind!r}: frame must be 0..{n_joints}")
        v = param_vector(params, "rate_mm_per_h", self.kind, 3)
        order = 1
        if "acceleration_mm_per_h2" in params:
            v = np.concatenate([v, param_vector(params, "acceleration_mm_per_h2", self.kind, 3)])
            order = 2
        spec = EffectSpec(
            self.kind, joint=int(frame), order=order, span_s=param_span(params, self.kind)
        )
        return spec, v

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        t = ctx.times_h(sel)
        v = values.reshape(spec.order, 3)
        a = int(np.argmax(np.sqrt(np.sum(v**2, axis=0))))
        frame = "" if spec.joint == 0 else f" of link {spec.joint}'s frame"
        return Evidence(
            x=t,
            x_label="time since the start of the campaign (h)",
            y_label=f"{AXES[a]} error{frame} (mm)",
            coordinate_mm=kin.frame_axes(spec.joint)[:, :, a],
        )
