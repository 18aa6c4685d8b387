"""Planning a measurement campaign: candidates in view, the best set, the shortest order.

1. **Candidates** (:func:`candidate_poses`): reflector positions drawn uniformly in the
   working region, the reflector's axis tilted from the line to the tracker by up to the
   acceptance cone less a margin, a random roll about it; every inverse-kinematics branch
   inside the joint limits (less a margin) and away from singularities is a candidate,
   kept when the reflector is in view and the arm clear of the floor and the obstacles
   at the pose and along the straight joint move from Home (:mod:`calibration.model.cell_geometry`).
2. **Identification set** (:func:`select_identification`): what the campaign must pin
   down is the identifiable geometry (:func:`calibration.identify.identifiability.analyze_model`)
   plus the closed loop's usual effects, with the loop's own regressors
   (:mod:`calibration.effects.effect_kinds`: the gravity deflection in the physical form
   the loop ends with, linearised (:func:`physical_form_columns`), each joint's cyclic
   error, the tracker's scale; :func:`loop_effects`). Each candidate's 3-row block of
   that Jacobian is column-scaled, reduced to the directions the candidates can observe
   at all, and weighted by the tracker's σ at its distance. The effects the loop cannot
   add from ``n_identify`` poses (:func:`loop_can_add`: the physical gravity form's 18
   parameters from fewer than 46 poses) are not fitted but left out (the gravity term
   then in its linear form), scaled to their prior. Start: D-optimal greedy selection (the O1 index,
   :func:`calibration.identify.pose_selection.select_poses`); then **I-optimal** exchange
   passes: swap a chosen pose for the candidate that most lowers the expected mean squared
   prediction error over the region (:mod:`calibration.plan.plan_criterion`: the fit's
   variance ``trace(W·M⁻¹)``, ``M`` the chosen poses' information plus the prior
   information of :func:`prior_sd` (Bayesian I-optimality), ``W`` the mean of the
   unweighted blocks' ``BᵀB`` over every candidate in view, the region where the robot
   works as a user measures it; plus the bias of the left-out effects the fit aliases),
   by rank-3 updates for every candidate at once.
3. **Validation set** (:func:`spread_validation`): farthest-point sampling of the
   reflector positions among the other candidates, from a seeded start; not optimised.
4. **Order** (:mod:`calibration.plan.travel_order`): a closed tour from Home; a leg takes
   ``max_j |Δq_j| / v_j`` (synchronous PTP at the joints' top speeds); nearest neighbour,
   then 2-opt until no move shortens it; measured forward then back (``passes`` 2, the
   default: every other pose of the tour on the way out, the rest on the way back), so a
   drift in time is not a smooth function of the pose.

Everything here is arrays in, a frozen result out; files are :mod:`calibration.cli.plan`'s.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec, ModelAtPoses
from calibration.effects.effect_candidates import gravity_candidate
from calibration.effects.effect_gravity import counterbalance_term
from calibration.effects.effect_kinds import regressor_matrix
from calibration.errors import PlanError
from calibration.identify.identifiability import analyze_model
from calibration.identify.pose_selection import select_poses
from calibration.model.cell_geometry import (
    VIEW_REASONS,
    CellGeometry,
    collision_codes,
    collision_reason,
    move_collision_codes,
    reflector_in_base,
    view_codes,
)
from calibration.model.description import DEFAULT_JOINT_SPEED_DEG_S, RobotDescription
from calibration.model.ik_results import JointLimits, SingularityMargins
from calibration.model.inverse_kinematics import solve_ik
from calibration.model.kinematics import (
    KinematicModel,
    identification_jacobian,
)
from calibration.model.numeric_ik import jacobian_conditioning, multi_start_ik
from calibration.model.pieper_closed_form import has_spherical_approximation
from calibration.plan.plan_criterion import (
    DesignProblem,
    criterion_value,
    drift_bias,
    exchange,
)
from calibration.plan.travel_order import DriftCost, TravelOrder, travel_order

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Why a drawn pose gives no candidate (the report's "Poses dropped"), two of the reasons.
UNREACHABLE = "out of the arm's reach"
NEAR_SINGULARITY = "IK branch near a singularity"
#: Batches of drawn poses after which a region none of whose poses the arm reaches is
#: given up (a numeric inverse kinematics spends ~0.5 s a batch finding nothing).
_GIVE_UP_BATCHES = 4


@dataclass(frozen=True)
class PlanSettings:
    """How a campaign is planned (angles in degrees)."""

    n_identify: int = 50
    n_validate: int = 30
    #: candidate poses in view to choose from: 20 000 lowered the planned error 2.5–6 %
    #: against 5000 on every truth measured (docs/planning.md, "From 20 000 candidates")
    n_candidates: int = 20000
    seed: int = 1
    criterion: Literal["I", "D"] = "I"
    exchange_passes: int = 6
    limit_margin_deg: float = 2.0  # kept inside every joint limit
    cone_margin_deg: float = 5.0  # the reflector's axis at most cone − this off the beam
    range_margin_mm: float = 150.0  # inside the tracker's range by this (the station is taped)
    clearance_margin_mm: float = 20.0  # links kept this much farther from floor and obstacles
    #: the loop's effects the criterion covers besides the geometry (:func:`loop_effects`)
    effects: tuple[str, ...] = ("gravity", "harmonic", "scale")
    wrist_margin_deg: float = 10.0  # q5 at least this far from 0 (axes 4 and 6 apart)
    elbow_margin_deg: float = 10.0  # forearm this far from stretched or folded
    #: an arm without a spherical wrist (numeric IK): starts per drawn pose, and the least
    #: conditioning of its Jacobian (:func:`calibration.model.numeric_ik.jacobian_conditioning`;
    #: 0.01 flags about as many random joint vectors of the presets as the 10° margins)
    ik_starts: int = 4
    min_conditioning: float = 0.01
    tracker_mpe_um: float = 15.0  # the tracker's MPE: ±(a + b·distance), taken as 2 σ
    tracker_mpe_um_per_m: float = 6.0
    #: 2: the tour forward then back, a drift in time kept apart from the pose; 1: one
    #: pass, the shortest tour (:mod:`calibration.plan.travel_order`)
    passes: int = 2


@dataclass(frozen=True, eq=False)
class Candidates:
    """Candidate poses in view and clear: joint vectors ``q_rad`` ``(N, n)``, reflector
    ``tcp_mm`` ``(N, 3)`` (base frame); ``dropped``: why the others went, with counts."""

    q_rad: FloatArray
    tcp_mm: FloatArray
    tried: int  # reflector poses drawn
    dropped: dict[str, int] = field(default_factory=dict)
    ik: str = "closed form"  # how the drawn poses were solved (the report states it)


@dataclass(frozen=True, eq=False)
class Observability:
    """The candidates' observability blocks and what they stand for.

    ``weighted`` ``(N, 3, r)``: reduced, σ-weighted blocks (information ``Σ HᵢᵀHᵢ``);
    ``plain`` ``(N, 3, r)``: the same unweighted (mm per unit reduced parameter);
    ``to_scaled`` ``(p, r)``: reduced -> scaled parameters; ``scale`` ``(p,)``: the
    scaled parameters' units; ``names`` ``(p,)``; ``prior_sd`` ``(p,)``: what is known
    before measuring (:func:`prior_sd`), 1 σ per scaled parameter."""

    weighted: FloatArray
    plain: FloatArray
    to_scaled: FloatArray
    scale: FloatArray
    names: tuple[str, ...]
    prior_sd: FloatArray
    #: ``(N, 3, q)`` the effects the loop cannot add from ``n_identify`` poses
    #: (:func:`loop_can_add`), each column scaled to its prior 1 σ; σ-weighted and plain
    left_out_weighted: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 0)))
    left_out_plain: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 0)))
    left_out: tuple[str, ...] = ()  # the left-out effects' labels
    unseen: tuple[str, ...] = ()  # effect parameters that move the reflector at no candidate

    @cached_property
    def prior(self) -> FloatArray:
        """``(r, r)`` the prior information of the reduced parameters, restricted to the
        directions the candidates observe (the design's; :func:`parameter_sigmas` takes
        each parameter's own)."""
        basis = self.to_scaled
        out: FloatArray = basis.T @ (basis / self.prior_sd[:, None] ** 2)
        return out


@dataclass(frozen=True, eq=False)
class Selection:
    """The identification poses chosen (rows of the candidates) and the criteria."""

    indices: IntArray
    criterion: str
    d_index: float  # O1 of the chosen set
    i_value_mm2: float  # expected mean squared prediction error over the region (mm²)
    exchanges: int
    bias_mm2: float = 0.0  # its part from the left-out effects (plan_criterion)


def joint_speeds_rad_s(description: RobotDescription) -> FloatArray:
    """Each joint's top speed ``(n,)`` rad/s (:data:`DEFAULT_JOINT_SPEED_DEG_S` where the
    description states none)."""
    return np.radians([j.max_speed_deg_s or DEFAULT_JOINT_SPEED_DEG_S for j in description.joints])


def _aligning(a: FloatArray) -> FloatArray:
    """A rotation ``(3, 3)`` taking the unit vector ``a`` to +z."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(a, z), float(a @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    rot: FloatArray = np.eye(3) + k + k @ k / (1.0 + c)
    return rot


def _target_poses(
    geometry: CellGeometry, n: int, rng: np.random.Generator, tilt_max_rad: float
) -> FloatArray:
    """``n`` reflector poses ``(n, 4, 4)`` (flange orientation, reflector origin) in the
    region, the reflector's axis within ``tilt_max_rad`` of the line to the station."""
    p = rng.uniform(geometry.region_lo, geometry.region_hi, size=(n, 3))
    d = geometry.station_mm - p
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(d, u)
    tilt = tilt_max_rad * np.sqrt(rng.uniform(0.0, 1.0, n))  # uniform over the cap
    az = rng.uniform(-np.pi, np.pi, n)
    z = np.cos(tilt)[:, None] * d + np.sin(tilt)[:, None] * (
        np.cos(az)[:, None] * u + np.sin(az)[:, None] * w
    )
    roll = rng.uniform(-np.pi, np.pi, n)
    x0 = np.cross(z, helper)
    x0 /= np.linalg.norm(x0, axis=1, keepdims=True)
    y0 = np.cross(z, x0)
    x = np.cos(roll)[:, None] * x0 + np.sin(roll)[:, None] * y0
    y = np.cross(z, x)
    frame = np.stack([x, y, z], axis=2)  # columns: the reflector frame, axis = z
    t = np.zeros((n, 4, 4))
    t[:, :3, :3] = frame @ _aligning(geometry.axis_flange)
    t[:, :3, 3] = p
    t[:, 3, 3] = 1.0
    return t


def with_margins(geometry: CellGeometry, settings: PlanSettings) -> CellGeometry:
    """The cell as the planner checks it: the range narrowed and the links thickened by
    the settings' margins (the planned poses must hold on the real cell too)."""
    return replace(
        geometry,
        min_range_mm=geometry.min_range_mm + settings.range_margin_mm,
        max_range_mm=geometry.max_range_mm - settings.range_margin_mm,
        link_radius_mm=geometry.link_radius_mm + settings.clearance_margin_mm,
    )


def candidate_poses(
    description: RobotDescription,
    geometry: CellGeometry,
    settings: PlanSettings,
    rng: np.random.Generator,
) -> Candidates:
    """Up to ``settings.n_candidates`` candidates in view and clear (see the module text),
    drawn in batches until there are enough or 40 batches are spent. Raises
    :class:`PlanError` when the region has no reachable pose or the tracker sees none.
    Long for counting every reason a pose is dropped, which the report lists."""
    model = KinematicModel.from_description(description)
    limits = JointLimits.from_description(description)
    margin = np.radians(settings.limit_margin_deg)
    inner = JointLimits(limits.lower_rad + margin, limits.upper_rad - margin)
    home = np.radians(description.home)
    tilt = np.radians(max(geometry.cone_half_angle_deg - settings.cone_margin_deg, 0.0))
    margins = SingularityMargins(
        elbow_rad=float(np.radians(settings.elbow_margin_deg)),
        wrist_rad=float(np.radians(settings.wrist_margin_deg)),
    )
    dropped: Counter[str] = Counter()
    found: list[FloatArray] = []
    have = tried = 0
    batch = max(512, settings.n_candidates // 4)
    closed_form = has_spherical_approximation(model)
    for _ in range(40):
        poses = _target_poses(geometry, batch, rng, tilt)
        tried += batch
        if closed_form:
            q = _closed_form_solutions(model, poses, inner, home, margins, settings, dropped)
        else:
            q = _numeric_solutions(model, poses, inner, home, settings, dropped, rng)
        q = q[_first_of_each(q)]
        q = _keep(model, with_margins(geometry, settings), q, home, dropped)
        found.append(q)
        have += len(q)
        if have >= settings.n_candidates:
            break
        if tried >= _GIVE_UP_BATCHES * batch and dropped[UNREACHABLE] == tried:
            break  # nothing in reach so far: more draws would only take longer to say so
    q_all = np.concatenate(found)
    # the branches of one drawn pose come together: shuffled, any first k are random poses
    q_all = q_all[rng.permutation(len(q_all))][: settings.n_candidates]
    if len(q_all) == 0:
        reachable = tried - dropped[UNREACHABLE]
        if reachable == 0 or dropped[NEAR_SINGULARITY] + sum(
            v for k, v in dropped.items() if k.startswith("IK branch outside")
        ) == sum(v for k, v in dropped.items() if k != UNREACHABLE):
            raise PlanError(
                f"region {_box(geometry)}: no pose the arm reaches within its joint limits "
                f"(of {tried} drawn); move the region into the arm's reach"
            )
        raise PlanError(
            f"tracker at {_vec(geometry.station_mm)} mm sees no pose in region {_box(geometry)} "
            f"(of {tried} drawn: {_reasons(dropped)})"
        )
    pos, _ = reflector_in_base(model, geometry, q_all)
    ik = "closed form" if closed_form else f"numeric, {settings.ik_starts} starts per drawn pose"
    return Candidates(q_rad=q_all, tcp_mm=pos, tried=tried, dropped=dict(dropped), ik=ik)


def _closed_form_solutions(
    model: KinematicModel,
    poses: FloatArray,
    inner: JointLimits,
    home: FloatArray,
    margins: SingularityMargins,
    settings: PlanSettings,
    dropped: Counter[str],
) -> FloatArray:
    """Every closed-form branch of the TCP ``poses`` ``(B, 4, 4)`` inside ``inner`` and away
    from the singularities, ``(M, 6)`` rad; the others counted in ``dropped``."""
    ik = solve_ik(
        model, poses, frame="base", target="tcp", limits=inner, q_current_rad=home,
        margins=margins,
    )  # fmt: skip
    reach = ik.reachable
    dropped[UNREACHABLE] += int(np.count_nonzero(~reach.any(axis=1)))
    out_limits = reach & ~ik.within_limits
    dropped[_outside_limits(settings)] += int(np.count_nonzero(out_limits))
    sing = ik.valid & ik.singular
    dropped[NEAR_SINGULARITY] += int(np.count_nonzero(sing))
    q: FloatArray = ik.solutions_rad[ik.valid & ~ik.singular]
    return q


def _numeric_solutions(
    model: KinematicModel,
    poses: FloatArray,
    inner: JointLimits,
    home: FloatArray,
    settings: PlanSettings,
    dropped: Counter[str],
    rng: np.random.Generator,
) -> FloatArray:
    """For an arm without a spherical wrist: the TCP ``poses`` ``(B, 4, 4)`` solved from
    ``settings.ik_starts`` starts each (:func:`calibration.model.numeric_ik.multi_start_ik`),
    kept inside ``inner`` and with the Jacobian's conditioning at least
    ``settings.min_conditioning``, ``(M, 6)`` rad; the others counted in ``dropped``."""
    rot = poses[:, :3, :3]
    pos = poses[:, :3, 3] - rot @ model.tool_mm
    ik = multi_start_ik(
        model, rot, pos, inner, rng, n_starts=settings.ik_starts, reference_rad=home
    )
    dropped[UNREACHABLE] += int(np.count_nonzero(~ik.converged.any(axis=1)))
    out_limits = ik.converged & ~ik.within_limits
    dropped[_outside_limits(settings)] += int(np.count_nonzero(out_limits))
    q = ik.solutions_rad[ik.within_limits]
    singular = jacobian_conditioning(model, q) < settings.min_conditioning
    dropped[NEAR_SINGULARITY] += int(np.count_nonzero(singular))
    kept: FloatArray = q[~singular]
    return kept


def _outside_limits(settings: PlanSettings) -> str:
    return f"IK branch outside the joint limits (less {settings.limit_margin_deg:g}°)"


def _first_of_each(q: FloatArray) -> NDArray[np.bool_]:
    """Drop exact duplicates (a branch that coincides with another)."""
    _, idx = np.unique(np.round(q, 9), axis=0, return_index=True)
    keep = np.zeros(len(q), dtype=bool)
    keep[idx] = True
    return keep


def _keep(
    model: KinematicModel,
    geometry: CellGeometry,
    q: FloatArray,
    home: FloatArray,
    dropped: Counter[str],
) -> FloatArray:
    """The joint vectors in view and clear, at the pose and along the move from Home."""
    pos, axis = reflector_in_base(model, geometry, q)
    view = view_codes(geometry, pos, axis)
    for code, why in VIEW_REASONS.items():
        dropped[why] += int(np.count_nonzero(view == code))
    q = q[view == 0]
    coll = collision_codes(model, geometry, q)
    for code in np.unique(coll[coll != 0]).tolist():
        dropped[collision_reason(geometry, code)] += int(np.count_nonzero(coll == code))
    q = q[coll == 0]
    move = move_collision_codes(model, geometry, home, q)
    for code in np.unique(move[move != 0]).tolist():
        why = f"move from Home: {collision_reason(geometry, code)}"
        dropped[why] += int(np.count_nonzero(move == code))
    kept: FloatArray = q[move == 0]
    return kept


def _vec(v: FloatArray) -> str:
    return "(" + ", ".join(f"{x:.0f}" for x in v) + ")"


def _box(geometry: CellGeometry) -> str:
    return f"{_vec(geometry.region_lo)}..{_vec(geometry.region_hi)} mm"


def _reasons(dropped: Counter[str] | dict[str, int]) -> str:
    items = sorted(((v, k) for k, v in dropped.items() if v), reverse=True)
    return "; ".join(f"{k}: {v}" for v, k in items)


def tracker_sigma_mm(settings: PlanSettings, distance_mm: FloatArray) -> FloatArray:
    """The tracker's 1 σ per axis (mm) at ``distance_mm`` ``(N,)`` (MPE taken as 2 σ)."""
    sigma: FloatArray = (
        1e-3 * (settings.tracker_mpe_um + settings.tracker_mpe_um_per_m * distance_mm / 1000.0) / 2
    )
    return sigma


def observability(
    description: RobotDescription,
    geometry: CellGeometry,
    q_rad: FloatArray,
    settings: PlanSettings,
) -> Observability:
    """The candidates' blocks for the identifiable geometry and the loop's effects: those
    the loop can add from ``settings.n_identify`` poses fitted, the others left out."""
    model = KinematicModel.from_description(description)
    analysis = analyze_model(model, q_rad)
    tcp, jac = identification_jacobian(model, q_rad)
    geo = jac[:, :, analysis.free]
    names = [n for n, f in zip(analysis.parameter_names, analysis.free, strict=True) if f]
    ctx = EffectContext(description, EffectData(q_rad))
    kin = ModelAtPoses(model, q_rad, tcp, jac)
    specs = loop_effects(ctx, settings.effects)
    effects, effect_names, kinds, left = _fitted_effects(ctx, kin, specs, settings, geo.shape[2])
    # an effect that moves the reflector at no candidate (a cyclic error of joint 6 with
    # the reflector on its axis) is not observable here: its column is rounding noise
    seen = _column_rms(effects) > _DEAD_COLUMN * float(np.max(_column_rms(geo), initial=1.0))
    effects = effects[:, :, seen]
    names += [n for n, s in zip(effect_names, seen, strict=True) if s]
    unseen = tuple(n for n, s in zip(effect_names, seen, strict=True) if not s)
    kinds = [k for k, s in zip(kinds, seen, strict=True) if s]
    full = np.concatenate([geo, effects], axis=2)
    scale = _column_rms(full)
    scaled = full / scale
    gram = np.einsum("nip,niq->pq", scaled, scaled)
    ev, vec = np.linalg.eigh(gram)
    keep = ev > 1e-8 * ev[-1]
    basis = vec[:, keep]  # (p, r): directions the candidates observe
    plain = scaled @ basis
    dist = np.linalg.norm(
        reflector_in_base(model, geometry, q_rad)[0] - geometry.station_mm, axis=1
    )
    sigma = tracker_sigma_mm(settings, dist)[:, None, None]
    # in scaled units. An effect's value goes through ``scale`` too, so for a fitted
    # effect it acts in its parameter's own unit (µrad, °, ppm), not as a TCP effect in
    # mm: gravity moments and the tracker's scale all but fixed, a cyclic error's terms
    # 0.03° (0.006–0.5 mm at the TCP), a joint's compliance column free. The plans
    # measured in docs/planning.md are made so; the priors read as TCP mm measured worse
    # there (docs/planning.md, "What is left")
    sd = prior_sd(names, len(geo[0, 0]), kinds) * scale
    out = regressor_matrix(left, ctx, slice(0, len(q_rad)), kin)
    # a left-out effect as large as its prior says at the TCP, spread over its columns
    out_sd = np.concatenate(
        [np.full(len(sp.parameter_names()), PRIOR_EFFECT_MM[sp.kind])
         / np.sqrt(len(sp.parameter_names())) for sp in left]
        or [np.zeros(0)]
    )  # fmt: skip
    out_rms = _column_rms(out)
    out_sd = np.where(out_rms > _DEAD_COLUMN * float(np.max(scale)), out_sd, 0.0)
    out_plain = out / out_rms * out_sd
    return Observability(
        plain / sigma, plain, basis, scale, tuple(names), sd,
        out_plain / sigma, out_plain, tuple(sp.label for sp in left), unseen,
    )  # fmt: skip


def _fitted_effects(
    ctx: EffectContext,
    kin: ModelAtPoses,
    specs: list[EffectSpec],
    settings: PlanSettings,
    n_geometry: int,
) -> tuple[FloatArray, list[str], list[str], list[EffectSpec]]:
    """The columns ``(N, 3, k)`` of the effects ``specs`` the loop can add from
    ``settings.n_identify`` poses beside ``n_geometry`` parameters (the gravity term in
    its physical form, :func:`physical_form_columns`), their names and kinds (one per
    column); the specs left out (the gravity term in its linear form)."""
    linear = [sp for sp in specs if sp.kind == "gravity_deflection"]
    gravity = physical_form_columns(ctx, kin, linear[0]) if linear else None

    def count(sp: EffectSpec) -> int:
        if sp.kind == "gravity_deflection" and gravity is not None:
            return len(gravity[1])
        return len(sp.parameter_names())

    fitted = [sp for sp in specs if loop_can_add(count(sp), settings.n_identify, n_geometry)]
    left = [sp for sp in specs if sp not in fitted]
    plain = [sp for sp in fitted if sp.kind != "gravity_deflection"]
    columns = regressor_matrix(plain, ctx, slice(0, len(kin.q_rad)), kin)
    names = [f"{sp.label}: {p}" for sp in plain for p in sp.parameter_names()]
    kinds = [sp.kind for sp in plain for _ in sp.parameter_names()]
    if gravity is not None and linear[0] in fitted:
        columns = np.concatenate([columns, gravity[0]], axis=2)
        names += [f"gravity deflection (physical form, linearised): {p}" for p in gravity[1]]
        kinds += ["gravity_deflection"] * len(gravity[1])
    return columns, names, kinds, left


#: A column whose rms is below this fraction of the geometry's largest moves nothing.
_DEAD_COLUMN = 1e-9


def _column_rms(blocks: FloatArray) -> FloatArray:
    """Each column's rms over the blocks ``(N, 3, p)`` (1 where a column is all zero)."""
    rms = np.sqrt(np.mean(blocks**2, axis=(0, 1)))
    rms[rms == 0] = 1.0
    out: FloatArray = rms
    return out


def loop_can_add(n_parameters: int, m: int, n_model: int) -> bool:
    """Whether the closed loop can add an effect of ``n_parameters`` from ``m`` poses
    (``n_model`` parameters fitted besides). The loop adds a candidate whose
    cross-validated gain (the held-out SSE drop in units of the current residual
    variance) beats ``ln(3m)`` per parameter (:mod:`calibration.effects.closed_loop`); that
    gain hardly exceeds the residual's degrees of freedom, ``3m − n_model −
    n_parameters``, which it approaches when the effect dominates the residual. The
    gravity term counts in its physical form (18 parameters on the kr500, the loop scores
    it on its own count): beside 27 geometric ones it can be added from 46 poses (its
    linear form's 34 would need ~85)."""
    return n_parameters * float(np.log(3 * m)) < 3 * m - n_model - n_parameters


#: What a user knows of the parameters before measuring (1 σ): a nominal description
#: is this far from a real arm (lengths, angles), the base guess and the tool this far
#: from the truth; an effect this large at the TCP (mm: a gravity deflection of a
#: tenth of a mm, a cyclic error of 30 µm, a tracker scale error of 20 ppm at 3 m) when
#: it is left out; a fitted effect's value acts in its own unit (:func:`observability`).
PRIOR_LENGTH_MM = 0.5
PRIOR_ANGLE_DEG = 0.05
PRIOR_BASE_MM = 50.0
PRIOR_BASE_DEG = 1.0
PRIOR_TOOL_MM = 1.0
PRIOR_EFFECT_MM = {"gravity_deflection": 0.1, "joint_harmonic": 0.03, "instrument_scale": 0.06}


def prior_sd(names: list[str], n_geometry: int, kinds: list[str]) -> FloatArray:
    """The prior 1 σ ``(p,)`` of the parameters ``names`` (geometry first, in mm or rad;
    then the effects' parameters, of the effect kinds ``kinds``, one per parameter, as the
    TCP effect of a scaled column, mm)."""
    sd = []
    for name in names[:n_geometry]:
        if name.startswith("base."):
            sd.append(np.radians(PRIOR_BASE_DEG) if name.endswith("_rad") else PRIOR_BASE_MM)
        elif name.startswith("tool."):
            sd.append(PRIOR_TOOL_MM)
        else:
            sd.append(np.radians(PRIOR_ANGLE_DEG) if name.endswith("_rad") else PRIOR_LENGTH_MM)
    out = np.array(sd, dtype=float)
    effect = [PRIOR_EFFECT_MM[kind] for kind in kinds]
    return np.concatenate([out, np.array(effect, dtype=float)])


#: The cyclic orders a plan designs for: the low ones a joint's gear and grating usually
#: show. The loop scans higher orders too (effect_candidates.harmonic_orders), but a design
#: spread over 24 orders per joint would spend its poses on terms few arms have.
PLANNED_HARMONIC_ORDERS = (1, 2, 3)


def loop_effects(ctx: EffectContext, which: tuple[str, ...]) -> list[EffectSpec]:
    """The closed loop's usual effects a campaign must pin down with the geometry: the
    gravity deflection (linear form, counterbalance terms included), each joint's
    cyclic error (orders :data:`PLANNED_HARMONIC_ORDERS`) and the
    tracker's scale. Time terms and lost motion depend on the order and the clock, not
    on the poses chosen, and are left out. ``which``: of "gravity", "harmonic", "scale"."""
    specs: list[EffectSpec] = []
    gravity = gravity_candidate(ctx)
    if gravity is not None and "gravity" in which:
        specs.append(gravity)
    for j in range(1, ctx.description.n_joints + 1):
        if "harmonic" in which:
            specs += [
                EffectSpec("joint_harmonic", joint=j, order=k) for k in PLANNED_HARMONIC_ORDERS
            ]
    if "scale" in which:
        specs.append(EffectSpec("instrument_scale"))
    return specs


def physical_form_columns(
    ctx: EffectContext, kin: ModelAtPoses, linear: EffectSpec
) -> tuple[FloatArray, tuple[str, ...]]:
    """The gravity term's physical form (what the closed loop fits once gravity is in,
    :mod:`calibration.effects.gravity_form`), linearised for the design: its columns
    ``(N, 3, b + c + J − 1)`` and their names. The form ``Δθ_j = ρ_j·Σ_k Ŷ_jk·w_k`` is
    bilinear; at a guess of equal compliance ratios (ρ = 1: the planner knows no
    stiffness) its derivatives are the shared moments' columns ``Σ_j Ŷ_jk`` (b), the
    counterbalance terms of the ``linear`` candidate (c, fitted freely as the loop does),
    and one column per loaded joint but the reference, the joint turned in proportion to
    its gravity torque by the description's masses (``ρ_j``; the reference joint, whose
    column moves the TCP most, has ρ = 1). A description without masses has no torque to
    turn a joint by: those columns are zero and drop out with the directions no
    candidate observes."""
    base = ctx.base_moments
    own = tuple(n for n in linear.names if counterbalance_term(n) is not None)
    joints = base.loaded_joints
    spec = EffectSpec(
        "gravity_deflection", parameter="physical", joints=joints, names=base.names + own,
        shape=(1.0,) * len(joints),
    )  # fmt: skip
    shared = regressor_matrix([spec], ctx, slice(0, len(kin.q_rad)), kin)
    tau = ctx.torques_nmm  # (N, n)
    turned = np.stack([kin.joint_axis(j) * tau[:, None, j - 1] for j in joints], axis=2)
    reference = int(np.argmax(np.sqrt(np.mean(turned**2, axis=(0, 1)))))
    ratios = [k for k in range(len(joints)) if k != reference]
    # a joint's column is its compliance (rad per N·mm) times the torque: ρ_j up to the
    # reference's compliance, which no plan knows
    names = spec.parameter_names() + tuple(
        f"joint{joints[k]}.compliance_rad_per_nmm" for k in ratios
    )
    return np.concatenate([shared, turned[:, :, ratios]], axis=2), names


def design_problem(obs: Observability) -> DesignProblem:
    """The criterion's arrays (:mod:`calibration.plan.plan_criterion`) over every candidate
    in view: the region where the robot works, as a user measures it."""
    n = len(obs.plain)
    w = np.einsum("nip,niq->pq", obs.plain, obs.plain) / n
    x = np.einsum("nip,niq->pq", obs.plain, obs.left_out_plain) / n
    z = float(np.sum(obs.left_out_plain**2)) / n
    return DesignProblem(obs.weighted, obs.left_out_weighted, w, x, z, obs.prior)


def select_identification(obs: Observability, k: int, settings: PlanSettings) -> Selection:
    """``k`` identification poses by the settings' criterion (see the module text)."""
    h = obs.weighted
    n = h.shape[0]
    if k > n:
        raise PlanError(f"--poses {k}: only {n} candidate poses are in view and clear")
    problem = design_problem(obs)
    chosen = [int(i) for i in select_poses(h, k, index="O1", exchange_passes=0).indices]
    exchanges = 0
    if settings.criterion == "I":
        exchanges = exchange(problem, chosen, settings.exchange_passes)
    idx = np.array(chosen, dtype=np.intp)
    taken = h[idx]
    info = np.einsum("nip,niq->pq", taken, taken) + obs.prior
    s = np.sqrt(np.clip(np.linalg.eigvalsh(info), 0, None))
    d_index = float(np.exp(np.mean(np.log(s))) / np.sqrt(k))
    value = criterion_value(problem, idx)
    return Selection(idx, settings.criterion, d_index, value.total_mm2, exchanges, value.bias_mm2)


def parameter_sigmas(obs: Observability, indices: IntArray) -> FloatArray:
    """Predicted 1 σ ``(p,)`` of each parameter (its own units: mm, rad, or a gravity
    term's): the posterior's, every parameter's prior (``obs.prior_sd``) beside the chosen
    poses' information along the directions they observe. Where the poses see only a sum
    of parameters (joint 2's cyclic error of order 1 and the gravity term's link-2
    moments both turn joint 2 as cos/sin q2), the data pin the sum and each part's prior
    the split; the design's prior on the observed directions alone (``obs.prior``) held
    the loosely known part as fixed as the tight one and printed its σ."""
    h = obs.weighted[indices]
    info = obs.to_scaled @ np.einsum("nip,niq->pq", h, h) @ obs.to_scaled.T
    ev, vec = np.linalg.eigh(info + np.diag(1.0 / obs.prior_sd**2))
    cov_scaled = (vec / np.maximum(ev, 1e-15 * ev[-1])) @ vec.T  # a free, unseen one: huge
    sig: FloatArray = np.sqrt(np.clip(np.diag(cov_scaled), 0, None)) / obs.scale
    return sig


def spread_validation(
    tcp_mm: FloatArray, k: int, exclude: IntArray, rng: np.random.Generator
) -> IntArray:
    """``k`` rows of ``tcp_mm`` ``(N, 3)`` spread over the region (farthest-point
    sampling from a random start), none of ``exclude``."""
    pool = np.setdiff1d(np.arange(len(tcp_mm)), exclude)
    if k > len(pool):
        raise PlanError(
            f"--validate {k}: only {len(pool)} candidate poses in view are left for validation"
        )
    if k == 0:
        return np.empty(0, dtype=np.intp)
    pts = tcp_mm[pool]
    chosen = [int(rng.integers(len(pool)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for _ in range(k - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
    out: IntArray = pool[np.array(chosen)]
    return out


@dataclass(frozen=True, eq=False)
class CampaignPlan:
    """A planned campaign: ``q_rad`` ``(N + M, n)`` in travel order, ``is_identify``
    ``(N + M,)``, and how it was chosen."""

    q_rad: FloatArray
    is_identify: NDArray[np.bool_]
    candidates: Candidates
    selection: Selection
    travel: TravelOrder
    parameter_names: tuple[str, ...]
    parameter_sigma: FloatArray  # (p,) predicted 1 σ, the planned identification set
    random_parameter_sigma: FloatArray  # (p,) the same for N random candidates
    random_i_value_mm2: float  # the I criterion of N random candidates
    left_out: tuple[str, ...] = ()  # effects the criterion counts as bias (not fitted)
    unseen: tuple[str, ...] = ()  # effect parameters no candidate observes (not designed for)


def order_drift(problem: DesignProblem, identify: IntArray, n: int) -> DriftCost:
    """The drift's bias (:func:`drift_bias`) of an order of the plan's ``n`` poses (rows:
    the identification poses ``identify`` first, then the validation poses), a pose's time
    its place in the order (the dwell, not the move, takes most of a pose's time)."""
    bias = drift_bias(problem, identify)

    def cost(order: IntArray) -> float:
        t = np.empty(n)
        t[order] = np.arange(n) / max(n - 1, 1)
        return bias(t[: len(identify)])

    return cost


def plan_campaign(
    description: RobotDescription, geometry: CellGeometry, settings: PlanSettings
) -> CampaignPlan:
    """The whole plan (module text); the same settings and seed give the same plan."""
    rng = np.random.default_rng([settings.seed, 30])
    cands = candidate_poses(description, geometry, settings, rng)
    if settings.n_identify + settings.n_validate > len(cands.q_rad):
        raise PlanError(
            f"--poses {settings.n_identify} + --validate {settings.n_validate}: only "
            f"{len(cands.q_rad)} candidate poses are in view and clear "
            f"(of {cands.tried} drawn: {_reasons(cands.dropped)})"
        )
    obs = observability(description, geometry, cands.q_rad, settings)
    sel = select_identification(obs, settings.n_identify, settings)
    val = spread_validation(cands.tcp_mm, settings.n_validate, sel.indices, rng)
    rows = np.concatenate([sel.indices, val])
    model = KinematicModel.from_description(description)
    home = np.radians(description.home)
    is_id = np.zeros(len(rows), dtype=bool)
    is_id[: len(sel.indices)] = True
    speeds = joint_speeds_rad_s(description)
    problem = design_problem(obs)
    travel = travel_order(
        cands.q_rad[rows], home, speeds, rng, settings.passes, is_id.astype(int),
        order_drift(problem, sel.indices, len(rows)),
    )  # fmt: skip
    q = cands.q_rad[rows][travel.order]
    ends = np.vstack([home, q, home])
    legs = move_collision_codes(model, with_margins(geometry, settings), ends[:-1], ends[1:])
    travel = replace(travel, via_home=np.flatnonzero(legs))
    random_rows = rng.choice(len(cands.q_rad), settings.n_identify, replace=False)
    return CampaignPlan(
        q_rad=q,
        is_identify=is_id[travel.order],
        candidates=cands,
        selection=sel,
        travel=travel,
        parameter_names=obs.names,
        parameter_sigma=parameter_sigmas(obs, sel.indices),
        random_parameter_sigma=parameter_sigmas(obs, random_rows),
        random_i_value_mm2=criterion_value(problem, random_rows).total_mm2,
        left_out=obs.left_out,
        unseen=obs.unseen,
    )
