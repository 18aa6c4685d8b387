"""The candidates the closed loop offers for some poses (:func:`candidate_effects`): the
library, then the generic search; harmonics at every order the poses resolve
(:func:`harmonic_orders`), each joint's orders of one kind one scan (:func:`scan_key`)."""

from __future__ import annotations

import math
from collections.abc import Collection

import numpy as np
from numpy.typing import ArrayLike

from calibration.effects.effect_base import (
    DRIFT_MIN_LENGTH_MM,
    LOADED_JOINT_FRACTION,
    MAX_HARMONIC_ORDER,
    MIN_HARMONIC_ORDER,
    MIN_MOVE_RAD,
    POSES_PER_PERIOD,
    EffectContext,
    EffectData,
    EffectSpec,
)
from calibration.effects.effect_gravity import counterbalance_terms
from calibration.effects.effect_harmonics import HarmonicOfJoint
from calibration.effects.effect_kinds import KINDS, check_kinds
from calibration.effects.effect_thermal import (
    MIN_TEMPERATURE_RANGE_K,
    reference_temperature_c,
)

#: Two harmonic orders of one joint are told apart when they drift this many cycles against
#: each other over the joint's coverage (:func:`order_resolution`).
ORDER_BEATS = 1.0


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


def order_resolution(q_rad: ArrayLike) -> float:
    """The smallest difference of two harmonic orders a joint read at ``q_rad`` ``(m,)`` rad
    tells apart: ``2π / coverage`` to the nearest whole order (at least 1), the Rayleigh
    criterion — orders k and k' drift by one full cycle against each other over the
    coverage only when ``|k − k'|·coverage ≥ 2π``. Closer orders are one harmonic under a
    slow envelope; fitted together they take large amplitudes of opposite sign that cancel
    on the covered angles and not beyond them (infinite for a joint that does not move).

    The coverage is the range of the central 98 % of the readings (1st to 99th
    percentile): one isolated pose among 100 or more (a parked pose among random ones)
    does not resolve a pair that the others leave unresolved, and a joint read all round
    resolves every order (its coverage a little short of 2π)."""
    q = np.asarray(q_rad, dtype=float)
    coverage = float(np.subtract(*np.percentile(q, [99.0, 1.0]))) if q.size else 0.0
    if coverage <= MIN_MOVE_RAD:
        return math.inf
    return float(max(1, math.floor(ORDER_BEATS * 2.0 * math.pi / coverage + 0.5)))


def resolved_beside(spec: EffectSpec, specs: Collection[EffectSpec], q_rad: ArrayLike) -> bool:
    """Whether a harmonic candidate ``spec`` is told apart from every harmonic of the same
    joint in ``specs`` (any harmonic kind, another order): the orders differ by at least
    :func:`order_resolution` of that joint's readings ``q_rad`` ``(m, n)`` rad in the
    identification poses. Other candidates always are. The same order of another kind (a
    link's wobble beside its reading's error) differs in direction, not in frequency."""
    if scan_key(spec) is None:
        return True
    others = [
        s.order
        for s in specs
        if scan_key(s) is not None and s.joint == spec.joint and s.order != spec.order
    ]
    if not others:
        return True
    resolution = order_resolution(np.asarray(q_rad, dtype=float)[:, spec.joint - 1])
    return all(abs(spec.order - k) >= resolution for k in others)


def resolved_candidates(
    offered: list[EffectSpec], specs: Collection[EffectSpec], data: EffectData
) -> list[EffectSpec]:
    """The round's candidates ``offered`` with every harmonic not resolved beside the
    model's ``specs`` (:func:`resolved_beside`) left out, over the poses of ``data``; all
    of them when the data carry scale maps from sweeps (``sweep_reference``): there the
    loop's harmonics correct maps measured over the joint's whole range, which the joint
    fit rounds fold into them, not terms extrapolated beyond the poses' angles (the demo's
    first round needs orders 1 and 2 of joint 5 together, unresolved over its poses)."""
    if data.sweep_reference is not None:
        return offered
    return [s for s in offered if resolved_beside(s, specs, data.q_rad)]


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
    need ``t_s``, temperature terms a ``temp_c`` varying by at least
    :data:`~calibration.effects.effect_thermal.MIN_TEMPERATURE_RANGE_K`, lost motion the
    approach directions, ``gravity_compliance`` a mass model.
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
    for spec in temperature_candidates(ctx):
        offer(spec)
    for kind in ("cartesian_harmonic", "link_harmonic"):
        for j in range(1, n + 1):
            for k in orders[j - 1]:
                offer(EffectSpec(kind, joint=j, order=k))
    for frame in range(n + 1):
        offer(EffectSpec("cartesian_time", joint=frame, order=1))
    offer(EffectSpec("cartesian_time", joint=0, order=2))
    return out


def temperature_candidates(ctx: EffectContext) -> list[EffectSpec]:
    """The terms driven by the measured temperature, each with the median temperature
    as its reference: none without a ``temp_c`` varying by at least
    :data:`~calibration.effects.effect_thermal.MIN_TEMPERATURE_RANGE_K`."""
    temp = ctx.data.temp_c
    if temp is None or float(np.ptp(temp)) < MIN_TEMPERATURE_RANGE_K:
        return []
    t_ref = reference_temperature_c(temp)
    out = [
        EffectSpec("thermal_expansion", joints=g, t_ref_c=t_ref)
        for g in link_groups(ctx.description.n_joints)
    ]
    for j, joint in enumerate(ctx.description.joints, start=1):
        for parameter, length in (("d", joint.d_mm), ("a", joint.a_mm)):
            if abs(length) >= DRIFT_MIN_LENGTH_MM:
                out.append(
                    EffectSpec("length_temperature", joint=j, parameter=parameter, t_ref_c=t_ref)
                )
    return [*out, EffectSpec("instrument_scale_temperature", t_ref_c=t_ref)]


def link_groups(n_joints: int) -> tuple[tuple[int, ...], ...]:
    """The link groups of a thermal expansion: the whole arm, and for more than 3 joints
    the arm (joints 1–3: the long castings) and the wrist (4..n) apart, which warm
    differently (their own motors, less mass)."""
    whole = tuple(range(1, n_joints + 1))
    if n_joints <= 3:
        return (whole,)
    return (whole, (1, 2, 3), tuple(range(4, n_joints + 1)))


def scan_key(spec: EffectSpec) -> tuple[str, int] | None:
    """The scan a candidate belongs to: a harmonic's kind and joint (its orders are scanned
    together, the best one scored); None for a candidate scored on its own."""
    return (spec.kind, spec.joint) if isinstance(KINDS[spec.kind], HarmonicOfJoint) else None
