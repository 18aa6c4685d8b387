"""Candidate effects the geometric model lacks: small parametric models with a physical meaning.

Each effect *kind* is linear in a few parameters and adds ``R·c`` to the geometric TCP, with
an analytic regressor ``R`` ``(m, 3, k)`` (mm per unit of each parameter) computed from the
pose data (:class:`EffectData`: joint readings, times, approach directions), the robot
description (gravity direction, Home) and the current geometric model. Some kinds also
have nonlinear *shape* parameters (``EffectSpec.shape``), held fixed while the linear ones
are fitted and profiled by the closed loop. :data:`KINDS` is the one registry: the loop
offers these kinds, ``[[effect]]`` tables name them, and the one predictor
(:func:`calibration.identify.identification.predicted_points`, through :func:`effect_terms`)
applies them. The library (method.md §4, §6):

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
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import EffectLibraryError
from calibration.identify.identification import EffectTerms, predicted_points
from calibration.model.description import EffectDescription, EffectValue, RobotDescription
from calibration.model.gravity_regressor import (
    BaseMoments,
    base_moments,
    gravity_of,
    link_rotations,
    moment_names,
    raw_regressor,
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
    #: ``(n,)`` rad (None: maps that read the rings alone). Such a map has absorbed the
    #: swept link's deflection in its sweep configuration, so the gravity term models the
    #: deflection relative to it (:class:`GravityDeflection`).
    sweep_reference: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.q_rad)

    @classmethod
    def from_sequence(
        cls,
        q_rad: ArrayLike,
        t_s: ArrayLike | None = None,
        start_rad: ArrayLike | None = None,
        min_move_rad: float = MIN_MOVE_RAD,
    ) -> EffectData:
        """Data of a pose sequence: each joint's approach direction is the sign of its move
        from the previous pose in time order (the first from ``start_rad``, e.g. Home).
        A move smaller than ``min_move_rad`` (a joint standing still, read with noise) keeps
        the direction it had; before any move it is 0."""
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
        return cls(q, t, direction)

    def subset(self, mask: ArrayLike) -> EffectData:
        m = np.asarray(mask)
        return EffectData(
            self.q_rad[m],
            None if self.t_s is None else self.t_s[m],
            None if self.direction is None else self.direction[m],
            self.sweep_reference,
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


@dataclass(frozen=True, eq=False)
class Kinematics:
    """The current geometric model at some poses ``(r, n)``: TCP ``(r, 3)`` and
    identification Jacobian ``(r, 3, 5n + 9)`` (world frame)."""

    model: KinematicModel
    q_rad: FloatArray
    tcp_mm: FloatArray
    jacobian: FloatArray
    _rotation_axes: dict[int, FloatArray] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, model: KinematicModel, q_rad: FloatArray) -> Kinematics:
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


# -- specs and kinds --------------------------------------------------------------------------
@dataclass(frozen=True)
class EffectSpec:
    """One candidate: a kind and what it is attached to (1-based joint, harmonic order,
    length ``a``/``d``, the loaded joints of a compliance). Hashable.

    ``names`` are named parts of a term (the gravity term's joint-moment pairs or base
    moments); ``shape`` holds nonlinear shape parameters, fixed while the term's linear
    parameters are fitted and profiled by the closed loop (a lag's time constant in s, the
    physical gravity form's compliance ratios); ``span_s`` is the campaign's time span
    ``(t_min, t_max)``: a polynomial in time is held at its ends outside it.
    """

    kind: str
    joint: int = 0
    order: int = 0
    parameter: str = ""
    joints: tuple[int, ...] = ()
    names: tuple[str, ...] = ()
    shape: tuple[float, ...] = ()
    span_s: tuple[float, ...] = ()

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
    description: str = ""

    def slot(self, spec: EffectSpec) -> tuple[Any, ...]:
        """What the term is attached to, whatever its form (a model holds one term per
        slot: a drift and its lag form, a gravity term's linear and physical forms)."""
        return (spec.kind, spec.joint, spec.order, spec.parameter)

    @abstractmethod
    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]: ...

    @abstractmethod
    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        kin: Kinematics,
    ) -> Evidence: ...


