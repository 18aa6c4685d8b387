"""The effect library's base: the pose data and context an effect is computed on
(:class:`EffectData`, :class:`EffectContext`, :class:`ModelAtPoses`), a candidate
(:class:`EffectSpec`), the interface of a kind (:class:`EffectKind`) and the checks of an
``[[effect]]`` table's parameters.

Candidate effects the geometric model lacks: small parametric models with a physical meaning.

Each effect *kind* is linear in a few parameters and adds ``R·c`` to the geometric TCP, with
an analytic regressor ``R`` ``(m, 3, k)`` (mm per unit of each parameter) computed from the
pose data (:class:`EffectData`: joint readings, times, approach directions), the robot
description (gravity direction, Home) and the current geometric model. Some kinds also
have nonlinear *shape* parameters (``EffectSpec.shape``), held fixed while the linear ones
are fitted and profiled by the closed loop. :data:`calibration.effects.effect_kinds.KINDS`
is the one registry: the loop offers these kinds
(:mod:`calibration.effects.effect_candidates`), ``[[effect]]`` tables name them, and the one
predictor (:func:`calibration.identify.identification.predicted_points`, through
:func:`calibration.effects.effect_kinds.effect_terms`) applies them. The library (method.md §4, §6):

* ``gravity_deflection``: joints turn after their grating ring under gravity; no mass
  model needed: compliance × a torque linear in the links' first mass moments, in a
  linear form (one deflection per joint and base moment) or the physical form (compliance
  ratios and shared compliance-weighted moments), see :class:`GravityDeflection`.
* ``gravity_compliance``: the same with the torque from the description's mass model
  (``compliance_urad_per_knm`` per loaded joint); offered only when asked for by name.
* ``joint_harmonic``: cyclic error of joint j's reading, ``a·cos(k·q_j) + b·sin(k·q_j)``
  (``cos_deg``, ``sin_deg``).
* ``lost_motion``: joint j stands ``w·d_j`` off, d_j the direction of its last move
  (``half_width_deg``).
* ``length_drift``: a link length (``a`` or ``d`` of joint j) changing with time,
  linearly (``a_rate_mm_per_h``) or as a first-order lag (``a_final_mm``,
  ``time_constant_s``).
* ``link_bending``: link j turning about its own x and y axes under the bending moment of
  everything outboard (``bending_ratio``, the gravity term's weighted moments frozen);
  offered once a physical gravity term is in.
* ``joint_coupling``: joints 2 and 3 sharing compliance, each turning under the other's
  gravity torque (``coupling_ratio``, the gravity term's weighted moments frozen); offered
  once a gravity term is in (:mod:`calibration.effects.effect_coupling`).
* ``thermal_expansion``, ``length_temperature``, ``instrument_scale_temperature``: link
  lengths and the tracker's scale following a measured temperature (``temp_c``), linear in
  ``T − T_ref`` (:mod:`calibration.effects.effect_thermal`).
* ``instrument_scale``: distance-proportional scale error of the tracker (``scale_ppm``).
* ``instrument_scale_drift``: that scale drifting with time (``rate_ppm_per_h``).

and the generic search, for structure outside the library ("unexplained structure in X"):

* ``cartesian_harmonic``: an error vector in the tracker frame varying as
  ``cos/sin(k·q_j)`` (``cos_mm``, ``sin_mm``: 3 each).
* ``link_harmonic``: link j turning about its own x, y and z axes as ``cos/sin(k·q_j)``
  (``cos_deg``, ``sin_deg``: 3 each): bearing wobble; about z alone it is
  ``joint_harmonic``, so it names a cyclic error too when that kind is not offered.
* ``cartesian_time``: an error vector fixed in the tracker frame or in a link's frame
  (``frame``: 0 tracker, j link j), polynomial in time (``rate_mm_per_h``, and
  ``acceleration_mm_per_h2`` for order 2).

Joint-angle effects are first-order, ``R = ∂TCP/∂θ_j · Δθ_j`` (the second-order term,
``Δθ²·reach``, is below 1e-4 mm for Δθ < 2e-4 rad ≈ 0.01°); lengths, scale and Cartesian
terms are exact. Time terms use the campaign clock ``t_s`` with ``t0_s = 0``: the
geometry of a model with drift terms is the one at the start of the campaign. A polynomial
in time carries the campaign's span (``t_min_s``, ``t_max_s``) and is held at its value at
the nearer end outside it: it is never extrapolated.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import EffectLibraryError
from calibration.model.description import EffectValue, RobotDescription
from calibration.model.gravity_regressor import (
    BaseMoments,
    base_moments,
    gravity_of,
)
from calibration.model.kinematics import KinematicModel, flange_poses, identification_jacobian
from calibration.model.statics import MassModel, gravity_torques_nmm

FloatArray = NDArray[np.float64]

DEG = math.pi / 180.0
#: 1 µrad/(kN·m) in rad/(N·mm)
URAD_PER_KNM = 1e-12
HOUR_S = 3600.0
#: A loaded joint carries at least this fraction of the largest RMS gravity torque.
LOADED_JOINT_FRACTION = 1e-3
#: Nominal lengths (mm) from which a link length is a thermal-drift candidate.
DRIFT_MIN_LENGTH_MM = 50.0
#: Joint moves smaller than this (rad) keep the previous approach direction: 10× the
#: gratings' read noise, far below any move between measurement poses.
MIN_MOVE_RAD = 1e-5
#: Harmonic orders per revolution are scanned from 1 up to this (library and generic
#: search): rings and their mounting screws, gear stages and encoders make errors at orders
#: nobody declares. The scan pays for its orders (:func:`harmonic_orders`).
MAX_HARMONIC_ORDER = 24
#: Orders 1..3 (eccentricity, ovality, triangularity) are always scanned.
MIN_HARMONIC_ORDER = 3
#: A scanned order's period spans at least this many poses on average over the joint's
#: coverage: finer structure is not resolved by the poses.
POSES_PER_PERIOD = 4.0


# -- data ---------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class EffectData:
    """Per-pose inputs of the regressors: readings ``(m, n)`` rad, times ``(m,)`` s (None:
    unknown) and approach directions ``(m, n)`` in {-1, 0, 1} (None: unknown)."""

    q_rad: FloatArray
    t_s: FloatArray | None = None
    direction: FloatArray | None = None
    #: Readings through scale maps fitted on sweeps with the other joints at this vector
    #: ``(n,)`` rad, or per joint ``(n, n)`` rad (row j: joint j+1's sweep configuration,
    #: its own entry unused); None: maps that read the rings alone. Such a map has absorbed
    #: the swept link's deflection in its sweep configuration, so the gravity term models
    #: the deflection relative to it (:class:`GravityDeflection`).
    sweep_reference: FloatArray | None = None
    #: The temperature ``(m,)`` °C read at each pose (campaign.csv's optional ``temp_c``;
    #: None: not measured). Temperature-driven terms are 0 without it: the twin predicts at
    #: their reference temperature.
    temp_c: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.q_rad)

    @classmethod
    def from_sequence(
        cls,
        q_rad: ArrayLike,
        t_s: ArrayLike | None = None,
        start_rad: ArrayLike | None = None,
        min_move_rad: float = MIN_MOVE_RAD,
        temp_c: ArrayLike | None = None,
    ) -> EffectData:
        """Data of a pose sequence: each joint's approach direction is the sign of its move
        from the previous pose in time order (the first from ``start_rad``, e.g. Home).
        A move smaller than ``min_move_rad`` (a joint standing still, read with noise) keeps
        the direction it had; before any move it is 0. ``temp_c`` ``(m,)`` °C: the
        temperature at each pose, if measured."""
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))
        t = None if t_s is None else np.asarray(t_s, dtype=float)
        order = np.arange(len(q)) if t is None else np.argsort(t, kind="stable")
        start = np.zeros(q.shape[1]) if start_rad is None else np.asarray(start_rad, float)
        seq = q[order]
        moves = np.diff(np.vstack([start, seq]), axis=0)
        sign = np.where(np.abs(moves) >= min_move_rad, np.sign(moves), 0.0)
        rows = np.arange(len(seq))[:, None]
        last = np.maximum.accumulate(np.where(sign != 0.0, rows, 0), axis=0)  # last real move
        held = np.take_along_axis(sign, last, axis=0)
        direction = np.empty_like(q)
        direction[order] = held
        temp = None if temp_c is None else np.asarray(temp_c, dtype=float)
        return cls(q, t, direction, temp_c=temp)

    def subset(self, mask: ArrayLike) -> EffectData:
        m = np.asarray(mask)
        return EffectData(
            self.q_rad[m],
            None if self.t_s is None else self.t_s[m],
            None if self.direction is None else self.direction[m],
            self.sweep_reference,
            None if self.temp_c is None else self.temp_c[m],
        )


@dataclass(frozen=True, eq=False)
class EffectContext:
    """What the regressors need: the description (mass model, Home) and the pose data."""

    description: RobotDescription
    data: EffectData

    @cached_property
    def masses(self) -> MassModel:
        return MassModel.from_description(self.description)

    @cached_property
    def torques_nmm(self) -> FloatArray:
        """Gravity torques ``(m, n)`` N·mm at the readings with the description's geometry
        (for choosing candidates; the regressor uses the current model's geometry)."""
        return gravity_torques_nmm(
            KinematicModel.from_description(self.description), self.masses, self.data.q_rad
        )

    @cached_property
    def gravity(self) -> FloatArray:
        """Unit gravity direction in the robot base frame (the description's, else −z)."""
        return gravity_of(self.description)

    @cached_property
    def base_moments(self) -> BaseMoments:
        """The arm's base first moments (chosen on the description's nominal geometry)."""
        return base_moments(self.description)

    def times_h(self, sel: slice, t0_s: float = 0.0, span_s: Sequence[float] = ()) -> FloatArray:
        """Times of the poses ``sel`` in hours from ``t0_s``; with ``span_s`` held inside
        the span (a polynomial in time is never extrapolated past the campaign)."""
        if self.data.t_s is None:
            raise EffectLibraryError("this effect needs the poses' times (t_s)")
        t = self.data.t_s[sel]
        if len(span_s) == 2:
            t = np.clip(t, span_s[0], span_s[1])
        return (t - t0_s) / HOUR_S

    def temperature_rise_k(self, sel: slice, t_ref_c: float) -> FloatArray:
        """``T − T_ref`` ``(r,)`` K at the poses ``sel``: 0 where no temperature was
        measured (a temperature-driven term then predicts at its reference temperature)."""
        q = self.data.q_rad[sel]
        if self.data.temp_c is None:
            return np.zeros(len(q))
        return self.data.temp_c[sel] - t_ref_c


@dataclass(frozen=True, eq=False)
class ModelAtPoses:
    """The current geometric model at some poses ``(r, n)``: TCP ``(r, 3)`` and
    identification Jacobian ``(r, 3, 5n + 9)`` (world frame)."""

    model: KinematicModel
    q_rad: FloatArray
    tcp_mm: FloatArray
    jacobian: FloatArray
    _rotation_axes: dict[int, FloatArray] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, model: KinematicModel, q_rad: FloatArray) -> ModelAtPoses:
        q = np.atleast_2d(q_rad)
        tcp, jac = identification_jacobian(model, q)
        return cls(model, q, tcp, jac)

    def torques_nmm(self, masses: MassModel) -> FloatArray:
        """Gravity torques ``(r, n)`` N·mm at these poses with this model's geometry (the
        payload at this model's tool point)."""
        at_tool = replace(masses, tool_mm=np.asarray(self.model.tool_mm, dtype=float))
        return gravity_torques_nmm(self.model, at_tool, self.q_rad)

    def joint_axis(self, joint: int) -> FloatArray:
        """∂TCP/∂θ_j ``(r, 3)`` mm/rad (1-based joint)."""
        return self.jacobian[:, :, 5 * (joint - 1) + 3]

    def length_axis(self, joint: int, parameter: str) -> FloatArray:
        """∂TCP/∂a_j or ∂TCP/∂d_j ``(r, 3)`` mm/mm."""
        return self.jacobian[:, :, 5 * (joint - 1) + {"a": 0, "d": 2}[parameter]]

    def frame_axes(self, frame: int) -> FloatArray:
        """Axes of link frame ``frame`` in the world ``(r, 3, 3)`` (columns x, y, z); frame 0
        is the tracker frame. Read off the Jacobian: x_j = ∂TCP/∂a_(j+1), z_j = ∂TCP/∂d_j,
        the flange's from the tool columns."""
        r = len(self.tcp_mm)
        if frame == 0:
            return np.broadcast_to(np.eye(3), (r, 3, 3)).copy()
        n = (self.jacobian.shape[2] - 9) // 5
        if frame == n:
            return self.jacobian[:, :, 5 * n + 6 :].copy()
        x = self.jacobian[:, :, 5 * frame]
        z = self.jacobian[:, :, 5 * (frame - 1) + 2]
        return np.stack([x, np.cross(z, x), z], axis=2)

    def frame_origin(self, frame: int) -> FloatArray:
        """Origin of link frame ``frame`` (1..n) in the world ``(r, 3)`` mm."""
        sub = self.model.truncated(frame)
        return flange_poses(sub, self.q_rad[:, :frame])[:, :3, 3]

    def rotation_axes(self, frame: int) -> FloatArray:
        """∂TCP per rad of a small rotation of link ``frame`` about its own x, y, z axes
        ``(r, 3, 3)`` (columns): ``axis × (TCP − origin)``; the z column is ∂TCP/∂θ.
        Kept per frame: a harmonic scan asks for the same frame at every order."""
        if frame not in self._rotation_axes:
            axes = self.frame_axes(frame)
            lever = self.tcp_mm - self.frame_origin(frame)
            self._rotation_axes[frame] = np.cross(axes, lever[:, :, None], axis=1)
        return self._rotation_axes[frame]


