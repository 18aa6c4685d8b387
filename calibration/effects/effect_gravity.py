"""The gravity effects: ``gravity_deflection`` (linear and physical forms, counterbalanced
joints) and ``gravity_compliance`` (from the description's mass model); see
:mod:`calibration.effects.effect_base` for the library."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.effects.effect_base import (
    DEG,
    URAD_PER_KNM,
    EffectContext,
    EffectKind,
    EffectSpec,
    Evidence,
    FloatArray,
    ModelAtPoses,
    check_keys,
    param_vector,
)
from calibration.errors import EffectLibraryError
from calibration.model.description import EffectValue
from calibration.model.gravity_regressor import (
    link_rotations,
    moment_names,
    raw_regressor,
)
from calibration.model.kinematics import KinematicModel


class GravityCompliance(EffectKind):
    kind = "gravity_compliance"
    description = "links and bearings after the grating ring give under gravity and payload"

    def parameter_names(self, spec: EffectSpec) -> tuple[str, ...]:
        return tuple(f"joint{j}_compliance_urad_per_knm" for j in spec.joints)

    def regressor(
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
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
        check_keys(params, {"compliance_urad_per_knm"}, self.kind)
        c = param_vector(params, "compliance_urad_per_knm", self.kind, n_joints)
        joints = tuple(range(1, n_joints + 1))
        return EffectSpec(self.kind, joints=joints), c

    def evidence(
        self,
        spec: EffectSpec,
        values: FloatArray,
        ctx: EffectContext,
        sel: slice,
        kin: ModelAtPoses,
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


def group_moment(name: str) -> tuple[tuple[int, ...], str] | None:
    """A moment of a group of the physical form's limit (:func:`group_moment_name`):
    ``"joints4+5+6.link5.mx"`` -> ((4, 5, 6), ``"link5.mx"``), ``"joint6.link6.mx"`` ->
    ((6,), ``"link6.mx"``); None for a shared moment (``"link5.mx"``), a counterbalance
    term or another name."""
    head, _, moment = name.partition(".")
    if counterbalance_term(name) is not None or "." not in moment:
        return None
    digits = head[6:].split("+") if head.startswith("joints") else [head[5:]]
    if not head.startswith("joint") or not all(d.isdigit() for d in digits):
        return None
    return tuple(int(d) for d in digits), moment


def group_moment_name(group: tuple[int, ...], moment: str) -> str:
    """The name of ``moment`` owned by the limit form's ``group`` of joints (a joint's own
    free block, named as the linear form's term, for a group of one)."""
    if len(group) == 1:
        return f"joint{group[0]}.{moment}"
    return "joints" + "+".join(str(j) for j in group) + f".{moment}"


def gravity_groups(spec: EffectSpec) -> tuple[tuple[int, ...], ...]:
    """The physical form's groups of joints sharing moments: first the joints sharing the
    plain-named moments (absent when every joint is in a named group), then each named
    group of the limit form (:class:`~calibration.effects.effect_shapes.PhysicalGravityFit`)."""
    named: list[tuple[int, ...]] = []
    for name in spec.names:
        gm = group_moment(name)
        if gm is not None and gm[0] not in named:
            named.append(gm[0])
    apart = {j for g in named for j in g}
    shared = tuple(j for j in spec.joints if j not in apart)
    return ((shared,) if shared else ()) + tuple(named)


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


