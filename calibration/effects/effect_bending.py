"""``link_bending``: a link turning about its own x and y axes under the bending moment of
everything outboard (the link's bending and its output bearing's tilting, lumped at the
joint); see :mod:`calibration.effects.effect_base` for the library.

The moment gravity exerts at link j's frame origin about an axis u is linear in the same
first mass moments as the joint torques (:mod:`calibration.model.gravity_regressor`):

    M_u(q) = g · Σ_{k ≥ j} Σ_a (R_k e_a)·(ĝ × u) · μ_k,a

the gravity regressor with u in place of the joint axis z_j. The moments μ are not known,
but a physical gravity term in the model carries them weighted by its reference joint's
compliance (``w_k = c_ref·g·β_k``, µrad). So the bending of link j about x_j and y_j is

    φ_u = ρ_j · 1e-6 · Σ_k Ŷ^u_jk(q) · w_k

with one parameter, ``ρ_j`` (``bending_ratio``): link j's bending compliance over the
reference joint's. The candidate is offered only once a gravity term in its physical form
is in the model; its ``w`` are frozen when it is offered (``shape``, written to the file).
The moments are the gravity term's base set, chosen for joint torques: a raw moment that
is grouped into others for every joint torque but bends a link (link 1's moments, for
one) is missing. A moment constant in the link's own frame tilts everything outboard by a
constant, which the geometry absorbs.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
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
    param_vector,
)
from calibration.effects.effect_gravity import counterbalance_term, group_moment
from calibration.errors import EffectLibraryError
from calibration.model.description import EffectValue
from calibration.model.gravity_regressor import link_rotations, moment_names
from calibration.model.kinematics import KinematicModel

URAD = 1e-6
#: The axes a link bends about (its own x and y; about z it is the joint's deflection).
BENDING_AXES = (0, 1)


def _names(params: Mapping[str, Any], kind: str) -> tuple[str, ...]:
    value = params.get("moments")
    if not isinstance(value, tuple | list) or not all(isinstance(v, str) for v in value):
        raise EffectLibraryError(f"effect {kind!r}: 'moments' must be a list of names")
    return tuple(value)


class LinkBending(EffectKind):
    """Link j (``spec.joint``) turning about its own x and y axes by ``ρ·M⊥/(c_ref·g)``:
    ``spec.names`` the gravity term's base moments, ``spec.shape`` their weighted values
    (µrad) when the candidate was offered."""

    kind = "link_bending"
    built_on_gravity = True
    description = (
        "a link turning about its own x and y axes under the bending moment of everything "
        "outboard (its bending and its bearing's tilt; the gravity term's moments)"
    )

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return ("bending_ratio",)

    def bending_rad(self, spec: EffectSpec, ctx: EffectContext, kin: ModelAtPoses) -> FloatArray:
        """Rotation ``(r, 2)`` rad of link j about its x and y axes per unit ratio."""
        n = kin.model.n_joints
        j = spec.joint
        rot = link_rotations(kin.model, kin.q_rad)  # (r, n, 3, 3), robot base frame
        raw = moment_names(n)
        index = np.array([raw.index(m) for m in spec.names], dtype=np.intp)
        link = index // 3  # 0-based link of each moment
        axis = index % 3
        acting = link >= j - 1  # everything outboard of joint j, link j included
        arms = np.einsum("rpca,pa->rpc", rot[:, link], np.eye(3)[axis])  # (r, P, 3): R_k e_a
        out = np.zeros((len(kin.q_rad), len(BENDING_AXES)))
        w = np.asarray(spec.shape, dtype=float) * acting
        for c, u in enumerate(BENDING_AXES):
            lever = np.cross(ctx.gravity, rot[:, j - 1, :, u])  # ĝ × u, (r, 3)
            out[:, c] = np.einsum("rpc,rc,p->r", arms, lever, w) * URAD
        return out

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        phi = self.bending_rad(spec, ctx, kin)
        axes = kin.rotation_axes(spec.joint)[:, :, list(BENDING_AXES)]  # (r, 3, 2) mm/rad
        out: FloatArray = np.einsum("rcu,ru->rc", axes, phi)[:, :, None]
        return out

    def label(self, spec: EffectSpec) -> str:
        return f"bending of link {spec.joint} under gravity"

    def to_parameters(
        self, spec: EffectSpec, values: FloatArray, n_joints: int
    ) -> dict[str, EffectValue]:
        return {
            "joint": float(spec.joint),
            "bending_ratio": float(values[0]),
            "moments": spec.names,
            "weighted_moment_urad": tuple(float(v) for v in spec.shape),
        }

    def from_parameters(
        self, params: Mapping[str, Any], n_joints: int
    ) -> tuple[EffectSpec, FloatArray]:
        allowed = {"joint", "bending_ratio", "moments", "weighted_moment_urad"}
        check_keys(params, allowed, self.kind)
        names = _names(params, self.kind)
        bad = [m for m in names if m not in moment_names(n_joints)]
        if bad or not names:
            what = f"unknown moment {bad[0]!r}" if bad else "'moments' is empty"
            raise EffectLibraryError(f"effect {self.kind!r}: {what}")
        w = param_vector(params, "weighted_moment_urad", self.kind, len(names))
        spec = EffectSpec(
            self.kind,
            joint=param_joint(params, self.kind, n_joints),
            names=names,
            shape=tuple(float(v) for v in w),
        )
        return spec, np.array([param_number(params, "bending_ratio", self.kind)])

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
    ) -> Evidence:
        phi = self.bending_rad(spec, ctx, kin)
        c = int(np.argmax(np.sqrt(np.mean(phi**2, axis=0))))
        return Evidence(
            x=np.degrees(phi[:, c] * float(values[0])),
            x_label=f"modelled bending of link {spec.joint} about its {'xy'[c]} axis (deg)",
            y_label=f"link {spec.joint} {'xy'[c]} rotation error (deg)",
            coordinate_mm=kin.rotation_axes(spec.joint)[:, :, BENDING_AXES[c]] * DEG,
        )


def bending_candidates(
    ctx: EffectContext,
    specs: Sequence[EffectSpec],
    values: Sequence[FloatArray],
    exclude: Collection[EffectSpec] = (),
) -> list[EffectSpec]:
    """The bending of every link the gravity term's moments bend, offered once the model
    ``specs`` (with ``values``, one array per spec) holds a gravity term in its physical
    form; none for a link whose bending is in the model or in ``exclude`` already."""
    gravity = [
        (s, v)
        for s, v in zip(specs, values, strict=True)
        if s.kind == "gravity_deflection" and s.parameter == "physical"
    ]
    if not gravity:
        return []
    spec, v = gravity[0]
    # the shared moments alone: a limit-form group's are weighted by its own reference
    keep = [i for i, m in enumerate(spec.names) if not (counterbalance_term(m) or group_moment(m))]
    names = tuple(spec.names[i] for i in keep)
    w = tuple(float(v[i]) for i in keep)
    taken = {s.joint for s in (*specs, *exclude) if s.kind == "link_bending"}
    kind = LinkBending()
    kin = ModelAtPoses.of(KinematicModel.from_description(ctx.description), ctx.data.q_rad)
    out = []
    for j in range(1, ctx.description.n_joints + 1):
        candidate = EffectSpec(kind.kind, joint=j, names=names, shape=w)
        if j in taken:
            continue
        phi = kind.bending_rad(candidate, ctx, kin)
        if float(np.ptp(phi)) > 0.0:
            out.append(candidate)
    return out
