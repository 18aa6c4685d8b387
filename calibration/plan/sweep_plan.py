"""The scale-calibration sweeps planned (method.md §2): for each joint, where the other
joints stand while it sweeps limit to limit in 2° stops.

The default sweep holds every other joint at Home (the emulator's ``campaign`` program).
Planned, the other joints are chosen so that

1. the reflector stays **in view and the arm clear** at every stop of the whole sweep, with
   the planner's margins (:func:`calibration.plan.campaign_plan.with_margins`, the cone
   narrowed by ``cone_margin_deg``): the reflector is the TCP's (``[reflector]`` of the
   cell), which during joint J's sweep is fixed on the moving link (the joints after J
   hold still), so its circle is the swept joint's, as a target on link J would be;
2. among those, the **gravity torque on the swept joint varies least** over the sweep
   (max − min, N·m): from the description's masses and centres of mass
   (:func:`calibration.model.statics.gravity_torques_nmm`); a description without masses
   gets a stated proxy, unit masses at every joint origin and the tool point.

Candidates for the other joints: Home (the default sweep), uniform draws within the limits
less the margin, and draws with the joints after J at Home (which lines the reflector's
axis up with a wrist axis: what lets joints 4 and 6 turn a whole range in the cone). A
joint no candidate sweeps whole in view keeps the candidate with the most stops in view
(fewest torque swing among equals), its stops flagged, and the reason counted.

Units: rad inside, degrees in the settings; torques N·m.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from calibration.model.cell_geometry import (
    VIEW_REASONS,
    CellGeometry,
    collision_codes,
    collision_reason,
    reflector_in_base,
    view_codes,
)
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel
from calibration.model.statics import MassModel, gravity_torques_nmm
from calibration.plan.campaign_plan import PlanSettings, with_margins

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class SweepSettings:
    """How the sweeps are planned (degrees): the stop spacing, how many candidate
    positions of the other joints are tried per joint, the seed; the cell's margins are
    the campaign planner's (:class:`PlanSettings`)."""

    step_deg: float = 2.0
    n_candidates: int = 400
    seed: int = 1
    margins: PlanSettings = field(default_factory=PlanSettings)
    #: the refinement: this many best candidates, each perturbed this many times per
    #: round, over this many rounds of a shrinking step (deg), judged on every
    #: ``refine_every``-th stop (the final choice on every stop)
    refine_keep: int = 16
    refine_children: int = 8
    refine_rounds: int = 20
    refine_step_deg: float = 20.0
    refine_every: int = 3
    #: the reflector's least distance from the swept joint's axis (mm): the scale map is
    #: read off its circle, so a 2° step must move it ≥ 7 mm and a tracker point's
    #: ~0.015 mm must stay ≤ ~15″ of angle (the default link targets sit ~500 mm out); the
    #: TCP on a wrist axis sees every stop and measures no angle
    min_radius_mm: float = 200.0


@dataclass(frozen=True, eq=False)
class JointSweep:
    """One joint's planned sweep: the forward pass's stops ``q_rad`` ``(K, n)`` from the
    positive limit down (the backward pass is the same stops reversed), per stop whether
    the reflector is in view and the arm clear ``(K,)``, the gravity torque on the swept
    joint ``(K,)`` N·m; ``reason``: why stops are out (empty when it is whole in view)."""

    joint: int  # 1-based
    q_rad: FloatArray
    in_view: BoolArray
    torque_nm: FloatArray
    reason: str = ""

    @property
    def whole(self) -> bool:
        return bool(self.in_view.all())

    @property
    def torque_range_nm(self) -> float:
        return float(np.ptp(self.torque_nm))


@dataclass(frozen=True)
class SweepPlan:
    """Every joint's sweep, and where the torques come from."""

    sweeps: tuple[JointSweep, ...]
    torque_source: str


def sweep_stops_rad(
    description: RobotDescription, joint: int, settings: SweepSettings
) -> FloatArray:
    """The swept joint's stops ``(K,)`` rad, from its upper limit less the margin down
    every ``step_deg`` (the emulator's sweep, :func:`sim_devices.plant.campaign_moves`)."""
    j = description.joints[joint - 1]
    margin = settings.margins.limit_margin_deg
    lo, hi = j.lower_deg + margin, j.upper_deg - margin
    count = int(np.floor((hi - lo) / settings.step_deg + 1e-9)) + 1
    stops: FloatArray = np.radians(hi - settings.step_deg * np.arange(count))
    return stops


