"""Emulated identification campaign: random reachable poses measured by the tracker.

From a :class:`~sim_devices.truth.TrueCell`: sample reachable joint vectors within limits and
away from singularities, choose the identification poses by an observability index, measure
the true TCP with the tracker model, read the joints with the (scale-calibrated) gratings and
the motor encoders, and write ``campaign.csv`` (see :mod:`calibration.identify.campaign_files`).

    python -m sim_devices.pose_campaign --robot kr500 --seed 1 --out campaign.csv
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
from numpy.typing import NDArray

from calibration.errors import CalibrationError
from calibration.identify.campaign_files import Campaign, write_campaign
from calibration.identify.pose_selection import OBSERVABILITY_INDICES, select_poses_for_model
from calibration.model.description import RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel, flange_poses, tcp_positions
from edges.command import run_command, take_debug_flag
from edges.options import OptionParser
from edges.outputs import OutputSet
from sim_devices.config import (
    SEED_OPTION,
    CellConfig,
    integer_option,
    number_option,
    robot_option,
)
from sim_devices.drift import STEP_KINDS, CellDrift, DriftDraws, draw_drift, drifted_tcp_mm
from sim_devices.effects import (
    EFFECT_NAMES,
    UndeclaredEffects,
    approach_direction,
    arm_temperature_c,
    effects_document,
    grating_reading_rad,
    tracker_reading_mm,
    true_tcp_mm,
    with_derived_stiffness,
)
from sim_devices.errors import SimError
from sim_devices.truth import TrueCell

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Workspace:
    """Where measurement poses may be: away from singularities, in the tracker's range."""

    wrist_min_deg: float = 10.0  # angle between axes 4 and 6 (|q5| on these arms)
    elbow_margin_deg: float = 10.0  # elbow angle at least this far from stretched
    elbow_min_deg: float = 35.0  # ... and from folded
    shoulder_min_mm: float = 200.0  # wrist centre distance from the joint-1 axis
    floor_mm: float = 100.0  # TCP height above the base plane (robot base frame)
    tracker_min_mm: float = 1000.0  # tracker range (FARO Vantage E class: 25 m)
    tracker_max_mm: float = 25000.0


def _limits_rad(description: RobotDescription) -> tuple[FloatArray, FloatArray]:
    lo = np.radians([j.lower_deg for j in description.joints])
    hi = np.radians([j.upper_deg for j in description.joints])
    return lo, hi


