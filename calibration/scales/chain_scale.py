"""Grating-scale calibration of every joint in chain order: no joint absorbs another's motion.

During one joint's sweep the others are not perfectly still: gear torsion and backlash
turn the upstream joints by tens of arc-seconds as the swept link's load changes. Their
gratings see it (they read the joint output rings), but a circle through the target on the
swept link credits all the target's motion to the swept joint. Here each stop's point is
first moved back through the kinematic chain:

    p⁰_k = R_{J−1}(−δ_{J−1,k}) ··· R_1(−δ_{1,k}) · p_k

with ``δ_ik`` joint i's angle from Home at stop k, read by its own grating through its own
counts → angle map, and ``R_i`` the rotation about joint i's axis as it stands with the
joints before it at Home, which is exactly what joint i's own sweep measured (the axis of
its fitted circle, oriented with the joint's positive sense). The joints are calibrated in
chain order 1, 2, …, n, so every upstream map and axis exists when a joint needs it; the
maps of the upstream joints depend only on joints further upstream, so one pass is the
fixed point (no iteration needed; the rotations are exact, the axes' own second-order
dependence on upstream δ ≈ 1e-4 rad is below the tracker's noise). Joints downstream of
the swept one do not move its target.

Without the other joints' readings (a ``sweep.csv`` without ``g1_counts..gN_counts``) this
is the pure circle fit of :mod:`calibration.scales.grating_scale`: the documented special case,
and the start of each joint's fit. Both are computed; the result carries the circle-only
residual beside the whole-chain one so a user sees what the chain removed.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import ScaleError
from calibration.model.description import RobotDescription
from calibration.model.gravity_regressor import base_moments
from calibration.scales.grating_scale import calibrate_joint
from calibration.scales.joint_scale_result import JointScaleResult
from calibration.scales.sweep_inputs import JointSweep, ScaleOptions

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class JointAxis:
    """A joint's axis in the tracker frame: unit ``direction`` (positive rotation sense by
    the right-hand rule) through ``point_mm``, both ``(3,)``."""

    joint: int
    direction: FloatArray
    point_mm: FloatArray

    @classmethod
    def of(cls, result: JointScaleResult) -> JointAxis:
        """The axis of a calibrated joint: its common circle's normal and centre."""
        c = result.circle
        return cls(result.joint, np.asarray(c.normal, float), np.asarray(c.centre_mm, float))

    def rotate(self, points_mm: ArrayLike, angle_rad: ArrayLike) -> FloatArray:
        """Points ``(S, 3)`` turned about this axis by ``angle_rad`` ``(S,)`` (Rodrigues)."""
        p = np.atleast_2d(np.asarray(points_mm, dtype=float)) - self.point_mm
        a = np.asarray(angle_rad, dtype=float)[:, None]
        k = self.direction
        rotated = p * np.cos(a) + np.cross(k, p) * np.sin(a) + np.outer(p @ k, k) * (1 - np.cos(a))
        moved: FloatArray = rotated + self.point_mm
        return moved


def undo_upstream(
    points_mm: ArrayLike, upstream: Sequence[tuple[JointAxis, FloatArray]]
) -> FloatArray:
    """Points ``(S, 3)`` with the upstream joints' rotations ``(axis, δ (S,) rad)`` taken
    out, joint 1 first (it was applied last)."""
    out = np.asarray(points_mm, dtype=float)
    for axis, delta in sorted(upstream, key=lambda u: u[0].joint):
        out = axis.rotate(out, -np.asarray(delta, dtype=float))
    return out


@dataclass(frozen=True)
class ChainCorrection:
    """What the chain removed from one joint's sweep."""

    joint: int
    upstream_joints: tuple[int, ...]  # joints whose motion was taken out
    max_upstream_arcsec: dict[int, float]  # largest |δ| of each during the sweep
    circle_only: JointScaleResult  # the pure circle fit on the same stops
    missing: tuple[int, ...] = ()  # upstream joints without a calibration (not corrected)
    #: RMS and largest modelled deflection after the rings taken out (None: none given):
    #: of the swept link itself, and the largest of each upstream link's
    own_deflection_arcsec: tuple[float, float] | None = None
    upstream_deflection_arcsec: dict[int, float] | None = None

    @property
    def circle_only_residual_arcsec(self) -> float:
        return self.circle_only.residual_rms_arcsec