def torque_model(description: RobotDescription) -> tuple[MassModel, str]:
    """The masses the torques are computed from, and what they are."""
    masses = MassModel.from_description(description)
    if masses.total_mass_kg > 0.0:
        return masses, "the description's link and tool masses (mass_kg, com_mm)"
    n = description.n_joints
    proxy = MassModel(np.ones(n), np.zeros((n, 3)), 1.0, masses.tool_mm)
    return proxy, "a proxy: 1 kg at every joint origin and at the tool point (no masses given)"


def gravity_torque_nm(
    model: KinematicModel, masses: MassModel, q_rad: FloatArray, joint: int
) -> FloatArray:
    """The gravity torque on ``joint`` (1-based) at joint vectors ``(N, n)`` rad, N·m."""
    torque: FloatArray = gravity_torques_nmm(model, masses, q_rad)[:, joint - 1] / 1000.0
    return torque


def default_sweep(
    description: RobotDescription, joint: int, settings: SweepSettings = SweepSettings()
) -> FloatArray:
    """The default sweep's stops ``(K, n)`` rad: every other joint at Home."""
    stops = sweep_stops_rad(description, joint, settings)
    q = np.tile(np.radians(description.home), (len(stops), 1))
    q[:, joint - 1] = stops
    return q


def _candidates(
    description: RobotDescription, joint: int, settings: SweepSettings, rng: np.random.Generator
) -> FloatArray:
    """Positions of the other joints ``(C, n)`` rad (the swept joint's column unused):
    Home first, then uniform draws, then draws with the joints after ``joint`` at Home."""
    margin = settings.margins.limit_margin_deg
    lo = np.radians([j.lower_deg + margin for j in description.joints])
    hi = np.radians([j.upper_deg - margin for j in description.joints])
    home = np.radians(description.home)
    half = settings.n_candidates // 2
    uniform = rng.uniform(lo, hi, (half, len(lo)))
    aligned = rng.uniform(lo, hi, (settings.n_candidates - half, len(lo)))
    aligned[:, joint:] = home[joint:]
    return np.vstack([home[None, :], uniform, aligned])


def _why(view: NDArray[np.int8], clear: NDArray[np.int8], geometry: CellGeometry) -> str:
    """The reasons of the stops out, counted (view first, then collisions)."""
    reasons: Counter[str] = Counter()
    for code in view[view != 0].tolist():
        reasons[VIEW_REASONS[int(code)]] += 1
    for code in clear[(view == 0) & (clear != 0)].tolist():
        reasons[collision_reason(geometry, int(code))] += 1
    return ", ".join(f"{text}: {k} stop{'s' if k > 1 else ''}" for text, k in reasons.most_common())


@dataclass(frozen=True, eq=False)
class _Scores:
    """Candidates ``(C, n)`` judged on stops ``(K,)``: the joint vectors ``(C, K, n)``,
    view and collision codes and torques ``(C, K)``."""

    q: FloatArray
    view: NDArray[np.int8]
    clear: NDArray[np.int8]
    torque: FloatArray
    #: the reflector's distance from the swept axis ``(C,)`` mm, and the least usable
    radius_mm: FloatArray
    min_radius_mm: float

    @property
    def n_ok(self) -> NDArray[np.intp]:
        """Stops in view and clear per candidate ``(C,)``; none where the reflector is
        too near the swept axis to measure its angle."""
        counts: NDArray[np.intp] = ((self.view == 0) & (self.clear == 0)).sum(axis=1)
        return counts * (self.radius_mm >= self.min_radius_mm)

    def order(self) -> NDArray[np.intp]:
        """Best first: most stops in view and clear, then the least torque swing."""
        best: NDArray[np.intp] = np.lexsort((np.ptp(self.torque, axis=1), -self.n_ok))
        return best


