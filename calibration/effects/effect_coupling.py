"""``joint_coupling``: two joints sharing compliance after their rings, the cross term of
the joints' compliance matrix under gravity; see :mod:`calibration.effects.effect_base`
for the library.

The gravity term treats each joint as turning under its own torque alone, ``δq_j =
c_j·τ_j``. Where two joints share a structure that gives (the shoulder and the elbow in
one gearbox housing, a parallelogram linkage driving the elbow from the base, the casting
both bearings sit in), the compliance matrix has a cross term, and by Maxwell's
reciprocity one cross compliance works both ways:

    δq_a = c_aa·τ_a + c_ab·τ_b ,     δq_b = c_ab·τ_a + c_bb·τ_b

Rewritten with the one-ratio-per-joint form's compliances carrying the cross term,

    δq_a = (c_aa + c_ab)·τ_a − c_ab·(τ_a − τ_b) ,     δq_b = (c_bb + c_ab)·τ_b + c_ab·(τ_a − τ_b)

what a gravity term cannot have is the **differential** part: ``c_ab·(τ_a − τ_b)``,
taken from joint a and given to joint b. On an arm whose joints 2 and 3 are parallel,
``τ_2 − τ_3`` is the torque of link 2's own moments, which joint 3 never carries in either
gravity form (joint 2's share the gravity term's link-2 moments absorb). The torques are
not known, but the gravity term in the model carries them times a compliance:
``T_j(q) = 1e-6·(Σ_k Ŷ_jk(q)·w_k + counterbalance_j(q))`` rad, with ``w`` its physical
form's compliance-weighted moments (µrad; a counterbalance's terms over their joint's
ratio), or its linear form's joint-a block (joint a's own compliance). So the cross term
is **one parameter**, ``coupling_ratio`` ``κ`` (``c_ab`` over that compliance), with the
regressor

    (∂TCP/∂θ_b − ∂TCP/∂θ_a) · (T_a(q) − T_b(q))

(:class:`JointCoupling`). With the physical form's ratios ``ρ`` (which then carry
``c_jj + c_ab`` over the reference compliance) the coefficient ``c_ab/√(c_aa·c_bb)`` is
``κ/√((ρ_a − κ)·(ρ_b − κ))``. The candidate is offered for the shoulder pair
(:data:`COUPLED_JOINTS`) once a gravity term loading both joints is in the model (either
form); ``w`` is frozen when it is offered (``shape``, written to the file), as a link's
bending freezes it: a frozen scale error of ``w`` only rescales ``κ``. Not with scale maps
fitted on sweeps (``sweep_reference``): what the maps absorbed of the cross term is not
modelled.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
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
    param_number,
    param_vector,
)
from calibration.effects.effect_gravity import counterbalance_term, group_moment
from calibration.errors import EffectLibraryError
from calibration.model.description import EffectValue
from calibration.model.gravity_regressor import moment_names, raw_regressor
from calibration.model.kinematics import KinematicModel

URAD = 1e-6
#: The pair offered (1-based): the shoulder and the elbow, the joints that carry the arm.
COUPLED_JOINTS = (2, 3)


def torque_proxy_rad(
    spec: EffectSpec, gravity: FloatArray, model: KinematicModel, q_rad: FloatArray
) -> FloatArray:
    """``T_j = c·τ_j`` ``(r, n)`` rad at poses ``q_rad`` ``(r, n)``: each joint's gravity
    torque times one compliance ``c`` (the physical form's reference joint's, or the
    linear form's joint a's), from the frozen weighted moments ``spec.shape`` (µrad) of
    ``spec.names`` (a counterbalance's terms: its joint's own deflection over that
    joint's compliance ratio)."""
    n = model.n_joints
    y = raw_regressor(model, q_rad, gravity)  # (r, n, 3n)
    raw = moment_names(n)
    out = np.zeros((len(q_rad), n))
    for name, w in zip(spec.names, spec.shape, strict=True):
        cb = counterbalance_term(name)
        if cb is None:
            out += w * y[:, :, raw.index(name)]
        else:
            j, f, k = cb
            out[:, j - 1] += w * (np.cos if f == "cos" else np.sin)(k * q_rad[:, j - 1])
    return out * URAD


class JointCoupling(EffectKind):
    """Joints a and b (``spec.joints``) sharing compliance: beside a gravity term, joint b
    turns by ``κ·(T_a − T_b)`` and joint a by ``−κ·(T_a − T_b)`` (the cross term's
    differential part); ``spec.names`` the gravity term's moments (and counterbalance
    terms), ``spec.shape`` their weighted values (µrad) when offered."""

    kind = "joint_coupling"
    built_on_gravity = True
    description = (
        "two joints sharing compliance after their rings (a shared gearbox housing, a "
        "parallelogram linkage): each turns under the other's gravity torque (the "
        "gravity term's moments)"
    )

    def slot(self, spec: EffectSpec) -> tuple[str | int, ...]:
        return (spec.kind, *spec.joints)

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("coupling_ratio",)

    def differential_rad(
        self, spec: EffectSpec, ctx: EffectContext, kin: ModelAtPoses
    ) -> FloatArray:
        """``T_a − T_b`` ``(r,)`` rad per unit ratio: joint b's turn, joint a's negated."""
        t = torque_proxy_rad(spec, ctx.gravity, kin.model, kin.q_rad)
        a, b = spec.joints
        out: FloatArray = t[:, a - 1] - t[:, b - 1]
        return out

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        turn = self.differential_rad(spec, ctx, kin)
        a, b = spec.joints
        axis = kin.joint_axis(b) - kin.joint_axis(a)
        out: FloatArray = (axis * turn[:, None])[:, :, None]
        return out

    def label(self, spec: EffectSpec) -> str:
        a, b = spec.joints
        return f"coupled compliance of joints {a} and {b} under gravity"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {
            "joints": tuple(float(j) for j in spec.joints),
            "coupling_ratio": float(values[0]),
            "moments": spec.names,
            "weighted_moment_urad": tuple(float(v) for v in spec.shape),
        }

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        check_keys(
            params, {"joints", "coupling_ratio", "moments", "weighted_moment_urad"}, self.kind
        )
        pair = param_vector(params, "joints", self.kind, 2)
        if any(j != int(j) or not 1 <= j <= n_joints for j in pair) or pair[0] == pair[1]:
            raise EffectLibraryError(
                f"effect {self.kind!r}: 'joints' must be two different joints in 1..{n_joints}"
            )
        names = params.get("moments")
        if not isinstance(names, tuple | list) or not names:
            raise EffectLibraryError(f"effect {self.kind!r}: 'moments' must be a list of names")
        for m in names:
            cb = counterbalance_term(m) if isinstance(m, str) else None
            if m not in moment_names(n_joints) and (cb is None or not 1 <= cb[0] <= n_joints):
                raise EffectLibraryError(f"effect {self.kind!r}: unknown moment {m!r}")
        w = param_vector(params, "weighted_moment_urad", self.kind, len(names))
        spec = EffectSpec(
            self.kind,
            joints=(int(pair[0]), int(pair[1])),
            names=tuple(names),
            shape=tuple(float(v) for v in w),
        )
        return spec, np.array([param_number(params, "coupling_ratio", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        a, b = spec.joints
        turn = self.differential_rad(spec, ctx, kin) * float(values[0])
        return Evidence(
            x=np.degrees(turn),
            x_label=f"modelled turn of joint {b} under joint {a}'s differential torque (deg)",
            y_label=f"joint {b} / −joint {a} angle error (deg)",
            coordinate_mm=(kin.joint_axis(b) - kin.joint_axis(a)) * DEG,
        )


def coupling_candidates(
    ctx: EffectContext,
    specs: Sequence[EffectSpec],
    values: Sequence[FloatArray],
    exclude: Collection[EffectSpec] = (),
) -> list[EffectSpec]:
    """The shoulder pair's coupling, offered once the model ``specs`` (with ``values``,
    one array per spec) holds a gravity term loading both joints, its torques frozen from
    that term (:func:`coupling_weights`); none when the coupling is in the model or in
    ``exclude`` already, or the data carry a sweep reference."""
    if ctx.data.sweep_reference is not None:
        return []
    if any(s.kind == JointCoupling.kind for s in (*specs, *exclude)):
        return []
    for spec, v in zip(specs, values, strict=True):
        if spec.kind == "gravity_deflection":
            weights = coupling_weights(spec, v, COUPLED_JOINTS[0])
            if weights is None or not set(COUPLED_JOINTS) <= set(spec.joints):
                return []
            names, w = weights
            return [EffectSpec(JointCoupling.kind, joints=COUPLED_JOINTS, names=names, shape=w)]
    return []


def coupling_moment_columns(
    names: Sequence[str], columns_of: Callable[[EffectSpec], FloatArray]
) -> FloatArray:
    """The shoulder pair's coupling ``(3m, b)`` per unit weighted moment of each of the
    base moments ``names``: the columns ``D`` with which a physical gravity form is
    fitted beside its coupling (:func:`~calibration.effects.effect_shapes.fit_physical_gravity`),
    ``columns_of`` a candidate's weighted regressor ``(3m, 1)``."""
    return np.hstack(
        [
            columns_of(
                EffectSpec(JointCoupling.kind, joints=COUPLED_JOINTS, names=(n,), shape=(1.0,))
            )
            for n in names
        ]
    )


def coupling_weights(
    spec: EffectSpec, values: FloatArray, joint: int
) -> tuple[tuple[str, ...], tuple[float, ...]] | None:
    """Moment names and weights (µrad) whose torques stand for the joints' torques times
    one compliance: a physical gravity term's weighted moments (a counterbalance's terms
    over their joint's ratio), or a linear one's block of ``joint`` (that joint's own
    compliance); None when the term gives none."""
    if spec.parameter == "physical":
        # a limit form's group (its own moments, its own reference compliance) holding a
        # coupled joint leaves no common compliance to couple by; other groups' moments do
        # not load the pair (docs/closed-loop.md, "Limit form")
        grouped = [group_moment(m) for m in spec.names]
        if any(g is not None and set(g[0]) & set(COUPLED_JOINTS) for g in grouped):
            return None
        ratio = dict(zip(spec.joints, spec.shape, strict=True))
        names: list[str] = []
        weights: list[float] = []
        for name, value, g in zip(spec.names, values, grouped, strict=True):
            if g is not None:
                continue
            cb = counterbalance_term(name)
            if cb is not None and ratio.get(cb[0], 1.0) == 0.0:
                # a bounded fit's joint whose deflection the data do not show: its
                # torque is not known from it; the pair's is needed, another's is not
                if cb[0] in COUPLED_JOINTS:
                    return None
                continue
            names.append(name)
            weights.append(float(value) if cb is None else float(value) / ratio.get(cb[0], 1.0))
        if not names or not all(np.isfinite(weights)):
            return None
        return tuple(names), tuple(weights)
    names, weights = [], []
    for term, value in zip(spec.names, values, strict=True):
        head, _, moment = term.partition(".")
        if head == f"joint{joint}":
            names.append(moment if counterbalance_term(term) is None else term)
            weights.append(float(value))
    return (tuple(names), tuple(weights)) if names else None