@dataclass(frozen=True, eq=False)
class ScaleCampaignResult(Sequence[JointScaleResult]):
    """Every joint's calibration, in joint order, and what the chain removed per joint.

    A sequence of the joints' results (what the scale file and the report take)."""

    results: tuple[JointScaleResult, ...]
    chain: Mapping[int, ChainCorrection]

    def __iter__(self) -> Iterator[JointScaleResult]:
        return iter(self.results)

    def __len__(self) -> int:
        return len(self.results)

    @overload
    def __getitem__(self, index: int) -> JointScaleResult: ...
    @overload
    def __getitem__(self, index: slice) -> tuple[JointScaleResult, ...]: ...
    def __getitem__(self, index: int | slice) -> JointScaleResult | tuple[JointScaleResult, ...]:
        return self.results[index]

    def by_joint(self) -> dict[int, JointScaleResult]:
        return {r.joint: r for r in self.results}


def calibrate_scales(
    sweeps: Mapping[int, JointSweep],
    home_counts: Mapping[int, ArrayLike] | None = None,
    *,
    home_deg: Sequence[float] | None = None,
    limits_deg: Sequence[tuple[float, float]] | None = None,
    options: ScaleOptions | None = None,
    chain: bool = True,
    link_rotations_rad: Mapping[int, FloatArray] | None = None,
) -> ScaleCampaignResult:
    """Calibrate every swept joint in chain order (see the module docstring).

    ``home_deg`` and ``limits_deg`` (per joint, from the robot description) are needed
    only for a joint without Home returns. ``chain=False`` gives the pure circle fits.
    ``link_rotations_rad`` gives, per swept joint, the rotation ``(S, n)`` of every link
    after its ring at each stop that no grating sees (a modelled gravity deflection): it is
    taken out too, for the swept link as well, so the map is the strip's alone.
    """
    opt = options or ScaleOptions()
    done: dict[int, JointScaleResult] = {}
    corrections: dict[int, ChainCorrection] = {}
    for j in sorted(sweeps):
        sweep = sweeps[j]
        home = None if home_counts is None else home_counts.get(j)
        joint_home = None if home_deg is None else home_deg[j - 1]
        joint_limits = None if limits_deg is None else limits_deg[j - 1]
        circle_only = calibrate_joint(
            sweep, home, home_deg=joint_home, limits_deg=joint_limits, options=opt
        )
        upstream, missing, largest = _upstream(sweep, done) if chain else ([], (), {})
        unseen = None if link_rotations_rad is None else link_rotations_rad.get(j)
        if unseen is not None:
            upstream = _with_unseen(upstream, JointAxis.of(circle_only), np.asarray(unseen), j)
        if not upstream:
            done[j] = circle_only
            continue
        corrected = replace(sweep, points_mm=undo_upstream(sweep.points_mm, upstream))
        try:
            done[j] = calibrate_joint(
                corrected, home, home_deg=joint_home, limits_deg=joint_limits, options=opt
            )
        except ScaleError as exc:
            raise ScaleError(f"joint {j}: with the upstream joints taken out: {exc}") from exc
        note = _note([u for u in upstream if u[0].joint != j], largest, missing)
        if unseen is not None:
            note += f"; modelled deflection after the rings taken out (joints 1..{j})"
        done[j] = replace(done[j], notes=(*done[j].notes, note))
        corrections[j] = ChainCorrection(
            j,
            tuple(a.joint for a, _ in upstream if a.joint != j),
            largest,
            circle_only,
            missing,
            *_modelled_deflection_arcsec(unseen, j),
        )
    return ScaleCampaignResult(tuple(done[j] for j in sorted(done)), corrections)


