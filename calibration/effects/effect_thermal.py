"""Effects driven by a measured temperature (campaign.csv's optional ``temp_c``, °C): the
arm's links expanding (``thermal_expansion``: every link length of a group of joints
growing in proportion to its length, ``length_temperature``: one length on its own) and
the tracker's scale following the air (``instrument_scale_temperature``); see
:mod:`calibration.effects.effect_base` for the library.

Each is linear in ``T − T_ref``. ``T_ref`` (``t_ref_c``, °C) is the median temperature
of the identification poses: the geometry of a model with such a term is the one at
``T_ref``. Without a temperature (a ``twin predict`` input with no ``temp_c``) the terms
are 0: the twin predicts at ``T_ref``.

These are offered in place of nothing: the ``t_s``-driven drifts stay candidates beside
them; the physical priority puts a term driven by a measured temperature before one
driven by the clock (:data:`calibration.effects.candidate_scoring.PRIORITY`).
"""

from __future__ import annotations

import math
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
    param_joint,
    param_number,
)
from calibration.errors import EffectLibraryError
from calibration.model.description import EffectValue

#: A temperature column varying less than this (K, max − min over the identification
#: poses) offers no temperature-driven candidate: over 0.2 K a 3 m steel arm (11.5 ppm/K)
#: changes by 7 µm, a fraction of a tracker's noise, and a class-A Pt100 is only good to
#: ±0.15 K; such a column could only fit noise.
MIN_TEMPERATURE_RANGE_K = 0.2
PPM = 1e-6


def reference_temperature_c(temp_c: FloatArray) -> float:
    """``T_ref`` of temperature-driven terms: the median of ``temp_c`` ``(m,)`` °C,
    rounded to 0.01 °C (a value to read in calibrated.toml)."""
    return round(float(np.median(temp_c)), 2)


def _t_ref(params: Mapping[str, Any], kind: str) -> float:
    t = param_number(params, "t_ref_c", kind)
    if not -100.0 <= t <= 200.0:
        raise EffectLibraryError(f"effect {kind!r}: t_ref_c must be a temperature in °C")
    return t


def _rise(spec: EffectSpec, ctx: EffectContext, sel: slice) -> FloatArray:
    if spec.t_ref_c is None:
        raise EffectLibraryError(f"effect {spec.kind!r}: no reference temperature (t_ref_c)")
    return ctx.temperature_rise_k(sel, spec.t_ref_c)


def _temperature_x(ctx: EffectContext, sel: slice, r: int) -> FloatArray:
    t = ctx.data.temp_c
    return np.full(r, math.nan) if t is None else t[sel]