#: The former name of :class:`ModelAtPoses`.
Kinematics = ModelAtPoses


# -- specs and kinds --------------------------------------------------------------------------
@dataclass(frozen=True)
class EffectSpec:
    """One candidate: a kind and what it is attached to (1-based joint, harmonic order,
    length ``a``/``d``, the loaded joints of a compliance). Hashable.

    ``names`` are named parts of a term (the gravity term's joint-moment pairs or base
    moments); ``shape`` holds nonlinear shape parameters, fixed while the term's linear
    parameters are fitted and profiled by the closed loop (a lag's time constant in s, the
    physical gravity form's compliance ratios); ``span_s`` is the campaign's time span
    ``(t_min, t_max)``: a polynomial in time is held at its ends outside it; ``t_ref_c``
    the reference temperature of a temperature-driven term.
    """

    kind: str
    joint: int = 0
    order: int = 0
    parameter: str = ""
    joints: tuple[int, ...] = ()
    names: tuple[str, ...] = ()
    shape: tuple[float, ...] = ()
    span_s: tuple[float, ...] = ()
    #: The reference temperature (°C) of a temperature-driven term: the geometry is the
    #: one at this temperature (None for every other kind).
    t_ref_c: float | None = None

    @property
    def label(self) -> str:
        return KINDS[self.kind].label(self)

    @property
    def generic(self) -> bool:
        return KINDS[self.kind].generic

    def parameter_names(self) -> tuple[str, ...]:
        return KINDS[self.kind].parameter_names(self)


