"""``twin identify`` and ``twin predict``: identification from a campaign, and prediction.

twin identify --robot robot.toml --data campaign.csv --out calibrated.toml [--report DIR]
    [--no-effects] [--effect-kinds K,K] [--effects-alpha A] [--max-effects N]
twin predict --model calibrated.toml --data joints.csv --out points.csv

``twin identify`` runs the closed loop by default (geometric identification, then effects
the residuals show, :mod:`calibration.effects.closed_loop`); ``--no-effects`` stops after the
geometry.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration.effects.calibrate import CalibrationResult, calibrate, start_for
from calibration.effects.model_effects import load_checked_robot
from calibration.errors import (
    CalibrationError,
    DataFileError,
    IdentificationError,
    OptionError,
    OutputFileError,
)
from calibration.identify.campaign_files import (
    Campaign,
    read_campaign,
    read_joint_readings,
    write_points,
)
from calibration.identify.identifiability import NO_EFFECT
from calibration.identify.identification import (
    LOSSES,
    RAN_AWAY,
    START_METHODS,
    IdentificationResult,
    tracker_sigma_mm,
)
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel
from calibration.model.unit_plausibility import (
    OVERRIDE,
    check_campaign_units,
    check_joint_angle_units,
)
from edges.options import integer
from edges.outputs import OutputSet

if TYPE_CHECKING:  # the closed loop loads when a command runs it, not for --help
    from calibration.effects.closed_loop import ClosedLoopResult, LoopSettings

FloatArray = NDArray[np.float64]


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    _register_identify(sub)
    _register_predict(sub)


def _register_identify(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``twin identify``'s options. Long because it is a flat argparse builder, one option after
    another."""
    p = sub.add_parser(
        "identify",
        help="identify kinematic parameters from a campaign",
        description="Identify the geometry, base pose and tool from campaign.csv (LM) and "
        "write the calibrated robot description.",
    )
    p.add_argument("--robot", required=True, help="nominal robot: preset name or .toml path")
    p.add_argument("--data", required=True, help="campaign.csv")
    p.add_argument("--out", required=True, help="calibrated robot description (.toml)")
    p.add_argument("--report", metavar="DIR", help="write report.json, report.md and PNGs here")
    p.add_argument("--skip-bad", action="store_true", help="skip bad rows (counted in the report)")
    p.add_argument("--loss", default="linear", choices=list(LOSSES), help="robust loss")
    p.add_argument(
        "--f-scale-mm",
        type=float,
        help="robust loss scale (default: 3 σ estimated from the residuals)",
    )
    p.add_argument(
        "--start",
        default="auto",
        choices=["auto", *START_METHODS],
        help="base start: the description's guess, or a rigid registration "
        "(auto: the guess when the description has a [base] table)",
    )
    p.add_argument(
        "--tracker-mpe-um",
        metavar="A,B",
        help="weight each point by the tracker's data-sheet MPE ±(A µm + B µm/m · distance), "
        "taken as 2σ (e.g. 15,6); default: all points weigh the same",
    )
    p.add_argument(
        "--no-effects",
        action="store_true",
        help="the geometric model alone (default: also search the residuals for effects the "
        "geometric model lacks and add the significant ones)",
    )
    p.add_argument(
        "--no-learned",
        action="store_true",
        help="no learned residual stage after the effects (default: a Gaussian process of "
        "what the effects leave, kept when it lowers the cross-validated error significantly)",
    )
    p.add_argument(
        "--effect-kinds",
        metavar="K,K",
        help="offer only these candidate effect kinds (default: all; see docs/closed-loop.md)",
    )
    p.add_argument(
        "--effects-alpha",
        type=float,
        default=1e-3,
        help="family-wise false-positive probability of one search round (default 1e-3)",
    )
    p.add_argument(
        "--max-effects",
        type=integer(0),
        default=None,
        metavar="N",
        help="add at most N effects (default 6); the report names the best candidate left",
    )
    p.add_argument(
        OVERRIDE,
        action="store_true",
        help="do not refuse tracker points or joint angles that look like other units "
        "(metres, radians; see docs/identification.md)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=run_identify)


def _register_predict(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    q = sub.add_parser(
        "predict",
        help="predict tracker points from joint angles",
        description="Predict TCP points in the tracker frame from joints.csv with a "
        "calibrated model (geometry, base, tool and every modelled effect).",
    )
    q.add_argument("--model", required=True, help="calibrated robot description (.toml)")
    q.add_argument(
        "--data", required=True, help="joints.csv: pose,t_s,q1_deg..qN_deg (temp_c optional)"
    )
    q.add_argument("--out", required=True, help="points.csv to write")
    q.add_argument("--skip-bad", action="store_true", help="skip bad rows (counted on stderr)")
    q.add_argument(
        OVERRIDE, action="store_true", help="do not refuse joint angles that look like radians"
    )
    q.set_defaults(func=run_predict)


#: Fewer distinct identification poses cannot determine the base and tool (registration
#: needs 4 non-coplanar points); the method's campaigns have 100 (docs/identification.md).
MIN_DISTINCT_POSES = 4


def _limits(desc: RobotDescription) -> list[tuple[float, float]]:
    return [(j.lower_deg, j.upper_deg) for j in desc.joints]


def _mpe(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise OptionError(f"--tracker-mpe-um: expected 'A,B' (µm, µm/m), got {text!r}") from None
    if not (np.isfinite(a) and np.isfinite(b) and a > 0 and b >= 0):
        raise OptionError(f"--tracker-mpe-um: need A > 0 and B >= 0, got {text!r}")
    return a, b


def _check_options(args: argparse.Namespace) -> None:
    """Option values a parser cannot judge, refused before anything is read or fitted."""
    f = args.f_scale_mm
    if f is not None and not (np.isfinite(f) and f > 0):
        raise OptionError(f"--f-scale-mm: need a finite scale > 0 mm, got {f}")
    if not 0.0 < args.effects_alpha < 1.0:
        raise OptionError(f"--effects-alpha: need 0 < A < 1, got {args.effects_alpha}")
    if args.tracker_mpe_um:
        _mpe(args.tracker_mpe_um)
    _loop_settings(args)


def _loop_settings(args: argparse.Namespace) -> LoopSettings:
    from calibration.effects.loop_settings import LoopSettings

    kinds = None
    if args.effect_kinds:
        kinds = tuple(k.strip() for k in args.effect_kinds.split(",") if k.strip())
    try:
        settings = LoopSettings(alpha=args.effects_alpha, kinds=kinds)
    except ValueError as exc:
        raise OptionError(f"--effect-kinds: {exc}") from None
    if args.max_effects is None:
        return settings
    return replace(settings, max_effects=args.max_effects)


def _robot_file(name: str) -> str | None:
    """The robot description's path when it is a file (a preset name is not an input)."""
    return name if Path(name).exists() else None


def run_identify(args: argparse.Namespace) -> int:
    def say(text: str) -> None:
        if not args.quiet:
            print(f"twin identify: {text}", file=sys.stderr, flush=True)

    _check_options(args)
    with OutputSet([args.data, _robot_file(args.robot)], error=OutputFileError) as outputs:
        out_path = outputs.file(args.out, "--out")
        report_dir = outputs.directory(args.report, "--report") if args.report else None
        lines = _identify(args, out_path, report_dir, say)
    for line in lines:
        print(line)
    return 0


def _identify(
    args: argparse.Namespace,
    out_path: Path,
    report_dir: Path | None,
    say: Callable[[str], None],
) -> list[str]:
    """The identification, writing to the staged ``out_path`` and ``report_dir``; the
    lines to print once the outputs are in place."""
    desc = load_checked_robot(args.robot)
    campaign = _checked_campaign(args, desc, say)
    idm = campaign.mask("identify")
    start = start_for(desc, args.start)
    say(
        f"{int(idm.sum())} identification and {int(campaign.mask('validate').sum())} "
        f"validation poses; base start: {start}"
    )
    point_sigma = None
    if args.tracker_mpe_um:
        mpe_um, mpe_um_per_m = _mpe(args.tracker_mpe_um)
        point_sigma = tracker_sigma_mm(campaign.xyz_mm[idm], mpe_um, mpe_um_per_m)
    narrator = _Narrator(say)
    try:
        cal = calibrate(
            desc,
            campaign,
            effects=not args.no_effects,
            learned=not args.no_learned,
            start=start,
            loss=args.loss,
            f_scale_mm=args.f_scale_mm,
            point_sigma_mm=point_sigma,
            loop_settings=_loop_settings(args),
            progress=narrator.lm_iteration,
            say=say,
            on_geometric=narrator.geometric_done,
        )
    except _NotConverged:
        raise
    except CalibrationError as exc:  # the data cannot be fitted: say which data
        raise IdentificationError(f"{args.data}: {exc}") from None
    _require_converged(cal.result, "final")
    cal.description.save(out_path)
    return _reported(args, desc, campaign, cal, report_dir, say)


@dataclass(frozen=True)
class _Narrator:
    """Tells the identification's progress through ``say``."""

    say: Callable[[str], None]

    def lm_iteration(self, it: int, norm: float, mu: float) -> None:
        self.say(f"LM iteration {it}: error norm {norm:.6f} mm, damping {mu:.1e}")

    def geometric_done(self, result: IdentificationResult) -> None:
        """The geometric identification converged (else it stops the command): what it
        identified and which parameters it dropped for no effect or running away."""
        _require_converged(result, "geometric")
        ana = result.identifiability
        self.say(
            f"identified {ana.rank} of {len(ana.parameter_names)} parameters "
            f"({len(ana.dropped)} dropped), condition number {ana.condition_number:.1f}; "
            f"{result.optimize_result.message}"
        )
        for d in ana.dropped:
            if d.reason.startswith((NO_EFFECT, RAN_AWAY)):
                self.say(f"dropped {d.name}: {d.reason}")


def _reported(
    args: argparse.Namespace,
    desc: RobotDescription,
    campaign: Campaign,
    cal: CalibrationResult,
    report_dir: Path | None,
    say: Callable[[str], None],
) -> list[str]:
    """The report written to the staged ``report_dir`` (when asked for); the lines to print."""
    from calibration.effects.identification_report import build_report
    from calibration.effects.report_rendering import write_report

    result, loop = cal.result, cal.loop
    doc, errors = build_report(
        result,
        desc,
        campaign,
        robot_source=str(args.robot),
        calibrated_path=str(args.out),
        closed_loop=loop,
        learned=cal.learned,
    )
    doc["solver"]["point_weights"] = (
        f"tracker MPE ±({args.tracker_mpe_um.replace(',', ' µm + ')} µm/m) as 2σ"
        if args.tracker_mpe_um
        else "none (all points weigh the same)"
    )
    lines = _result_lines(doc, loop, campaign)
    if cal.learned is not None:
        st = cal.learned
        kept = "kept" if st.accepted else "not kept"
        lines.append(
            f"unexplained residual (learned): {kept}, {st.reason}; explains "
            f"{100 * st.share:.1f} % of the traced mean square (leave-one-out)"
            + (
                f", validate mean AP {st.validate_before_mm:.4f} -> {st.validate_after_mm:.4f} mm"
                if np.isfinite(st.validate_before_mm)
                else ""
            )
        )
    lines.append(f"wrote {args.out}")
    if report_dir is not None:
        started = time.perf_counter()
        paths = write_report(report_dir, doc, errors, closed_loop=loop)
        say(f"report written in {time.perf_counter() - started:.1f} s")
        lines.append(f"wrote report to {args.report} ({len(paths)} files)")
    return lines


def _checked_campaign(
    args: argparse.Namespace, desc: RobotDescription, say: Callable[[str], None]
) -> Campaign:
    """The campaign file, read against the robot's limits, its units checked (unless
    ``--no-unit-check``), with enough distinct identification poses."""
    campaign = read_campaign(
        args.data, desc.n_joints, limits_deg=_limits(desc), skip_bad=args.skip_bad
    )
    nominal = KinematicModel.from_description(desc)
    if not args.no_unit_check:
        check_campaign_units(
            str(args.data), campaign.q_deg, campaign.xyz_mm, nominal, _limits(desc)
        )
    if campaign.skipped:
        say(f"skipped {len(campaign.skipped)} bad row(s)")
        for s in campaign.skipped[:10]:
            say(f"  {s}")
    idm = campaign.mask("identify")
    if not idm.any():
        raise DataFileError(f"{args.data}: no rows with set 'identify'")
    distinct = len(np.unique(np.round(campaign.q_deg[idm], 6), axis=0))
    if distinct < MIN_DISTINCT_POSES:
        raise DataFileError(
            f"{args.data}: only {distinct} distinct pose(s) among the 'identify' rows; the "
            f"geometry needs at least {MIN_DISTINCT_POSES} (the method uses 100)"
        )
    return campaign


def _result_lines(
    doc: dict[str, Any], loop: ClosedLoopResult | None, campaign: Campaign
) -> list[str]:
    """What ``twin identify`` prints: the loop's stages, before → after per set."""
    lines = []
    if loop is not None:
        set_name = "validate" if "validate" in loop.final.errors_mm else "identify"
        for st in doc["closed_loop"]["stages"]:
            ap = st["sets"][set_name]["AP"]
            lines.append(f"stage {st['label']}: {set_name} mean AP {ap['mean']:.4f} mm")
        stop = doc["closed_loop"]["stopped"]
        best = stop["best_remaining"]
        left = f" (best remaining: {best['effect']})" if best else ""
        lines.append(f"stopped: {stop['reason']}{left}")
        second = doc["closed_loop"].get("second_search")
        if second:
            lines.append(f"searched again with gravity first: {second['text']}")
        for c in stop["not_identifiable"]:
            lines.append(f"not identifiable: {c['effect']}")
    for name, s in doc["sets"].items():
        b, a = s["before"]["AP"], s["after"]["AP"]
        lines.append(
            f"{name}: mean AP {b['mean']:.4f} -> {a['mean']:.4f} mm, "
            f"max {b['max']:.4f} -> {a['max']:.4f} mm ({s['n_poses']} poses)"
        )
    if doc["outlier_poses"]:
        lines.append(f"outlier poses: {', '.join(doc['outlier_poses'])}")
    if campaign.skipped:
        lines.append(f"skipped {len(campaign.skipped)} bad row(s)")
    return lines


class _NotConverged(IdentificationError):
    """A fit that did not converge (its message is whole: no file prefix added)."""


def _require_converged(result: IdentificationResult, which: str) -> None:
    """A fit that did not converge is an error (exit 2, nothing written). Converged: the
    error norm's change fell to tol_mm, or no step of any damping lowers a finite error
    norm (LM status −1). Not converged: the iteration limit. A fit that ran away beyond
    repair has already raised in identify()."""
    if not result.success:
        opt = result.optimize_result
        raise _NotConverged(
            f"the {which} fit did not converge: {opt.message} (status {opt.status}, "
            f"{opt.nit} iterations)"
        )


def run_predict(args: argparse.Namespace) -> int:
    from calibration.effects.model_effects import (
        missing_temperature_warning,
        predict_tcp_sd,
        times_outside_span,
    )

    with OutputSet([args.data, args.model], error=OutputFileError) as outputs:
        out_path = outputs.file(args.out, "--out")
        desc = load_checked_robot(args.model)
        readings = read_joint_readings(
            args.data, desc.n_joints, limits_deg=_limits(desc), skip_bad=args.skip_bad
        )
        if not args.no_unit_check:
            check_joint_angle_units(str(args.data), readings.q_deg, _limits(desc))
        q = np.radians(readings.q_deg)
        pred = predict_tcp_sd(desc, q, readings.t_s, temp_c=readings.temp_c)
        write_points(out_path, readings.pose, pred.points_mm, pred.sd_mm, pred.beyond_reach)
    outside, span = times_outside_span(desc, readings.t_s)
    if outside and span is not None:
        print(
            f"twin predict: warning: {outside} row(s) outside the campaign's time span "
            f"[{span[0]:.0f}, {span[1]:.0f}] s: the drift terms are held at their value at "
            "the nearer end (a polynomial in time is never extrapolated)",
            file=sys.stderr,
        )
    no_temperature = missing_temperature_warning(desc, readings.temp_c)
    if no_temperature:
        print(f"twin predict: warning: {no_temperature}", file=sys.stderr)
    far = int(np.count_nonzero(pred.beyond_reach))
    if far:
        print(
            f"twin predict: {far} row(s) outside the learned residual stage's reach (kernel "
            "distance to the nearest identification pose): the traced model and its standard "
            "deviation (beyond_reach = 1)",
            file=sys.stderr,
        )
    if readings.skipped:
        print(f"twin predict: skipped {len(readings.skipped)} bad row(s)", file=sys.stderr)
        for s in readings.skipped[:10]:
            print(f"twin predict:   {s}", file=sys.stderr)
    print(f"wrote {args.out}: {len(readings)} points")
    return 0
