"""The harmonics of a joint angle: ``joint_harmonic`` (cyclic error of a joint's reading),
and the generic ``cartesian_harmonic`` and ``link_harmonic``; see
:mod:`calibration.effects.effect_base` for the library."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from calibration.effects.effect_base import (
    AXES,
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
    param_order,
    param_vector,
)
from calibration.model.description import EffectValue


class HarmonicOfJoint(EffectKind):
    """A harmonic of one joint's angle: cosine and sine amplitudes, ``components`` each,
    in ``unit`` (written as ``cos_<unit>``/``sin_<unit>``: a number for one component, an
    array for three)."""

    unit: str = "deg"
    components: int = 1

    def _basis(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice
    ) -> tuple[FloatArray, FloatArray]:
        q = ctx.data.q_rad[sel, spec.joint - 1]
        return np.cos(spec.order * q), np.sin(spec.order * q)

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        k = self.components
        cos, sin = values[:k], values[k : 2 * k]
        return {
            "joint": float(spec.joint),
            "order": float(spec.order),
            f"cos_{self.unit}": float(cos[0]) if k == 1 else tuple(float(v) for v in cos),
            f"sin_{self.unit}": float(sin[0]) if k == 1 else tuple(float(v) for v in sin),
        }

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        keys = (f"cos_{self.unit}", f"sin_{self.unit}")
        check_keys(params, {"joint", "order", *keys}, self.kind)
        spec = EffectSpec(
            self.kind,
            joint=param_joint(params, self.kind, n_joints),
            order=param_order(params, self.kind),
        )
        if self.components == 1:
            return spec, np.array([param_number(params, key, self.kind) for key in keys])
        return spec, np.concatenate(
            [param_vector(params, key, self.kind, self.components) for key in keys]
        )


class JointHarmonic(HarmonicOfJoint):
    kind = "joint_harmonic"
    unit = "deg"
    components = 1
    description = "cyclic error of one joint's reading (harmonic of its angle)"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("cos_deg", "sin_deg")

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        c, s = self._basis(spec, ctx, sel)
        axis = kin.joint_axis(spec.joint) * DEG
        return np.stack([axis * c[:, None], axis * s[:, None]], axis=2)

    def label(self, spec: EffectSpec) -> str:
        return f"cyclic error of joint {spec.joint} (harmonic {spec.order})"

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        return Evidence(
            x=np.degrees(ctx.data.q_rad[sel, spec.joint - 1]),
            x_label=f"joint {spec.joint} reading (deg)",
            y_label=f"joint {spec.joint} angle error (deg)",
            coordinate_mm=kin.joint_axis(spec.joint) * DEG,
        )


class CartesianHarmonic(HarmonicOfJoint):
    kind = "cartesian_harmonic"
    unit = "mm"
    components = 3
    generic = True
    description = "an error vector in the tracker frame varying with a harmonic of one joint"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return tuple(f"{a}_{f}_mm" for f in ("cos", "sin") for a in AXES)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        c, s = self._basis(spec, ctx, sel)
        out = np.zeros((len(c), 3, 6))
        for a in range(3):
            out[:, a, a] = c
            out[:, a, 3 + a] = s
        return out

    def label(self, spec: EffectSpec) -> str:
        return f"unexplained structure in q{spec.joint} (harmonic {spec.order})"

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        a = int(np.argmax(np.hypot(values[:3], values[3:])))
        g = np.zeros((len(kin.tcp_mm), 3))
        g[:, a] = 1.0
        return Evidence(
            x=np.degrees(ctx.data.q_rad[sel, spec.joint - 1]),
            x_label=f"joint {spec.joint} reading (deg)",
            y_label=f"{AXES[a].upper()} error (mm)",
            coordinate_mm=g,
        )


class LinkHarmonic(HarmonicOfJoint):
    kind = "link_harmonic"
    unit = "deg"
    components = 3
    generic = True
    description = (
        "link i turning about its own x, y and z axes with a harmonic of its joint angle "
        "(bearing wobble; about z alone it is a cyclic error of the reading)"
    )

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return tuple(f"{a}_{f}_deg" for f in ("cos", "sin") for a in AXES)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        c, s = self._basis(spec, ctx, sel)
        rot = kin.rotation_axes(spec.joint) * DEG
        return np.concatenate([rot * c[:, None, None], rot * s[:, None, None]], axis=2)

    def label(self, spec: EffectSpec) -> str:
        return (
            f"unexplained structure in q{spec.joint} "
            f"(harmonic {spec.order}, link {spec.joint} turning)"
        )

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        a = int(np.argmax(np.hypot(values[:3], values[3:])))
        return Evidence(
            x=np.degrees(ctx.data.q_rad[sel, spec.joint - 1]),
            x_label=f"joint {spec.joint} reading (deg)",
            y_label=f"link {spec.joint} rotation about its {AXES[a]} axis (deg)",
            coordinate_mm=kin.rotation_axes(spec.joint)[:, :, a] * DEG,
        )