@dataclass(frozen=True, eq=False)
class Evidence:
    """The residual in an effect's own coordinate: per pose, the driving variable ``x``
    (``(r,)``) and the TCP displacement per unit coordinate ``coordinate_mm`` ``(r, 3)``
    (e.g. ∂TCP/∂θ_j per degree: residuals then read as joint-angle errors)."""

    x: FloatArray
    x_label: str
    y_label: str
    coordinate_mm: FloatArray

    def project(self, residual_mm: ArrayLike) -> FloatArray:
        """Least-squares coordinate ``(r,)`` of residuals ``(r, 3)`` (NaN where undefined)."""
        g = self.coordinate_mm
        gg = np.sum(g * g, axis=1)
        num = np.sum(g * np.asarray(residual_mm, dtype=float), axis=1)
        out = np.full(len(g), np.nan)
        ok = gg > 1e-12 * max(float(gg.max(initial=0.0)), 1e-300)
        out[ok] = num[ok] / gg[ok]
        return out


class EffectKind(ABC):
    """How one kind of effect predicts, is named, written and shown."""

    kind: str = ""
    generic: bool = False  # part of the generic search, not the physical library
    needs_time: bool = False
    needs_direction: bool = False
    needs_temperature: bool = False  # offered only with a varying temp_c column
    #: its shape is the gravity term's fitted values when offered (the gravity term's
    #: ratios are then not refitted beneath it)
    built_on_gravity: bool = False
    description: str = ""

    def slot(self, spec: EffectSpec) -> tuple[str | int, ...]:
        """What the term is attached to, whatever its form (a model holds one term per
        slot: a drift and its lag form, a gravity term's linear and physical forms)."""
        return (spec.kind, spec.joint, spec.order, spec.parameter)

    @abstractmethod
    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]: ...

    @abstractmethod
    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        """``(r, 3, k)`` mm per unit parameter at the poses ``sel``."""

    @abstractmethod
    def label(self, spec: EffectSpec) -> str: ...

    @abstractmethod
    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]: ...

    @abstractmethod
    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]: ...

    @abstractmethod
    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence: ...