def _score(
    model: KinematicModel,
    masses: MassModel,
    geometry: CellGeometry,
    cand: FloatArray,
    joint: int,
    stops: FloatArray,
    min_radius_mm: float,
) -> _Scores:
    q = np.repeat(cand[:, None, :], len(stops), axis=1)  # (C, K, n)
    q[:, :, joint - 1] = stops
    flat = q.reshape(-1, cand.shape[1])
    pos, axis = reflector_in_base(model, geometry, flat)
    shape = (len(cand), len(stops))
    # the circle's radius from its chords: |Δp| = 2·R·sin(Δq/2) between stops
    p = pos.reshape(*shape, 3)
    chord = np.linalg.norm(np.diff(p, axis=1), axis=2)
    radius = np.median(chord / (2.0 * np.sin(np.abs(np.diff(stops)) / 2.0)), axis=1)
    return _Scores(
        q,
        view_codes(geometry, pos, axis).reshape(shape),
        collision_codes(model, geometry, flat).reshape(shape),
        gravity_torque_nm(model, masses, flat, joint).reshape(shape),
        radius,
        min_radius_mm,
    )


def _refine(
    score: Callable[[FloatArray], _Scores],
    start: FloatArray,
    joint: int,
    limits: tuple[FloatArray, FloatArray],
    settings: SweepSettings,
    rng: np.random.Generator,
) -> FloatArray:
    """Random local search from the best of ``start`` ``(C, n)``: each kept candidate's
    other joints perturbed (normal, the step shrinking 15 % a round), a child replacing
    its parent when it scores better; the kept candidates ``(T, n)``."""
    keep = start[score(start).order()[: settings.refine_keep]]
    lo, hi = limits
    step = np.radians(settings.refine_step_deg)
    mask = np.ones(keep.shape[1])
    mask[joint - 1] = 0.0  # the swept joint's column is the stops'
    for _ in range(settings.refine_rounds):
        kids = np.repeat(keep, settings.refine_children, axis=0)
        kids = np.clip(kids + rng.normal(0.0, step, kids.shape) * mask, lo, hi)
        pool = np.vstack([keep, kids])
        s = score(pool)
        parent = np.concatenate(
            [np.arange(len(keep)), np.repeat(np.arange(len(keep)), settings.refine_children)]
        )
        rank = np.empty(len(pool), dtype=np.intp)
        rank[s.order()] = np.arange(len(pool))
        best = np.full(len(keep), -1)
        for i in np.argsort(rank).tolist():  # best first: each parent's best of its family
            if best[parent[i]] < 0:
                best[parent[i]] = i
        keep = pool[best]
        step *= 0.85
    return keep


def plan_joint_sweep(
    description: RobotDescription,
    geometry: CellGeometry,
    joint: int,
    settings: SweepSettings = SweepSettings(),
) -> JointSweep:
    """Joint ``joint``'s (1-based) sweep: the other joints' position that keeps every
    stop in view and clear with the least torque swing (module docstring)."""
    rng = np.random.default_rng([settings.seed, joint])
    model = KinematicModel.from_description(description)
    masses, _ = torque_model(description)
    m = settings.margins
    checked = replace(
        with_margins(geometry, m),
        cone_half_angle_deg=geometry.cone_half_angle_deg - m.cone_margin_deg,
    )
    stops = sweep_stops_rad(description, joint, settings)
    coarse = stops[:: settings.refine_every]
    lo = np.radians([j.lower_deg + m.limit_margin_deg for j in description.joints])
    hi = np.radians([j.upper_deg - m.limit_margin_deg for j in description.joints])

    r_min = settings.min_radius_mm

    def on_coarse(cand: FloatArray) -> _Scores:
        return _score(model, masses, checked, cand, joint, coarse, r_min)

    cand = _candidates(description, joint, settings, rng)
    refined = _refine(on_coarse, cand, joint, (lo, hi), settings, rng)
    final = _score(model, masses, checked, np.vstack([cand[:1], refined]), joint, stops, r_min)
    best = int(final.order()[0])
    ok = (final.view[best] == 0) & (final.clear[best] == 0)
    tried = len(cand) + settings.refine_rounds * settings.refine_keep * settings.refine_children
    reason = ""
    if final.radius_mm[best] < r_min:  # no position holds the reflector off the axis in view
        ok[:] = False
        reason = (
            f"over {tried} positions of the other joints none kept the reflector (the TCP's) "
            f"in view and {r_min:.0f} mm or more from joint {joint}'s axis (the best "
            f"{float(final.radius_mm[best]):.0f} mm: too near to read the angle off its "
            "circle): sweep it with a target on the link"
        )
    elif not ok.all():
        reason = (
            f"at best {int(ok.sum())} of {len(stops)} stops in view and clear over {tried} "
            f"positions of the other joints ({_why(final.view[best], final.clear[best], checked)})"
        )
    return JointSweep(joint, final.q[best], ok, final.torque[best], reason)