def reachable_mask(
    description: RobotDescription, q_rad: FloatArray, workspace: Workspace = Workspace()
) -> NDArray[np.bool_]:
    """Which joint vectors ``(N, n)`` rad are good measurement poses, shape ``(N,)``."""
    model = KinematicModel.from_description(description)
    q = np.atleast_2d(q_rad)
    lo, hi = _limits_rad(description)
    ok = np.all((q >= lo) & (q <= hi), axis=1)
    tcp_base = tcp_positions(model, q, world=False)
    ok &= tcp_base[:, 2] > workspace.floor_mm
    dist = np.linalg.norm(tcp_positions(model, q), axis=1)
    ok &= (dist >= workspace.tracker_min_mm) & (dist <= workspace.tracker_max_mm)
    if model.n_joints == 6:
        frames = [flange_poses(model.truncated(k), q[:, :k], world=False) for k in range(1, 7)]
        shoulder, elbow, wrist = (frames[i][:, :3, 3] for i in (1, 2, 4))
        u, v = shoulder - elbow, wrist - elbow
        cos_el = np.sum(u * v, axis=1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        elbow_deg = np.degrees(np.arccos(np.clip(cos_el, -1.0, 1.0)))
        ok &= elbow_deg <= 180.0 - workspace.elbow_margin_deg
        ok &= elbow_deg >= workspace.elbow_min_deg
        z1 = frames[0][:, :3, 2]
        o1 = frames[0][:, :3, 3]
        rel = wrist - o1
        radial = rel - np.sum(rel * z1, axis=1)[:, None] * z1
        ok &= np.linalg.norm(radial, axis=1) >= workspace.shoulder_min_mm
        z4, z6 = frames[3][:, :3, 2], frames[5][:, :3, 2]
        wrist_deg = np.degrees(np.arccos(np.clip(np.abs(np.sum(z4 * z6, axis=1)), 0.0, 1.0)))
        ok &= wrist_deg >= workspace.wrist_min_deg
    feasible: NDArray[np.bool_] = ok
    return feasible


def sample_reachable_poses(
    description: RobotDescription,
    n: int,
    rng: np.random.Generator,
    *,
    workspace: Workspace = Workspace(),
) -> FloatArray:
    """``n`` random joint vectors ``(n, n_joints)`` rad, uniform within limits, kept if
    :func:`reachable_mask` accepts them (rejection sampling)."""
    lo, hi = _limits_rad(description)
    out: list[FloatArray] = []
    have = 0
    for _ in range(1000):
        batch = rng.uniform(lo, hi, size=(max(4 * (n - have), 64), len(lo)))
        good = batch[reachable_mask(description, batch, workspace)]
        out.append(good[: n - have])
        have += len(out[-1])
        if have >= n:
            return np.concatenate(out)
    raise SimError(
        f"robot {description.name!r}: could not find {n} reachable measuring poses in 1000 "
        f"batches: is its TCP above the floor ({workspace.floor_mm:g} mm) and within the "
        f"tracker's range ({workspace.tracker_min_mm / 1000:g}..{workspace.tracker_max_mm / 1000:g}"
        " m from the origin) in enough of its joint space?"
    )


def plan_identification_poses(
    description: RobotDescription,
    n: int,
    rng: np.random.Generator,
    *,
    index: str | None = "O1",
    candidates_per_pose: int = 5,
    workspace: Workspace = Workspace(),
) -> FloatArray:
    """``n`` identification poses ``(n, n_joints)`` rad: the best ``n`` of
    ``candidates_per_pose · n`` random reachable ones by ``index`` (None: just random)."""
    if index is None:
        return sample_reachable_poses(description, n, rng, workspace=workspace)
    cand = sample_reachable_poses(description, candidates_per_pose * n, rng, workspace=workspace)
    model = KinematicModel.from_description(description)
    sel = select_poses_for_model(model, cand, n, index=index)
    return cand[sel.indices]


@dataclass(frozen=True)
class CampaignSettings:
    """How the emulated campaign is run and read."""

    n_identify: int = 100
    n_validate: int = 150
    selection: str | None = "O1"  # observability index for the identification poses
    grating_noise_deg: float = 5e-5  # read noise of a scale-calibrated grating (1 σ)
    grating_scale_error_ppm: float = 0.0  # residual scale error after scale calibration
    encoder_backlash_deg: float = 0.01  # full backlash seen by the motor encoders
    encoder_noise_deg: float = 0.002
    pose_time_s: tuple[float, float] = (8.0, 20.0)  # move, settle and measure, per pose
    encoders: bool = True
    effects: UndeclaredEffects = field(default_factory=UndeclaredEffects)  # off by default


@dataclass(frozen=True)
class CampaignData:
    """An emulated campaign and its hidden truth."""

    campaign: Campaign
    q_true_rad: FloatArray  # (m, n) true joint angles (of the grating rings)
    tcp_true_mm: FloatArray  # (m, 3) true TCP in the tracker frame, physical effects included
    cell: TrueCell
    #: (m, 3) what a noise-free tracker reads: the true model's prediction of the points
    #: (tcp_true_mm with the tracker's own scale error); None: same as tcp_true_mm
    expected_mm: FloatArray | None = None
    #: the settings used, with the derived deflection stiffness filled in
    effects: UndeclaredEffects = field(default_factory=UndeclaredEffects)

    @property
    def true_model(self) -> KinematicModel:
        return self.cell.model

    @property
    def true_prediction_mm(self) -> FloatArray:
        """The true model's (noise-free) prediction of every measured point ``(m, 3)`` mm."""
        return self.tcp_true_mm if self.expected_mm is None else self.expected_mm

    def truth_document(self) -> dict[str, Any]:
        """The cell's truth plus the undeclared effects and their derived parameters."""
        doc = self.cell.truth_document()
        doc["undeclared_effects"] = effects_document(self.effects, self.cell.arm)
        return doc

    def write_truth(self, path: str | Path) -> None:
        """Write the truth for tests (the twin never reads this file); 0 stiffness = rigid.
        Atomic: the file appears whole or not at all."""
        text = tomli_w.dumps(self.truth_document())
        with OutputSet(error=SimError) as outputs:
            outputs.file(path, "--truth").write_text(text, encoding="utf-8")


def generate_campaign(
    cell: TrueCell,
    rng: np.random.Generator,
    settings: CampaignSettings = CampaignSettings(),
) -> CampaignData:
    """Run an emulated campaign on ``cell``: identification poses then validation poses.

    ``settings.effects`` switches on undeclared effects (:mod:`sim_devices.effects`, on
    the cell's own physical arm). The random draws are the same with and without them, so
    a campaign with an effect differs from the clean one of the same seed by the effect
    alone (the tracker's noise σ is taken at the effect-free point; sub-mm displacements
    change it by < 1e-9 mm).
    """
    nominal = cell.nominal
    q_id = plan_identification_poses(nominal, settings.n_identify, rng, index=settings.selection)
    q_val = sample_reachable_poses(nominal, settings.n_validate, rng)
    return measure_campaign(cell, q_id, q_val, rng, settings)


def measure_campaign(
    cell: TrueCell,
    q_identify_rad: FloatArray,
    q_validate_rad: FloatArray,
    rng: np.random.Generator,
    settings: CampaignSettings = CampaignSettings(),
    t_s: FloatArray | None = None,
) -> CampaignData:
    """Run the campaign of the given joint vectors (``(m_id, n)`` then ``(m_val, n)`` rad,
    the true ring angles, in this order) on ``cell``: the tracker's points, the gratings'
    and encoders' readings, with ``settings``' effects and noise (``settings.n_identify``,
    ``n_validate`` and ``selection`` are not used: the poses are given). ``t_s`` ``(m,)``:
    the poses' times from the campaign's start (s) instead of one move-and-settle after
    another (the same random draws either way)."""
    q_true = np.vstack([q_identify_rad, q_validate_rad])
    n_identify, n_validate = len(q_identify_rad), len(q_validate_rad)
    m = len(q_true)
    tcp = cell.tcp_mm(q_true)
    measured = _measure(cell, tcp, rng)
    eff = with_derived_stiffness(settings.effects, cell.arm)
    grating = grating_reading_rad(eff, q_true) * (1.0 + 1e-6 * settings.grating_scale_error_ppm)
    grating = grating + np.radians(rng.normal(0.0, settings.grating_noise_deg, q_true.shape))
    dt = rng.uniform(*settings.pose_time_s, size=m)
    t_s = np.cumsum(dt) if t_s is None else np.asarray(t_s, dtype=float)
    direction = approach_direction(q_true)
    expected = None
    if eff.any_active:
        tcp_physical = true_tcp_mm(eff, cell.arm, q_true, t_s, direction)
        expected = tracker_reading_mm(eff, tcp_physical, t_s)
        measured = measured + (expected - tcp)
        tcp = tcp_physical
    encoder = None
    if settings.encoders:
        encoder = q_true + np.radians(
            0.5 * settings.encoder_backlash_deg * direction
            + rng.normal(0.0, settings.encoder_noise_deg, q_true.shape)
        )
    temp_c = None
    if eff.thermal_expansion:  # drawn last: every other draw as without the effect
        noise = rng.normal(0.0, eff.temp_sensor_noise_k, m)
        temp_c = arm_temperature_c(eff, t_s) + noise
    sets = ("identify",) * n_identify + ("validate",) * n_validate
    campaign = Campaign(
        source="<emulated>",
        pose=tuple(str(i + 1) for i in range(m)),
        set=sets,
        t_s=t_s,
        q_deg=np.degrees(grating),
        xyz_mm=measured,
        encoder_deg=None if encoder is None else np.degrees(encoder),
        temp_c=temp_c,
    )
    return CampaignData(
        campaign=campaign,
        q_true_rad=q_true,
        tcp_true_mm=tcp,
        cell=cell,
        expected_mm=expected,
        effects=eff,
    )


def _measure(cell: TrueCell, tcp_mm: FloatArray, rng: np.random.Generator) -> FloatArray:
    """The tracker's points of ``tcp_mm`` ``(m, 3)``; a broken beam is measured again, up
    to 100 times (draws from ``rng``)."""
    measured, ok = cell.tracker.measure(tcp_mm, rng)
    for _ in range(100):
        if ok.all():
            break
        again, ok_again = cell.tracker.measure(tcp_mm[~ok], rng)
        measured[~ok] = again
        ok[~ok] = ok_again
    return measured


def emulated_campaign(
    robot: str | RobotDescription,
    seed: int,
    settings: CampaignSettings = CampaignSettings(),
) -> CampaignData:
    """A reproducible campaign on a true cell drawn around ``robot`` from ``seed``."""
    nominal = load_robot(robot) if isinstance(robot, str) else robot
    cell = TrueCell.create(nominal, seed)
    return generate_campaign(cell, np.random.default_rng([seed, 6]), settings)


@dataclass(frozen=True)
class CheckProgram:
    """A production program after the campaign: ``n_poses`` check poses visited in turn,
    one every ``every_min`` minutes for ``hours`` (the reflector in view at each), while
    the cell drifts as ``drift`` says."""

    hours: float = 8.0
    every_min: float = 2.0
    n_poses: int = 12
    gap_s: float = 600.0  # from the campaign's last pose to the first check
    drift: CellDrift = field(default_factory=CellDrift)


@dataclass(frozen=True)
class ChecksData:
    """An emulated production run: the check file's rows and the hidden truth."""

    checks: Campaign  # set 'validate' on every row (the column is ignored by twin track)
    true_mm: FloatArray  # (m, 3) what a noise-free tracker reads at each check
    draws: DriftDraws
    program: CheckProgram

    def truth_document(self) -> dict[str, Any]:
        return {
            "drift": self.program.drift.document(),
            "draws": self.draws.document(),
            "program": {
                "hours": self.program.hours,
                "every_min": self.program.every_min,
                "n_poses": self.program.n_poses,
            },
        }


def generate_checks(
    data: CampaignData,
    program: CheckProgram,
    rng: np.random.Generator,
    settings: CampaignSettings = CampaignSettings(),
) -> ChecksData:
    """Production checks after ``data``'s campaign on the same cell and clock: the check
    poses in turn, each measured by the tracker of the drifting cell, read by the gratings
    (their noise), with the campaign's undeclared effects; with the arm's thermal
    expansion on, its temperature read as the campaign's is (``temp_c``)."""
    cell, eff = data.cell, data.effects
    poses = sample_reachable_poses(cell.nominal, program.n_poses, rng)
    start = float(data.campaign.t_s[-1]) + program.gap_s
    m = max(int(program.hours * 60.0 / program.every_min), 1)
    t_s = start + 60.0 * program.every_min * np.arange(m) + rng.uniform(0.0, 10.0, m)
    q_true = poses[np.arange(m) % program.n_poses]
    draws = draw_drift(program.drift, cell.nominal.n_joints, start, float(t_s[-1]), rng)
    shift = drifted_tcp_mm(program.drift, draws, cell.model, q_true, t_s) - cell.tcp_mm(q_true)
    direction = approach_direction(q_true)
    physical = true_tcp_mm(eff, cell.arm, q_true, t_s, direction) if eff.any_active else None
    tcp = (cell.tcp_mm(q_true) if physical is None else physical) + shift
    true_read = tracker_reading_mm(eff, tcp, t_s) if eff.any_active else tcp
    measured = _measure(cell, true_read, rng)
    grating = grating_reading_rad(eff, q_true) + np.radians(
        rng.normal(0.0, settings.grating_noise_deg, q_true.shape)
    )
    temp_c = None
    if eff.thermal_expansion:  # drawn last: every other draw as without the effect
        temp_c = arm_temperature_c(eff, t_s) + rng.normal(0.0, eff.temp_sensor_noise_k, m)
    checks = Campaign(
        source="<emulated checks>",
        pose=tuple(f"c{i + 1}" for i in range(m)),
        set=("validate",) * m,
        t_s=t_s,
        q_deg=np.degrees(grating),
        xyz_mm=measured,
        temp_c=temp_c,
    )
    return ChecksData(checks=checks, true_mm=true_read, draws=draws, program=program)


def emulated_checks(
    data: CampaignData, seed: int, program: CheckProgram, settings: CampaignSettings
) -> ChecksData:
    """The reproducible production run of ``seed`` after its campaign ``data`` (a random
    stream of its own: the campaign is the same with and without it)."""
    return generate_checks(data, program, np.random.default_rng([seed, 28]), settings)


#: The most identification or validation poses (a candidate pool of 5 per pose is drawn
#: in batches of 4×: more would take minutes and gigabytes).
MAX_POSES = 10_000


def build_parser() -> argparse.ArgumentParser:
    """The generator's options, each checked as it is parsed (counts in range); long as a
    flat list of ``add_argument`` calls is (the campaign's, then the production run's)."""
    parser = OptionParser(
        prog="python -m sim_devices.pose_campaign",
        description="Write an emulated identification campaign (campaign.csv).",
    )
    parser.add_argument("--robot", default="kr500", help="preset name or robot .toml")
    parser.add_argument("--seed", type=SEED_OPTION, default=1)
    parser.add_argument("--out", required=True, help="campaign.csv to write")
    parser.add_argument(
        "--identify",
        type=integer_option(1, MAX_POSES, "identification poses"),
        default=100,
        help=f"identification poses, 1..{MAX_POSES}",
    )
    parser.add_argument(
        "--validate",
        type=integer_option(0, MAX_POSES, "validation poses"),
        default=150,
        help=f"validation poses, 0..{MAX_POSES}",
    )
    parser.add_argument(
        "--selection",
        default="O1",
        choices=[*OBSERVABILITY_INDICES, "none"],
        help="observability index choosing the identification poses (none: random)",
    )
    parser.add_argument("--no-encoders", action="store_true", help="omit e1_deg..eN_deg")
    parser.add_argument("--truth", help="also write the hidden truth (TOML) here, for tests")
    parser.add_argument(
        "--checks",
        metavar="FILE",
        help="also write a production run after the campaign: periodic check poses in time "
        "order (campaign.csv's columns, for twin track)",
    )
    parser.add_argument(
        "--check-hours",
        type=number_option(0.01, 1000.0, what="hours of production"),
        default=8.0,
        help="length of the production run, h (default 8)",
    )
    parser.add_argument(
        "--check-every-min",
        type=number_option(0.2, 600.0, what="minutes between checks"),
        default=2.0,
        help="one check every N minutes (default 2)",
    )
    parser.add_argument(
        "--check-poses",
        type=integer_option(1, 1000, "check poses"),
        default=12,
        help="distinct check poses, visited in turn (default 12)",
    )
    parser.add_argument(
        "--cell",
        metavar="CELL.toml",
        help="take the drift of the production run from this cell.toml's [effects.drift] "
        "(the --drift flags add to it)",
    )
    parser.add_argument(
        "--drift",
        action="append",
        default=[],
        choices=["thermal", "creep", *STEP_KINDS],
        help="let the cell move during the production run (repeatable): thermal (link "
        "lengths grow, warm-up τ 1 h), creep (the base slides), "
        + "; ".join(f"{k}: {v}" for k, v in STEP_KINDS.items())
        + " (at a time drawn from the seed)",
    )
    parser.add_argument(
        "--effect",
        action="append",
        default=[],
        choices=list(EFFECT_NAMES),
        help="switch on an effect the twin is not told about, at its default strength "
        "(repeatable): " + "; ".join(f"{k}: {v}" for k, v in EFFECT_NAMES.items()),
    )
    return parser


def _run(args: argparse.Namespace) -> int:
    for option, path in (("--out", args.out), ("--truth", args.truth)):
        if path is not None and not path.strip():
            raise SimError(f"{option}: empty path; give a file to write")
    nominal = robot_option(args.robot)
    settings = CampaignSettings(
        n_identify=args.identify,
        n_validate=args.validate,
        selection=None if args.selection == "none" else args.selection,
        encoders=not args.no_encoders,
        effects=UndeclaredEffects.named(*args.effect),
    )
    program = CheckProgram(
        hours=args.check_hours,
        every_min=args.check_every_min,
        n_poses=args.check_poses,
        drift=_drift(args),
    )
    if program.drift.any_active and not args.checks:
        raise SimError(
            "--drift: the cell drifts (--drift or [effects.drift]) during a production run; "
            "give --checks FILE"
        )
    if args.checks is not None and not args.checks.strip():
        raise SimError("--checks: empty path; give a file to write")
    robot_file = args.robot if Path(args.robot).exists() else None
    with OutputSet(inputs=[robot_file, args.cell], error=SimError) as outputs:
        out = outputs.file(args.out, "--out")
        truth = outputs.file(args.truth, "--truth") if args.truth else None
        checks_out = outputs.file(args.checks, "--checks") if args.checks else None
        data = emulated_campaign(nominal, args.seed, settings)
        write_campaign(out, data.campaign)
        checks = None
        if checks_out is not None:
            checks = emulated_checks(data, args.seed, program, settings)
            write_campaign(checks_out, checks.checks)
        if truth is not None:
            doc = data.truth_document()
            if checks is not None:
                doc["production"] = checks.truth_document()
            truth.write_text(tomli_w.dumps(doc), encoding="utf-8")
    print(f"wrote {args.out}: {len(data.campaign)} poses", file=sys.stderr)
    if checks is not None:
        print(f"wrote {args.checks}: {len(checks.checks)} checks", file=sys.stderr)
    return 0


def _drift(args: argparse.Namespace) -> CellDrift:
    """The production run's drift: ``--cell``'s ``[effects.drift]`` and the ``--drift``
    flags on top."""
    if args.cell is not None and not args.cell.strip():
        raise SimError("--cell: empty path; give a cell.toml or leave the option out")
    base = CellConfig.load(args.cell).effects.drift if args.cell else CellDrift()
    return replace(
        base,
        thermal=base.thermal or "thermal" in args.drift,
        creep=base.creep or "creep" in args.drift,
        steps=tuple(k for k in STEP_KINDS if k in args.drift or k in base.steps),
    )


def main(argv: list[str] | None = None) -> int:
    """The command line: a user's mistake is one line on stderr and exit 2
    (:func:`edges.command.run_command`); ``--debug`` shows tracebacks."""
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return run_command(
        "python -m sim_devices.pose_campaign",
        lambda: _run(args),
        user_errors=(SimError, CalibrationError),
        debug=debug,
    )


if __name__ == "__main__":
    raise SystemExit(main())