#: Effect kind -> its implementation (the ``kind`` of an ``[[effect]]`` table): the one
#: registry. Defined here, where a spec looks its kind up, and filled by
#: :mod:`calibration.effects.effect_kinds`, which gathers every kind (each kind's module
#: imports this one); the package imports that module first, so it is always full.
KINDS: dict[str, EffectKind] = {}


def param_number(params: Mapping[str, Any], key: str, kind: str) -> float:
    if key not in params:
        raise EffectLibraryError(f"effect {kind!r}: missing parameter {key!r}")
    value = params[key]
    if isinstance(value, tuple | list | str | bool):
        raise EffectLibraryError(f"effect {kind!r}: {key!r} must be a number")
    return float(value)


def param_vector(params: Mapping[str, Any], key: str, kind: str, length: int) -> FloatArray:
    if key not in params:
        raise EffectLibraryError(f"effect {kind!r}: missing parameter {key!r}")
    value = params[key]
    if (
        not isinstance(value, tuple | list)
        or len(value) != length
        or any(isinstance(v, str | bool) for v in value)
    ):
        raise EffectLibraryError(f"effect {kind!r}: {key!r} must be {length} numbers")
    return np.asarray(value, dtype=float)


def param_joint(params: Mapping[str, Any], kind: str, n_joints: int) -> int:
    j = param_number(params, "joint", kind)
    if j != int(j) or not 1 <= j <= n_joints:
        raise EffectLibraryError(f"effect {kind!r}: joint must be 1..{n_joints}, got {j}")
    return int(j)