def plan_sweeps(
    description: RobotDescription,
    geometry: CellGeometry,
    settings: SweepSettings = SweepSettings(),
) -> SweepPlan:
    """Every joint's planned sweep (:func:`plan_joint_sweep`)."""
    sweeps = tuple(
        plan_joint_sweep(description, geometry, j, settings)
        for j in range(1, description.n_joints + 1)
    )
    return SweepPlan(sweeps, torque_model(description)[1])


def sweeps_csv(plan: SweepPlan) -> str:
    """``sweeps.csv``: ``joint,stop,q1_deg..qN_deg,in_view,torque_nm``, one row per stop
    of each joint's forward pass (positive limit down; the backward pass is the same stops
    reversed); ``in_view`` 1 when the reflector is in view and the arm clear; the gravity
    torque on the swept joint in N·m (3 decimals)."""
    from calibration.plan.robot_programs import format_angle

    n = plan.sweeps[0].q_rad.shape[1] if plan.sweeps else 0
    out = ["joint,stop," + ",".join(f"q{j + 1}_deg" for j in range(n)) + ",in_view,torque_nm"]
    for s in plan.sweeps:
        for k, (row, ok, tau) in enumerate(
            zip(np.degrees(s.q_rad), s.in_view, s.torque_nm, strict=True)
        ):
            angles = ",".join(format_angle(v) for v in row)
            out.append(f"{s.joint},{k},{angles},{int(ok)},{tau:.3f}")
    return "\n".join(out) + "\n"


def sweep_program_poses(plan: SweepPlan) -> tuple[FloatArray, list[str], set[int]]:
    """The sweeps as one robot program: stops ``(S, n)`` deg (each joint forward then
    back), labels ``S<j>F<k>`` / ``S<j>B<k>``, and the first stop of each joint (reached
    through Home)."""
    rows: list[FloatArray] = []
    labels: list[str] = []
    via: set[int] = set()
    for s in plan.sweeps:
        via.add(len(labels))
        q = np.degrees(s.q_rad)
        rows += [q, q[::-1]]
        labels += [f"S{s.joint}F{k}" for k in range(len(q))]
        labels += [f"S{s.joint}B{k}" for k in range(len(q))]
    n = plan.sweeps[0].q_rad.shape[1] if plan.sweeps else 0
    return (np.vstack(rows) if rows else np.zeros((0, n))), labels, via


def sweep_report(description: RobotDescription, plan: SweepPlan) -> str:
    """The report's section on the sweeps (markdown): per joint the other joints' angles,
    the stops in view, the torque swing against the default sweep's (others at Home)."""
    model = KinematicModel.from_description(description)
    masses, _ = torque_model(description)
    lines = [
        "",
        "## Scale-calibration sweeps (`sweeps.csv`, `twin_sweeps.*`)",
        "",
        "Each joint limit to limit in 2° stops and back, the other joints where the "
        "reflector stays in view and the gravity torque on the swept joint varies least; "
        f"torques from {plan.torque_source}.",
        "",
        "| joint | other joints (deg) | stops in view | torque swing, N·m | others at Home |",
        "|---|---|---|---|---|",
    ]
    for s in plan.sweeps:
        others = np.degrees(s.q_rad[0])
        text = ", ".join(
            f"q{i + 1} {others[i]:.1f}" for i in range(len(others)) if i != s.joint - 1
        )
        default = gravity_torque_nm(
            model, masses, default_sweep(description, s.joint), s.joint
        )  # fmt: skip
        lines.append(
            f"| {s.joint} | {text} | {int(s.in_view.sum())} of {len(s.in_view)} | "
            f"{s.torque_range_nm:.1f} | {float(np.ptp(default)):.1f} |"
        )
    lost = [s for s in plan.sweeps if not s.whole]
    lines.append("")
    if lost:
        lines.append("Not swept whole in view:")
        lines += [f"* joint {s.joint}: {s.reason}" for s in lost]
    else:
        lines.append("Every joint is swept whole in view.")
    return "\n".join(lines) + "\n"