class ThermalExpansion(EffectKind):
    """Every link length (``a`` and ``d``) of the joints ``spec.joints`` growing by
    ``κ·L·(T − T_ref)``, κ (ppm/K) the links' expansion coefficient (steel 11.5,
    aluminium 23): the arm warming up, with the measured temperature. One parameter for
    the group; the lengths are the current model's."""

    kind = "thermal_expansion"
    needs_temperature = True
    description = (
        "the links expanding with the measured temperature (every length of a link group "
        "∝ its length · (T − T_ref))"
    )

    def slot(self, spec: EffectSpec) -> tuple[str | int, ...]:
        return (spec.kind, *spec.joints)

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("expansion_ppm_per_k",)

    @staticmethod
    def unit_growth(spec: EffectSpec, kin: ModelAtPoses) -> FloatArray:
        """∂TCP per ppm of growth of every length of the group, ``(r, 3)`` mm."""
        out = np.zeros_like(kin.tcp_mm)
        for j in spec.joints:
            a, d = kin.model.a_mm[j - 1], kin.model.d_mm[j - 1]
            out += a * kin.length_axis(j, "a") + d * kin.length_axis(j, "d")
        return out * PPM

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        return (self.unit_growth(spec, kin) * _rise(spec, ctx, sel)[:, None])[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        j = spec.joints
        return f"thermal expansion of links {j[0]}–{j[-1]} with the measured temperature"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {
            "joints": tuple(float(j) for j in spec.joints),
            "expansion_ppm_per_k": float(values[0]),
            "t_ref_c": float(spec.t_ref_c or 0.0),
        }

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        check_keys(params, {"joints", "expansion_ppm_per_k", "t_ref_c"}, self.kind)
        joints_f = params.get("joints")
        if not isinstance(joints_f, tuple | list) or not joints_f:
            raise EffectLibraryError(f"effect {self.kind!r}: 'joints' must be joint numbers")
        joints = []
        for j in joints_f:
            if isinstance(j, str | bool) or j != int(j) or not 1 <= j <= n_joints:
                raise EffectLibraryError(
                    f"effect {self.kind!r}: 'joints' must be 1..{n_joints}, got {j!r}"
                )
            joints.append(int(j))
        spec = EffectSpec(self.kind, joints=tuple(joints), t_ref_c=_t_ref(params, self.kind))
        return spec, np.array([param_number(params, "expansion_ppm_per_k", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        return Evidence(
            x=_temperature_x(ctx, sel, len(kin.tcp_mm)),
            x_label="measured temperature (°C)",
            y_label=f"links {spec.joints[0]}–{spec.joints[-1]} growth (ppm)",
            coordinate_mm=self.unit_growth(spec, kin),
        )


class LengthTemperature(EffectKind):
    """One link length (``a`` or ``d`` of joint j) growing by ``c·(T − T_ref)`` (mm/K):
    a link warmed more than the others (its motor, the sun through a window)."""

    kind = "length_temperature"
    needs_temperature = True
    description = "a link length changing with the measured temperature"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return (f"{spec.parameter}_mm_per_k",)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        axis = kin.length_axis(spec.joint, spec.parameter)
        return (axis * _rise(spec, ctx, sel)[:, None])[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        return f"thermal growth of joint {spec.joint} length {spec.parameter} with the temperature"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {
            "joint": float(spec.joint),
            f"{spec.parameter}_mm_per_k": float(values[0]),
            "t_ref_c": float(spec.t_ref_c or 0.0),
        }

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        keys = [k for k in ("a_mm_per_k", "d_mm_per_k") if k in params]
        if len(keys) != 1:
            raise EffectLibraryError(f"effect {self.kind!r}: exactly one of a_mm_per_k, d_mm_per_k")
        check_keys(params, {"joint", keys[0], "t_ref_c"}, self.kind)
        spec = EffectSpec(
            self.kind,
            joint=param_joint(params, self.kind, n_joints),
            parameter=keys[0][0],
            t_ref_c=_t_ref(params, self.kind),
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
        return Evidence(
            x=_temperature_x(ctx, sel, len(kin.tcp_mm)),
            x_label="measured temperature (°C)",
            y_label=f"joint {spec.joint} {spec.parameter} error (mm)",
            coordinate_mm=kin.length_axis(spec.joint, spec.parameter),
        )


class InstrumentScaleTemperature(EffectKind):
    """The tracker's distance scale following the temperature, ``s·(T − T_ref)`` ppm/K
    about the tracker: the air's refractive index (about −1 ppm/K) where the tracker's
    weather station reads the air elsewhere than along the beam."""

    kind = "instrument_scale_temperature"
    needs_temperature = True
    description = "the tracker's scale following the measured (air) temperature"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("scale_ppm_per_k",)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        return (kin.tcp_mm * PPM * _rise(spec, ctx, sel)[:, None])[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        return "tracker scale with the measured temperature"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {"scale_ppm_per_k": float(values[0]), "t_ref_c": float(spec.t_ref_c or 0.0)}

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        check_keys(params, {"scale_ppm_per_k", "t_ref_c"}, self.kind)
        spec = EffectSpec(self.kind, t_ref_c=_t_ref(params, self.kind))
        return spec, np.array([param_number(params, "scale_ppm_per_k", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        return Evidence(
            x=_temperature_x(ctx, sel, len(kin.tcp_mm)),
            x_label="measured temperature (°C)",
            y_label="tracker scale error (ppm)",
            coordinate_mm=kin.tcp_mm * PPM,
        )
