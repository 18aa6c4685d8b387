"""``report.md`` of a planned campaign: the index, the predicted uncertainties, the travel
time against a random order, the poses dropped and why (text only; the CLI writes it)."""

from __future__ import annotations

import numpy as np

from calibration.model.cell_geometry import CellGeometry
from calibration.model.description import RobotDescription
from calibration.plan.campaign_plan import CampaignPlan, PlanSettings, joint_speeds_rad_s
from calibration.plan.robot_programs import ProgramSettings, programs_refused
from calibration.plan.travel_order import TravelOrder


def _vec(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.0f}" for x in v) + ")"


def _sigma_text(name: str, sigma: float) -> str:
    if name.endswith("_rad"):
        return f"{np.degrees(sigma) * 3600:.3g}″"
    if name.endswith("_mm"):
        return f"{sigma * 1000:.3g} µm"
    return f"{sigma:.3g}"


def plan_report(
    description: RobotDescription,
    geometry: CellGeometry,
    settings: PlanSettings,
    plan: CampaignPlan,
    programs: ProgramSettings,
) -> str:
    """The report's Markdown text. Long because it is one Markdown line per item, nothing else."""
    sel, travel, cands = plan.selection, plan.travel, plan.candidates
    n_id = int(plan.is_identify.sum())
    lines = [
        f"# Campaign plan: {description.name}",
        "",
        f"{n_id} identification + {len(plan.q_rad) - n_id} validation poses, seed "
        f"{settings.seed}, chosen from {len(cands.q_rad)} candidates in view and clear "
        f"({cands.tried} reflector poses drawn in the region).",
        "",
        "## Cell",
        "",
        f"- tracker station {_vec(geometry.station_mm)} mm (base frame), range "
        f"{geometry.min_range_mm:g}..{geometry.max_range_mm:g} mm",
        f"- reflector axis {tuple(float(v) for v in geometry.axis_flange)} (flange frame), "
        f"acceptance ±{geometry.cone_half_angle_deg:g}°; poses planned within "
        f"±{geometry.cone_half_angle_deg - settings.cone_margin_deg:g}°",
        f"- region {_vec(geometry.region_lo)}..{_vec(geometry.region_hi)} mm",
        f"- floor z = {geometry.floor_z_mm:g} mm (clearance {geometry.floor_clearance_mm:g} mm), "
        f"links as capsules of radius {geometry.link_radius_mm:.0f} mm, obstacles: "
        + (", ".join(f"{b.name} {_vec(b.lo)}..{_vec(b.hi)}" for b in geometry.obstacles) or "none"),
        f"- joint limits kept with a margin of {settings.limit_margin_deg:g}°; "
        + (
            f"wrist ≥ {settings.wrist_margin_deg:g}° and elbow ≥ {settings.elbow_margin_deg:g}° "
            "from singular (closed-form inverse kinematics)"
            if plan.candidates.ik == "closed form"
            else f"the Jacobian's conditioning ≥ {settings.min_conditioning:g} (no spherical "
            f"wrist: inverse kinematics {plan.candidates.ik})"
        ),
        "",
        "## Index",
        "",
        f"Criterion: **{'I-optimality' if sel.criterion == 'I' else 'D-optimality (O1)'}**: "
        "the expected mean squared prediction error over the region of the twin fitted to "
        "the identifiable geometry and the effects the closed loop can add from this many "
        "poses, with the bias of those it cannot ("
        + (", ".join(plan.left_out) or "none")
        + "), started from a D-optimal greedy selection, then "
        f"{sel.exchanges} I-optimal exchanges."
        if sel.criterion == "I"
        else "Criterion: **D-optimality (O1)**, greedy with exchange.",
        "",
        "| | planned | random (same count) |",
        "|---|---|---|",
        f"| expected mean squared prediction error over the region (I, mm²) | "
        f"{sel.i_value_mm2:.4g} (bias {sel.bias_mm2:.4g}) | "
        f"{plan.random_i_value_mm2:.4g} |",
        f"| O1 (D-optimality) | {sel.d_index:.4g} | |",
        "",
        "## Predicted parameter uncertainties (1 σ)",
        "",
        "The tracker's noise ±(15 µm + 6 µm/m) as 2 σ; geometry in µm and arc seconds, "
        "gravity terms in their own units (mm per unit regressor). Each is the posterior "
        "of every parameter below fitted together, beside what is known before measuring "
        "(docs/planning.md): a σ at that prior (a gravity moment's or counterbalance "
        "term's 0.1 µrad, the tracker scale's 0.06 ppm) is the prior's, not these poses'.",
        "",
        "| parameter | planned | random |",
        "|---|---|---|",
    ]
    for name, s, r in zip(
        plan.parameter_names, plan.parameter_sigma, plan.random_parameter_sigma, strict=True
    ):
        lines.append(f"| {name} | {_sigma_text(name, s)} | {_sigma_text(name, r)} |")
    if plan.unseen:
        lines += [
            "",
            "Not designed for: no candidate's reflector moves with "
            + ", ".join(plan.unseen)
            + " (such as the last joint's cyclic error with the reflector on its axis).",
        ]
    speeds = np.degrees(joint_speeds_rad_s(description))
    lines += [
        "",
        "## Travel",
        "",
        f"Closed tour from Home, synchronous PTP at the joints' top speeds "
        f"({', '.join(f'{v:g}' for v in speeds)} °/s): **{travel.time_s:.1f} s** against "
        f"{travel.random_time_s:.1f} s for a random order (mean of 20): "
        f"{travel.time_s / travel.random_time_s:.2f}×. Nearest neighbour, then 2-opt. "
        + _passes_text(travel),
        f"Moves through Home (the direct move is not clear of the cell): {len(travel.via_home)}.",
        _programs_line(description, programs),
        "",
        "## Poses dropped",
        "",
        "| why | count |",
        "|---|---|",
    ]
    for why, count in sorted(cands.dropped.items(), key=lambda kv: -kv[1]):
        if count:
            lines.append(f"| {why} | {count} |")
    return "\n".join(lines) + "\n"


def _passes_text(travel: TravelOrder) -> str:
    if travel.passes == 1:
        text = (
            "One pass: a pose's time follows where it is on the tour, so a drift in time "
            "while the arm is measured (not warmed up) is taken for geometry; the default, "
            "`--passes 2`, measures the tour forward then back (from four poses on)."
        )
    else:
        text = (
            "Forward then back (`--passes 2`): of every two poses next to each other on "
            "the tour one on the way out, the other on the way back (from pose "
            f"{travel.back_from + 1}), so neighbouring poses are half the campaign apart "
            "in time and a drift in time (the arm warming up) is not taken for geometry."
        )
    order, one, random = np.sqrt(travel.drift_bias)
    if np.isfinite(order):
        one_pass = "" if travel.passes == 1 else f"one pass: {one:.2f} mm, "
        text += (
            " A drift of the arm that moves the TCP 1 mm over the campaign would leave "
            f"{order:.2f} mm rms over the region in the twin, in this order ({one_pass}"
            f"random orders: {random:.2f} mm; `plan_criterion.drift_bias`)."
        )
    return text


def _programs_line(description: RobotDescription, programs: ProgramSettings) -> str:
    refused = programs_refused(description)
    if refused is not None:
        return f"Programs: none ({refused}); `campaign_joints.csv` holds the joints."
    return (
        f"Programs: KRL PTP at {programs.krl_velocity_pct} % axis speed, RAPID MoveAbsJ "
        f"{programs.rapid_speed}; zone: exact stop (no approximation / fine); dwell "
        f"{programs.dwell_s:g} s per pose."
    )