def param_order(params: Mapping[str, Any], kind: str) -> int:
    k = param_number(params, "order", kind)
    if k != int(k) or k < 1:
        raise EffectLibraryError(f"effect {kind!r}: order must be a positive integer")
    return int(k)


def check_keys(params: Mapping[str, Any], allowed: set[str], kind: str) -> None:
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise EffectLibraryError(
            f"effect {kind!r}: unknown parameter {unknown[0]!r} (allowed: "
            f"{', '.join(sorted(allowed))})"
        )


def param_span(params: Mapping[str, Any], kind: str) -> tuple[float, ...]:
    """The campaign's time span of a time term (absent in files of earlier versions)."""
    if "t_min_s" not in params and "t_max_s" not in params:
        return ()
    lo, hi = param_number(params, "t_min_s", kind), param_number(params, "t_max_s", kind)
    if not lo <= hi:
        raise EffectLibraryError(f"effect {kind!r}: t_min_s must not exceed t_max_s")
    return (lo, hi)


def span_parameters(spec: EffectSpec) -> dict[str, float]:
    if len(spec.span_s) != 2:
        return {}
    return {"t_min_s": float(spec.span_s[0]), "t_max_s": float(spec.span_s[1])}


def check_t0(params: Mapping[str, Any], kind: str) -> None:
    if float(params.get("t0_s", 0.0)) != 0.0:
        raise EffectLibraryError(f"effect {kind!r}: only t0_s = 0 is supported")


#: The axes of a Cartesian vector, in parameter order.
AXES = ("x", "y", "z")