def _moment_ok(name: str, n_joints: int) -> bool:
    """A physical form's moment name: a base moment, or one of a group's
    (:func:`group_moment`) with its joints in 1..n_joints."""
    gm = group_moment(name)
    if gm is None:
        return name in moment_names(n_joints)
    return gm[1] in moment_names(n_joints) and all(1 <= j <= n_joints for j in gm[0])


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

    def slot(self, spec: EffectSpec) -> tuple[str | int, ...]:
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
        # the joints of the limit form's named groups: they share no plain-named moment
        apart = {j for name in spec.names for j in (group_moment(name) or ((), ""))[0]}
        apart = apart if spec.parameter == "physical" else set()
        for p, name in enumerate(spec.names):
            cb = counterbalance_term(name)
            gm = group_moment(name) if spec.parameter == "physical" else None
            if cb is not None:
                j, f, k = cb
                out[:, j - 1, p] = (np.cos if f == "cos" else np.sin)(k * q[:, j - 1])
            elif gm is not None:  # a group's own moment loads its joints alone
                m = raw.index(gm[1])
                for j in gm[0]:
                    out[:, j - 1, p] = ratio.get(j, 1.0) * y[:, j - 1, m]
            elif spec.parameter == "physical":
                m = raw.index(name)
                for j, rho in ratio.items():
                    if j not in apart:  # a shared moment loads no joint of another group
                        out[:, j - 1, p] = rho * y[:, j - 1, m]
            else:
                j, moment = joint_moment(name, "gravity_deflection", n)
                out[:, j - 1, p] = y[:, j - 1, raw.index(moment)]
        return out

    def deflection_jacobian(
        self, spec: EffectSpec, ctx: EffectContext, kin: ModelAtPoses
    ) -> FloatArray:
        """``D`` ``(r, n, P)``: each joint's deflection per unit of each parameter (×1e-6
        rad for µrad values) at the poses of ``kin``.

        With a sweep reference in the data, joint j's row is less what j's map absorbed in
        its sweep (the reference with joint j at its reading): the deflection of every link
        i ≤ j there, turned into an angle about axis j by ``z_i·z_j`` (a rotation about a
        parallel upstream axis shows in j's circle one to one, about a perpendicular one
        it only tilts the circle). A term of joint j's own angle alone vanishes. The
        reference is one configuration ``(n,)`` for every joint or one per joint ``(n, n)``
        (row j: joint j's sweep configuration; the axes ``z`` are taken there).
        """
        d = self._plain(spec, ctx.gravity, kin.model, kin.q_rad)
        ref = ctx.data.sweep_reference
        if ref is None:
            return d
        n = kin.model.n_joints
        rows = np.broadcast_to(np.asarray(ref, dtype=float), (n, n))
        # each distinct configuration once (one for a single reference, as the (n,) form)
        configs, which = np.unique(rows, axis=0, return_inverse=True)
        z = link_rotations(kin.model, configs)[:, :, :, 2]  # (U, n, 3): axes at each
        seen = [np.tril(zu @ zu.T).T for zu in z]  # [u][i, j] = z_i·z_j for i ≤ j, at u
        scale = np.sqrt(np.mean(d * d, axis=0))  # (n, P) before the subtraction
        for j in range(n):
            qs = np.broadcast_to(rows[j], kin.q_rad.shape).copy()
            qs[:, j] = kin.q_rad[:, j]
            absorbed = self._plain(spec, ctx.gravity, kin.model, qs)
            at = seen[int(which.ravel()[j])]
            d[:, j] -= np.einsum("i,rip->rp", at[: j + 1, j], absorbed[:, : j + 1])
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
        kin: ModelAtPoses,
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
        self, spec: EffectSpec, ctx: EffectContext, sel: slice, kin: ModelAtPoses
    ) -> FloatArray:
        d = self.deflection_jacobian(spec, ctx, kin)  # (r, n, P)
        theta = kin.jacobian[:, :, 3 : 5 * d.shape[1] : 5]  # ∂TCP/∂θ_j, (r, 3, n)
        reg: FloatArray = np.einsum("rak,rkp->rap", theta, d) * URAD
        return reg

    def label(self, spec: EffectSpec) -> str:
        joints = ", ".join(str(j) for j in spec.joints)
        form = spec.parameter or "linear"
        groups = gravity_groups(spec) if form == "physical" else ()
        limit = "".join(
            f", joint{'s' if len(g) > 1 else ''} {'+'.join(str(j) for j in g)} apart"
            for g in groups[1:]
        )
        return f"gravity deflection (joints {joints}; {form} form{limit})"

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
            check_keys(params, {"form", "terms", "deflection_urad"}, self.kind)
            terms = _strings(params, "terms", self.kind)
            joints = sorted({joint_moment(t, self.kind, n_joints)[0] for t in terms})
            values = param_vector(params, "deflection_urad", self.kind, len(terms))
            return EffectSpec(self.kind, parameter="linear", joints=tuple(joints), names=terms), (
                values
            )
        keys = {"form", "joints", "compliance_ratio", "moments", "weighted_moment_urad"}
        check_keys(params, keys | {"counterbalance", "counterbalance_urad"}, self.kind)
        moments = _strings(params, "moments", self.kind)
        bad = [m for m in moments if not _moment_ok(m, n_joints)]
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
            cb_values = param_vector(params, "counterbalance_urad", self.kind, len(cb))
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
        ratios = param_vector(params, "compliance_ratio", self.kind, len(joints))
        values = param_vector(params, "weighted_moment_urad", self.kind, len(moments))
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
        kin: ModelAtPoses,
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