def _number(params: Mapping[str, Any], key: str, kind: str) -> float:
    if key not in params:
        raise EffectLibraryError(f"effect {kind!r}: missing parameter {key!r}")
    value = params[key]
    if isinstance(value, tuple | list | str | bool):
        raise EffectLibraryError(f"effect {kind!r}: {key!r} must be a number")
    return float(value)


def _vector(params: Mapping[str, Any], key: str, kind: str, length: int) -> FloatArray:
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


def _joint(params: Mapping[str, Any], kind: str, n_joints: int) -> int:
    j = _number(params, "joint", kind)
    if j != int(j) or not 1 <= j <= n_joints:
        raise EffectLibraryError(f"effect {kind!r}: joint must be 1..{n_joints}, got {j}")
    return int(j)


def _order(params: Mapping[str, Any], kind: str) -> int:
    k = _number(params, "order", kind)
    if k != int(k) or k < 1:
        raise EffectLibraryError(f"effect {kind!r}: order must be a positive integer")
    return int(k)


def _check_keys(params: Mapping[str, Any], allowed: set[str], kind: str) -> None:
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise EffectLibraryError(
            f"effect {kind!r}: unknown parameter {unknown[0]!r} (allowed: "
            f"{', '.join(sorted(allowed))})"
        )


class GravityCompliance(EffectKind):
    kind = "gravity_compliance"
    description = "links and bearings after the grating ring give under gravity and payload"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return tuple(f"joint{j}_compliance_urad_per_knm" for j in spec.joints)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
    ) -> FloatArray:
        tau = kin.torques_nmm(ctx.masses)
        cols = [kin.joint_axis(j) * (tau[:, j - 1] * URAD_PER_KNM)[:, None] for j in spec.joints]
        return np.stack(cols, axis=2)

    def label(self, spec: EffectSpec) -> str:
        return "gravity compliance (joints " + ", ".join(str(j) for j in spec.joints) + ")"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        c = np.zeros(n_joints)
        for j, v in zip(spec.joints, values, strict=True):
            c[j - 1] = v
        return {"compliance_urad_per_knm": tuple(float(v) for v in c)}

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        _check_keys(params, {"compliance_urad_per_knm"}, self.kind)
        c = _vector(params, "compliance_urad_per_knm", self.kind, n_joints)
        joints = tuple(range(1, n_joints + 1))
        return EffectSpec(self.kind, joints=joints), c

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: Kinematics,
    ) -> Evidence:
        # the joint whose term moves the TCP most
        torques = kin.torques_nmm(ctx.masses)
        shift = [
            np.sqrt(np.mean(np.sum(kin.joint_axis(j) ** 2, axis=1) * torques[:, j - 1] ** 2))
            * abs(v)
            for j, v in zip(spec.joints, values, strict=True)
        ]
        j = spec.joints[int(np.argmax(shift))]
        tau = torques[:, j - 1]
        return Evidence(
            x=tau / 1e6,
            x_label=f"gravity torque of joint {j} (kN·m)",
            y_label=f"joint {j} angle error (deg)",
            coordinate_mm=kin.joint_axis(j) * DEG,
        )


#: Gravity deflections are written in µrad.
URAD = 1e-6
GRAVITY_FORMS = ("linear", "physical")


#: Orders of a counterbalance's torque profile beyond the first (which link 2's own
#: moments already carry): a spring's torque is no pure sinusoid of the joint angle.
COUNTERBALANCE_ORDERS = (2, 3)


def counterbalance_terms(joint: int) -> tuple[str, ...]:
    """Names of a counterbalance's profile terms on ``joint``: ``joint2.counterbalance.cos2``."""
    return tuple(
        f"joint{joint}.counterbalance.{f}{k}" for k in COUNTERBALANCE_ORDERS for f in ("cos", "sin")
    )


def counterbalance_term(name: str) -> tuple[int, str, int] | None:
    """``"joint2.counterbalance.cos2"`` -> (2, "cos", 2); None for other names."""
    parts = name.split(".")
    if len(parts) != 3 or parts[1] != "counterbalance" or not parts[0].startswith("joint"):
        return None
    f, k = parts[2][:3], parts[2][3:]
    if f not in ("cos", "sin") or not k.isdigit() or not parts[0][5:].isdigit():
        return None
    return int(parts[0][5:]), f, int(k)