def _with_unseen(
    upstream: list[tuple[JointAxis, FloatArray]], own_axis: JointAxis, unseen: FloatArray, j: int
) -> list[tuple[JointAxis, FloatArray]]:
    """The upstream joints' angles plus the rotations no grating sees ``unseen`` ``(S, n)``
    rad, and joint ``j``'s own axis with its link's: the swept link itself turns after its
    ring."""
    return [(a, d + unseen[:, a.joint - 1]) for a, d in upstream] + [(own_axis, unseen[:, j - 1])]


def _modelled_deflection_arcsec(
    unseen: FloatArray | None, j: int
) -> tuple[tuple[float, float] | None, dict[int, float] | None]:
    """The modelled deflection taken out of joint ``j``'s map: its own link's RMS and
    largest (″), and each upstream link's largest (None without a model)."""
    if unseen is None:
        return None, None
    arcsec = np.degrees(np.asarray(unseen, dtype=float)) * 3600.0
    own = (float(np.sqrt(np.mean(arcsec[:, j - 1] ** 2))), float(np.abs(arcsec[:, j - 1]).max()))
    return own, {i: float(np.abs(arcsec[:, i - 1]).max()) for i in range(1, j)}


def _upstream(
    sweep: JointSweep, done: Mapping[int, JointScaleResult]
) -> tuple[list[tuple[JointAxis, FloatArray]], tuple[int, ...], dict[int, float]]:
    """The calibrated upstream joints' axes and angles from Home at every stop."""
    if sweep.chain_counts is None:
        return [], (), {}
    out, missing, largest = [], [], {}
    for i in range(1, sweep.joint):
        r = done.get(i)
        if r is None:
            missing.append(i)
            continue
        delta = np.radians(r.scale.counts_to_angle_deg(sweep.chain_counts[:, i - 1]))
        out.append((JointAxis.of(r), delta))
        largest[i] = float(np.degrees(np.max(np.abs(delta)))) * 3600.0
    return out, tuple(missing), largest


def _note(
    upstream: Sequence[tuple[JointAxis, FloatArray]],
    largest: Mapping[int, float],
    missing: Sequence[int],
) -> str:
    moved = ", ".join(f"joint {i} up to {largest[i]:.1f}″" for i in sorted(largest))
    text = f"whole chain: the motion of the upstream joints taken out ({moved})"
    if missing:
        text += f"; joints {', '.join(map(str, missing))} uncalibrated, not taken out"
    return text


def with_load_notes(
    scales: ScaleCampaignResult, robot: RobotDescription, *, deflection_taken_out: bool
) -> ScaleCampaignResult:
    """Say, per joint, what of its map could be load rather than strip.

    A sweep alone cannot tell a strip's first harmonic (eccentricity) from the swept link's
    deflection under its own weight after the ring: both are a first harmonic of the joint's
    angle. Where gravity loads the joint (its row of the gravity regressor is not empty),
    the note says so, and whether the closed loop's modelled deflection was taken out of
    the sweeps (``twin run``). A declared counterbalance's torque depends on the joint's
    own angle alone: what it deflects is the same at every pose, no campaign can tell it
    from the strip, and it stays in the map (its non-linear terms may be that load).
    """
    base = base_moments(robot)
    loaded = set(base.loaded_joints)
    out = []
    for r in scales.results:
        notes = list(r.notes)
        j = r.joint
        if j in loaded and deflection_taken_out:
            notes.append(
                "load: the closed loop's modelled gravity deflection after the rings was taken "
                "out of this sweep; what depends on this joint's angle alone stays in the map"
            )
        elif j in loaded:
            notes.append(
                "load: gravity loads this joint in its sweep; its first harmonic (cyclic term) "
                "may be this link's deflection under its own weight as much as strip "
                "eccentricity (a sweep alone cannot tell; twin run separates them with the "
                "closed loop's gravity term)"
            )
        if robot.joints[j - 1].counterbalance:
            terms = [t for t in r.scale.terms if t in ("cyclic", "nonlinear")]
            notes.append(
                "load: the declared counterbalance's torque depends on this joint's angle "
                "alone; the deflection it causes after the ring stays in this map "
                + (f"(the kept {' and '.join(terms)} term(s) may be that load)" if terms else "")
            )
        out.append(replace(r, notes=tuple(notes)))
    return ScaleCampaignResult(tuple(out), scales.chain)