def joint_moment(name: str, kind: str, n_joints: int) -> tuple[int, str]:
    """``"joint3.link4.mx"`` -> (3, ``"link4.mx"``); errors name the term."""
    cb = counterbalance_term(name)
    if cb is not None and 1 <= cb[0] <= n_joints:
        return cb[0], name.split(".", 1)[1]
    head, _, moment = name.partition(".")
    if not (head.startswith("joint") and head[5:].isdigit()) or moment not in moment_names(
        n_joints
    ):
        raise EffectLibraryError(
            f"effect {kind!r}: term {name!r} is not 'jointJ.linkK.mA' (J, K in 1..{n_joints}, "
            "A in x, y, z)"
        )
    j = int(head[5:])
    if not 1 <= j <= n_joints:
        raise EffectLibraryError(f"effect {kind!r}: term {name!r}: joint must be 1..{n_joints}")
    return j, moment


def _strings(params: Mapping[str, Any], key: str, kind: str) -> tuple[str, ...]:
    value = params.get(key)
    if not isinstance(value, tuple | list) or not all(isinstance(v, str) for v in value):
        raise EffectLibraryError(f"effect {kind!r}: {key!r} must be a list of names")
    return tuple(value)


class GravityDeflection(EffectKind):
    """Gravity deflection with no mass model (method.md §6): joint j turns after its ring by
    ``c_j·τ_j(q)``, ``τ_j = g·Σ_k Ŷ_jk(q)·β_k`` linear in the base first moments β
    (:mod:`calibration.model.gravity_regressor`). Only products c·β are identifiable.

    * ``linear`` form: one free deflection ``p_jk = c_j·g·β_k`` (µrad) per loaded joint and
      base moment acting on it (``names``: ``jointJ.linkK.mA``), 30 for a 6R arm;
    * ``physical`` form: every joint shares the same moments, ``p_jk = ρ_j·w_k``: compliance
      ratios ρ (``shape``, one per loaded joint in ``joints``, 1 for the reference joint)
      and compliance-weighted moments w (µrad: the reference joint's deflection from that
      moment alone with its lever horizontal; ``names``: the base moments).
    """

    kind = "gravity_deflection"
    description = (
        "joints turn after their grating ring under the gravity torque of the links outboard "
        "(compliance × a torque linear in the links' first mass moments; no masses needed)"
    )

    def slot(self, spec: EffectSpec) -> tuple[Any, ...]:
        return (spec.kind,)  # the whole arm; ``parameter`` is the form

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        if spec.parameter == "physical":
            return tuple(
                f"{m}_urad" if counterbalance_term(m) else f"{m}_weighted_urad" for m in spec.names
            )
        return tuple(f"{n}_urad" for n in spec.names)

    @staticmethod
    def _plain(
        spec: EffectSpec, gravity: FloatArray, model: KinematicModel, q: FloatArray
    ) -> FloatArray:
        """Joint deflections per unit parameter ``(r, n, P)`` at poses ``q`` (before the
        µrad scale), the plain regressor with no sweep reference."""
        n = model.n_joints
        y = raw_regressor(model, q, gravity)
        raw = moment_names(n)
        out = np.zeros((len(q), n, len(spec.names)))
        ratio = dict(zip(spec.joints, spec.shape, strict=False))
        for p, name in enumerate(spec.names):
            cb = counterbalance_term(name)
            if cb is not None:
                j, f, k = cb
                out[:, j - 1, p] = (np.cos if f == "cos" else np.sin)(k * q[:, j - 1])
            elif spec.parameter == "physical":
                m = raw.index(name)
                for j, rho in ratio.items():
                    out[:, j - 1, p] = rho * y[:, j - 1, m]
            else:
                j, moment = joint_moment(name, "gravity_deflection", n)
                out[:, j - 1, p] = y[:, j - 1, raw.index(moment)]
        return out

    def deflection_jacobian(
        self, spec: EffectSpec, ctx: EffectContext, kin: Kinematics
    ) -> FloatArray:
        """``D`` ``(r, n, P)``: each joint's deflection per unit of each parameter (×1e-6
        rad for µrad values) at the poses of ``kin``.

        With a sweep reference in the data, joint j's row is less what j's map absorbed in
        its sweep (the reference with joint j at its reading): the deflection of every link
        i ≤ j there, turned into an angle about axis j by ``z_i·z_j`` (a rotation about a
        parallel upstream axis shows in j's circle one to one, about a perpendicular one
        it only tilts the circle). A term of joint j's own angle alone vanishes.
        """
        d = self._plain(spec, ctx.gravity, kin.model, kin.q_rad)
        ref = ctx.data.sweep_reference
        if ref is None:
            return d
        n = kin.model.n_joints
        home = np.asarray(ref, dtype=float)
        z = link_rotations(kin.model, home[None, :])[0, :, :, 2]  # axes at the reference
        seen = np.tril(z @ z.T).T  # [i, j] = z_i·z_j for i ≤ j
        scale = np.sqrt(np.mean(d * d, axis=0))  # (n, P) before the subtraction
        for j in range(n):
            qs = np.broadcast_to(home, kin.q_rad.shape).copy()
            qs[:, j] = kin.q_rad[:, j]
            absorbed = self._plain(spec, ctx.gravity, kin.model, qs)
            d[:, j] -= np.einsum("i,rip->rp", seen[: j + 1, j], absorbed[:, : j + 1])
        # what cancels (a term of the joint's own angle alone) cancels to rounding, ~1e-16
        # of the plain term: make it exactly zero, or it would pass for a parameter
        gone = np.sqrt(np.mean(d * d, axis=0)) <= 1e-9 * scale
        d[:, gone] = 0.0
        return d

    def joint_deflections_rad(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        kin: Kinematics,
        acting: NDArray[np.bool_] | None = None,
    ) -> FloatArray:
        """Each joint's deflection ``(r, n)`` rad at the poses of ``kin`` (relative to the
        sweep configuration when the data carry a sweep reference); ``acting`` ``(n, P)``
        keeps only some parameters' share of each joint's deflection."""
        d = self.deflection_jacobian(spec, ctx, kin)
        if acting is not None:
            d = d * acting[None, :, :]
        return d @ (np.asarray(values, dtype=float) * URAD)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
    ) -> FloatArray:
        d = self.deflection_jacobian(spec, ctx, kin)  # (r, n, P)
        theta = kin.jacobian[:, :, 3 : 5 * d.shape[1] : 5]  # ∂TCP/∂θ_j, (r, 3, n)
        reg: FloatArray = np.einsum("rak,rkp->rap", theta, d) * URAD
        return reg

    def label(self, spec: EffectSpec) -> str:
        joints = ", ".join(str(j) for j in spec.joints)
        form = spec.parameter or "linear"
        return f"gravity deflection (joints {joints}; {form} form)"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        v = tuple(float(x) for x in values)
        if spec.parameter == "physical":
            cb = [i for i, m in enumerate(spec.names) if counterbalance_term(m)]
            moments = [i for i in range(len(spec.names)) if i not in cb]
            out: dict[str, EffectValue] = {
                "form": "physical",
                "joints": tuple(float(j) for j in spec.joints),
                "compliance_ratio": tuple(float(r) for r in spec.shape),
                "moments": tuple(spec.names[i] for i in moments),
                "weighted_moment_urad": tuple(v[i] for i in moments),
            }
            if cb:
                out["counterbalance"] = tuple(spec.names[i] for i in cb)
                out["counterbalance_urad"] = tuple(v[i] for i in cb)
            return out
        return {"form": "linear", "terms": spec.names, "deflection_urad": v}

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        form = params.get("form", "linear")
        if form not in GRAVITY_FORMS:
            raise EffectLibraryError(
                f"effect {self.kind!r}: form must be one of {', '.join(GRAVITY_FORMS)}, "
                f"got {form!r}"
            )
        if form == "linear":
            _check_keys(params, {"form", "terms", "deflection_urad"}, self.kind)
            terms = _strings(params, "terms", self.kind)
            joints = sorted({joint_moment(t, self.kind, n_joints)[0] for t in terms})
            values = _vector(params, "deflection_urad", self.kind, len(terms))
            return EffectSpec(self.kind, parameter="linear", joints=tuple(joints), names=terms), (
                values
            )
        keys = {"form", "joints", "compliance_ratio", "moments", "weighted_moment_urad"}
        _check_keys(params, keys | {"counterbalance", "counterbalance_urad"}, self.kind)
        moments = _strings(params, "moments", self.kind)
        bad = [m for m in moments if m not in moment_names(n_joints)]
        if bad:
            raise EffectLibraryError(f"effect {self.kind!r}: unknown moment {bad[0]!r}")
        cb: tuple[str, ...] = ()
        cb_values = np.zeros(0)
        if "counterbalance" in params or "counterbalance_urad" in params:
            cb = _strings(params, "counterbalance", self.kind)
            for t in cb:
                term = counterbalance_term(t)
                if term is None or not 1 <= term[0] <= n_joints:
                    raise EffectLibraryError(
                        f"effect {self.kind!r}: counterbalance term {t!r} is not "
                        "'jointJ.counterbalance.cosK' or '...sinK'"
                    )
            cb_values = _vector(params, "counterbalance_urad", self.kind, len(cb))
        joints_f = params.get("joints")
        if not isinstance(joints_f, tuple | list) or not joints_f:
            raise EffectLibraryError(f"effect {self.kind!r}: 'joints' must be joint numbers")
        joints = []
        for j in joints_f:
            if isinstance(j, str) or j != int(j) or not 1 <= j <= n_joints:
                raise EffectLibraryError(
                    f"effect {self.kind!r}: 'joints' must be 1..{n_joints}, got {j!r}"
                )
            joints.append(int(j))
        ratios = _vector(params, "compliance_ratio", self.kind, len(joints))
        values = _vector(params, "weighted_moment_urad", self.kind, len(moments))
        spec = EffectSpec(
            self.kind,
            parameter="physical",
            joints=tuple(joints),
            names=moments + cb,
            shape=tuple(float(r) for r in ratios),
        )
        return spec, np.concatenate([values, cb_values])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: Kinematics,
    ) -> Evidence:
        defl = self.joint_deflections_rad(spec, values, ctx, kin)
        lever = np.stack([np.linalg.norm(kin.joint_axis(j), axis=1) for j in spec.joints], 1)
        shift = np.sqrt(np.mean((lever * defl[:, [j - 1 for j in spec.joints]]) ** 2, axis=0))
        j = spec.joints[int(np.argmax(shift))]
        return Evidence(
            x=np.degrees(defl[:, j - 1]),
            x_label=f"modelled gravity deflection of joint {j} (deg)",
            y_label=f"joint {j} angle error (deg)",
            coordinate_mm=kin.joint_axis(j) * DEG,
        )


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
        _check_keys(params, {"joint", "order", *keys}, self.kind)
        spec = EffectSpec(
            self.kind, joint=_joint(params, self.kind, n_joints), order=_order(params, self.kind)
        )
        if self.components == 1:
            return spec, np.array([_number(params, key, self.kind) for key in keys])
        return spec, np.concatenate(
            [_vector(params, key, self.kind, self.components) for key in keys]
        )


class JointHarmonic(HarmonicOfJoint):
    kind = "joint_harmonic"
    unit = "deg"
    components = 1
    description = "cyclic error of one joint's reading (harmonic of its angle)"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("cos_deg", "sin_deg")

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        kin: Kinematics,
    ) -> Evidence:
        return Evidence(
            x=np.degrees(ctx.data.q_rad[sel, spec.joint - 1]),
            x_label=f"joint {spec.joint} reading (deg)",
            y_label=f"joint {spec.joint} angle error (deg)",
            coordinate_mm=kin.joint_axis(spec.joint) * DEG,
        )


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
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        _check_keys(params, {"joint", "half_width_deg"}, self.kind)
        spec = EffectSpec(self.kind, joint=_joint(params, self.kind, n_joints))
        return spec, np.array([_number(params, "half_width_deg", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: Kinematics,
    ) -> Evidence:
        d = self._direction(spec, ctx, sel)
        return Evidence(
            x=d,
            x_label=f"joint {spec.joint} approach direction",
            y_label=f"joint {spec.joint} angle error (deg)",
            coordinate_mm=kin.joint_axis(spec.joint) * DEG,
        )


def _span(params: Mapping[str, Any], kind: str) -> tuple[float, ...]:
    """The campaign's time span of a time term (absent in files of earlier versions)."""
    if "t_min_s" not in params and "t_max_s" not in params:
        return ()
    lo, hi = _number(params, "t_min_s", kind), _number(params, "t_max_s", kind)
    if not lo <= hi:
        raise EffectLibraryError(f"effect {kind!r}: t_min_s must not exceed t_max_s")
    return (lo, hi)


def _span_parameters(spec: EffectSpec) -> dict[str, float]:
    if len(spec.span_s) != 2:
        return {}
    return {"t_min_s": float(spec.span_s[0]), "t_max_s": float(spec.span_s[1])}


def _t0(params: Mapping[str, Any], kind: str) -> None:
    if float(params.get("t0_s", 0.0)) != 0.0:
        raise EffectLibraryError(f"effect {kind!r}: only t0_s = 0 is supported")


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
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        out.update(_span_parameters(spec))
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
        _check_keys(params, allowed | ({"time_constant_s"} if lag else set()), self.kind)
        _t0(params, self.kind)
        shape: tuple[float, ...] = ()
        if lag:
            tau = _number(params, "time_constant_s", self.kind)
            if not tau > 0:
                raise EffectLibraryError(f"effect {self.kind!r}: time_constant_s must be > 0")
            shape = (tau,)
        spec = EffectSpec(
            self.kind,
            joint=_joint(params, self.kind, n_joints),
            parameter=keys[0][0],
            shape=shape,
            span_s=_span(params, self.kind),
        )
        return spec, np.array([_number(params, keys[0], self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: Kinematics,
    ) -> Evidence:
        t = ctx.times_h(sel)
        return Evidence(
            x=t,
            x_label="time since the start of the campaign (h)",
            y_label=f"joint {spec.joint} {spec.parameter} error (mm)",
            coordinate_mm=kin.length_axis(spec.joint, spec.parameter),
        )


class InstrumentScale(EffectKind):
    kind = "instrument_scale"
    description = "distance-proportional scale error of the tracker"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("scale_ppm",)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        _check_keys(params, {"scale_ppm"}, self.kind)
        return EffectSpec(self.kind), np.array([_number(params, "scale_ppm", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: Kinematics,
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
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
    ) -> FloatArray:
        t = ctx.times_h(sel, span_s=spec.span_s)
        return (kin.tcp_mm * 1e-6 * t[:, None])[:, :, None]

    def label(self, spec: EffectSpec) -> str:
        return "tracker scale drift"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {"rate_ppm_per_h": float(values[0]), "t0_s": 0.0, **_span_parameters(spec)}

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        _check_keys(params, {"rate_ppm_per_h", "t0_s", "t_min_s", "t_max_s"}, self.kind)
        _t0(params, self.kind)
        spec = EffectSpec(self.kind, span_s=_span(params, self.kind))
        return spec, np.array([_number(params, "rate_ppm_per_h", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: Kinematics,
    ) -> Evidence:
        t = ctx.times_h(sel)
        return Evidence(
            x=t,
            x_label="time since the start of the campaign (h)",
            y_label="scale error (ppm)",
            coordinate_mm=kin.tcp_mm * 1e-6,
        )


_AXES = ("x", "y", "z")


class CartesianHarmonic(HarmonicOfJoint):
    kind = "cartesian_harmonic"
    unit = "mm"
    components = 3
    generic = True
    description = "an error vector in the tracker frame varying with a harmonic of one joint"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return tuple(f"{a}_{f}_mm" for f in ("cos", "sin") for a in _AXES)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        kin: Kinematics,
    ) -> Evidence:
        a = int(np.argmax(np.hypot(values[:3], values[3:])))
        g = np.zeros((len(kin.tcp_mm), 3))
        g[:, a] = 1.0
        return Evidence(
            x=np.degrees(ctx.data.q_rad[sel, spec.joint - 1]),
            x_label=f"joint {spec.joint} reading (deg)",
            y_label=f"{_AXES[a].upper()} error (mm)",
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
        return tuple(f"{a}_{f}_deg" for f in ("cos", "sin") for a in _AXES)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        kin: Kinematics,
    ) -> Evidence:
        a = int(np.argmax(np.hypot(values[:3], values[3:])))
        return Evidence(
            x=np.degrees(ctx.data.q_rad[sel, spec.joint - 1]),
            x_label=f"joint {spec.joint} reading (deg)",
            y_label=f"link {spec.joint} rotation about its {_AXES[a]} axis (deg)",
            coordinate_mm=kin.rotation_axes(spec.joint)[:, :, a] * DEG,
        )


class CartesianTime(EffectKind):
    kind = "cartesian_time"
    generic = True
    needs_time = True
    description = (
        "an error vector fixed in the tracker frame or in a link's frame, polynomial in time"
    )

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        names = [f"{a}_mm_per_h" for a in _AXES]
        if spec.order >= 2:
            names += [f"{a}_mm_per_h2" for a in _AXES]
        return tuple(names)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: Kinematics
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
        out.update(_span_parameters(spec))
        return out

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        allowed = {"frame", "rate_mm_per_h", "acceleration_mm_per_h2", "t0_s", "t_min_s", "t_max_s"}
        _check_keys(params, allowed, self.kind)
        _t0(params, self.kind)
        frame = _number(params, "frame", self.kind) if "frame" in params else 0.0
        if frame != int(frame) or not 0 <= frame <= n_joints:
            raise EffectLibraryError(f"effect {self.kind!r}: frame must be 0..{n_joints}")
        v = _vector(params, "rate_mm_per_h", self.kind, 3)
        order = 1
        if "acceleration_mm_per_h2" in params:
            v = np.concatenate([v, _vector(params, "acceleration_mm_per_h2", self.kind, 3)])
            order = 2
        spec = EffectSpec(self.kind, joint=int(frame), order=order, span_s=_span(params, self.kind))
        return spec, v

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: Kinematics,
    ) -> Evidence:
        t = ctx.times_h(sel)
        v = values.reshape(spec.order, 3)
        a = int(np.argmax(np.sqrt(np.sum(v**2, axis=0))))
        frame = "" if spec.joint == 0 else f" of link {spec.joint}'s frame"
        return Evidence(
            x=t,
            x_label="time since the start of the campaign (h)",
            y_label=f"{_AXES[a]} error{frame} (mm)",
            coordinate_mm=kin.frame_axes(spec.joint)[:, :, a],
        )


#: Effect kind -> its implementation (the ``kind`` of an ``[[effect]]`` table).
KINDS: dict[str, EffectKind] = {
    k.kind: k
    for k in (
        GravityDeflection(),
        GravityCompliance(),
        JointHarmonic(),
        LostMotion(),
        LengthDrift(),
        InstrumentScale(),
        InstrumentScaleDrift(),
        CartesianHarmonic(),
        LinkHarmonic(),
        CartesianTime(),
    )
}
LIBRARY_KINDS = tuple(k for k, v in KINDS.items() if not v.generic)
GENERIC_KINDS = tuple(k for k, v in KINDS.items() if v.generic)


def check_kinds(kinds: Collection[str]) -> None:
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise EffectLibraryError(f"unknown effect kind {unknown[0]!r} (valid: {', '.join(KINDS)})")


# -- candidates, terms, descriptions ----------------------------------------------------------
def harmonic_orders(q_rad: ArrayLike) -> tuple[int, ...]:
    """Harmonic orders ``1..K`` scanned for a joint read at ``q_rad`` ``(m,)`` rad.

    ``K`` is what the poses resolve: a period ``2π/K`` spanning :data:`POSES_PER_PERIOD`
    poses on average over the joint's coverage (``K = 2π·m / (4·coverage)``), at least
    :data:`MIN_HARMONIC_ORDER`, at most :data:`MAX_HARMONIC_ORDER`; none for a joint that
    does not move. The closed loop scores the best order of each scan, Šidák-corrected
    for the orders scanned (:func:`calibration.effects.candidate_scoring.score_candidate`).
    """
    q = np.asarray(q_rad, dtype=float)
    coverage = float(np.ptp(q)) if q.size else 0.0
    if coverage <= MIN_MOVE_RAD:
        return ()
    resolved = int(2.0 * math.pi * len(q) / (POSES_PER_PERIOD * coverage))
    return tuple(range(1, min(MAX_HARMONIC_ORDER, max(MIN_HARMONIC_ORDER, resolved)) + 1))


def loaded_joints(ctx: EffectContext) -> tuple[int, ...]:
    """Joints (1-based) whose RMS gravity torque over the poses is at least
    :data:`LOADED_JOINT_FRACTION` of the largest (none without a mass model)."""
    rms = np.sqrt(np.mean(ctx.torques_nmm**2, axis=0))
    top = float(rms.max(initial=0.0))
    if top <= 0.0:
        return ()
    return tuple(int(j) + 1 for j in np.flatnonzero(rms >= LOADED_JOINT_FRACTION * top))


def gravity_candidate(ctx: EffectContext) -> EffectSpec | None:
    """The gravity deflection in its linear form: every loaded joint with every base
    moment acting on it (None when gravity loads no joint)."""
    base = ctx.base_moments
    names = tuple(
        f"joint{j + 1}.{base.names[i]}" for j, cols in enumerate(base.per_joint) for i in cols
    )
    if not names:
        return None
    for j, joint in enumerate(ctx.description.joints, start=1):
        if joint.counterbalance and j in base.loaded_joints:
            names += counterbalance_terms(j)
    return EffectSpec(
        "gravity_deflection", parameter="linear", joints=base.loaded_joints, names=names
    )


def candidate_effects(ctx: EffectContext, kinds: Collection[str] | None = None) -> list[EffectSpec]:
    """Every candidate for these poses: the library, then the generic search.

    ``kinds`` restricts the kinds offered (default: all but ``gravity_compliance``, the
    mass-model form of the gravity term, which is offered only when named). Time terms
    need ``t_s``, lost motion the approach directions, ``gravity_compliance`` a mass model.
    Harmonics come at every order :func:`harmonic_orders` resolves; each joint's orders of
    one kind are one scan (:func:`scan_key`).
    """
    allowed = set(KINDS) if kinds is None else set(kinds)
    check_kinds(allowed)
    n = ctx.description.n_joints
    has_t = ctx.data.t_s is not None and float(np.ptp(ctx.data.t_s)) > 0
    out: list[EffectSpec] = []

    def offer(spec: EffectSpec) -> None:
        kind = KINDS[spec.kind]
        if spec.kind not in allowed or (kind.needs_time and not has_t):
            return
        if kind.needs_direction and ctx.data.direction is None:
            return
        out.append(spec)

    gravity = gravity_candidate(ctx)
    if gravity is not None:
        offer(gravity)
    loaded = loaded_joints(ctx)
    if loaded and kinds is not None:  # the mass-model form: only when asked for by name
        offer(EffectSpec("gravity_compliance", joints=loaded))
    orders = [harmonic_orders(ctx.data.q_rad[:, j]) for j in range(n)]
    for j in range(1, n + 1):
        for k in orders[j - 1]:
            offer(EffectSpec("joint_harmonic", joint=j, order=k))
    for j in range(1, n + 1):
        offer(EffectSpec("lost_motion", joint=j))
    for j, joint in enumerate(ctx.description.joints, start=1):
        for parameter, length in (("d", joint.d_mm), ("a", joint.a_mm)):
            if abs(length) >= DRIFT_MIN_LENGTH_MM:
                offer(EffectSpec("length_drift", joint=j, parameter=parameter))
    offer(EffectSpec("instrument_scale"))
    offer(EffectSpec("instrument_scale_drift"))
    for kind in ("cartesian_harmonic", "link_harmonic"):
        for j in range(1, n + 1):
            for k in orders[j - 1]:
                offer(EffectSpec(kind, joint=j, order=k))
    for frame in range(n + 1):
        offer(EffectSpec("cartesian_time", joint=frame, order=1))
    offer(EffectSpec("cartesian_time", joint=0, order=2))
    return out


def scan_key(spec: EffectSpec) -> tuple[str, int] | None:
    """The scan a candidate belongs to: a harmonic's kind and joint (its orders are scanned
    together, the best one scored); None for a candidate scored on its own."""
    return (spec.kind, spec.joint) if isinstance(KINDS[spec.kind], HarmonicOfJoint) else None


def regressor_matrix(
    specs: Sequence[EffectSpec], ctx: EffectContext, sel: slice, kin: Kinematics
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
        return regressor_matrix(specs, ctx, sel, Kinematics.of(model, q[sel]))

    return EffectTerms(
        names=names,
        regressor=regressor,
        start=None if start is None else tuple(float(v) for v in np.asarray(start)),
    )


def _tag(spec: EffectSpec) -> str:
    if spec.kind == "gravity_compliance":
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
