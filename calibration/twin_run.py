"""The twin on recorded (or collected live) streams: phases → files → calibrations → reports.

:func:`export_campaign` finds the campaign's phases in the streams, pairs tracker and
grating samples, and writes the documented files (``home.csv``, ``sweep.csv``; then, with
the scale calibration, ``scale.toml`` and ``campaign.csv``) plus ``phases.json`` (what was
found, what was rejected and why, lost intervals). :func:`run_twin` continues with the
identification and the closed loop (the library functions ``twin identify`` uses) and
writes ``calibrated.toml`` and the report.

Determinism: the same streams give bit-identical files. Nothing of the run's own clock goes
into ``calibrated.toml``, ``report.json``, ``phases.json`` or the CSV files (the solver
times are removed from ``report.json``; they stay in ``report.md`` and ``run.json``); the
closed loop's CV folds use its fixed seed; every list is in time or joint order.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calibration.campaign_files import Campaign, read_campaign, write_campaign
from calibration.description import RobotDescription, load_robot
from calibration.errors import CalibrationError
from calibration.grating_scale import COUNTER_MODULUS, ScaleOptions
from calibration.pairing import PairingOptions, StopMeasurement, pair_dwell
from calibration.phase_detection import PhaseOptions, Phases, find_phases
from calibration.scale_files import write_csv
from calibration.streams import CellStreams

Say = Callable[[str], None]


class TwinRunError(CalibrationError, ValueError):
    """The data do not hold what a calibration needs (named in the message)."""


@dataclass
class ExportResult:
    out: Path
    phases: Phases
    measurements: dict[int, StopMeasurement]
    files: dict[str, Path]
    summary: dict[str, Any]


def _quiet(_text: str) -> None:
    pass


def _counter(value: float) -> int:
    return int(np.rint(value)) % COUNTER_MODULUS


def export_campaign(
    streams: CellStreams,
    robot: RobotDescription,
    out: str | Path,
    *,
    phase_options: PhaseOptions | None = None,
    pairing_options: PairingOptions | None = None,
    scale_options: ScaleOptions | None = None,
    encoder_counts_per_rev: int = 131072,
    say: Say = _quiet,
) -> ExportResult:
    """Write ``home.csv``, ``sweep.csv``, ``scale.toml``, ``campaign.csv``, ``phases.json``."""
    from calibration.cli_scale import calibrate_files
    from calibration.scale_files import scale_document, write_scale_toml

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    g = streams.grating
    n = robot.n_joints
    if g.values.shape[1] != n:
        raise TwinRunError(
            f"{streams.source}: the grating stream has {g.values.shape[1]} strips, "
            f"the robot {robot.name!r} {n} joints"
        )
    say(f"{len(g)} grating, {len(streams.tracker)} tracker samples; finding phases")
    ph = find_phases(g.t_ns, g.values, phase_options)
    s = ph.summary()
    say(
        f"{s['dwells']} dwells: sweeps {s['sweep_stops']}, Home returns {s['home_returns']}, "
        f"poses {s['poses']}, other {s['other_dwells']}"
    )
    popts = pairing_options or PairingOptions()
    needed = sorted({st.dwell for st in ph.sweeps} | {p.dwell for p in ph.poses})
    meas = {
        k: pair_dwell(ph.dwells[k], g, streams.tracker, streams.encoders, popts) for k in needed
    }
    rejected = [
        {
            "dwell": m.dwell,
            "t_ns": m.t_ns,
            "reason": m.reason,
            "pairs": m.n_pairs,
            "beam_broken": m.n_rejected_beam,
            "moving": m.n_rejected_moving,
        }
        for m in meas.values()
        if not m.ok
    ]
    say(f"paired {len(needed) - len(rejected)} of {len(needed)} stops ({len(rejected)} lost)")
    files = {
        "home": out / "home.csv",
        "sweep": out / "sweep.csv",
        "scale": out / "scale.toml",
        "campaign": out / "campaign.csv",
        "phases": out / "phases.json",
    }
    write_csv(
        files["home"],
        ["joint", "trial", "counts"],
        (
            [h.joint, h.trial, _counter(ph.dwells[h.dwell].counts[h.joint - 1])]
            for h in sorted(ph.home_returns, key=lambda h: (h.joint, h.trial))
        ),
    )
    sweep_rows = []
    for st in sorted(ph.sweeps, key=lambda x: (x.joint, x.pass_name != "forward", x.step)):
        m = meas[st.dwell]
        if not m.ok:
            continue
        sweep_rows.append(
            [
                st.joint,
                st.pass_name,
                st.step,
                _counter(m.counts[st.joint - 1]),
                *(f"{v:.6f}" for v in m.point_mm),
            ]
        )
    if not sweep_rows:
        raise TwinRunError(f"{streams.source}: no sweep found (see phases.json)")
    write_csv(
        files["sweep"], ["joint", "pass", "step", "counts", "x_mm", "y_mm", "z_mm"], sweep_rows
    )
    sopts = scale_options or ScaleOptions()
    say("scale calibration")
    summary: dict[str, Any] = {
        "format": "twin-phases/1",
        "source": Path(streams.source).name,
        "recording_complete": streams.complete,
        "note": streams.note,
        "robot": robot.name,
        "phases": s,
        "home_counts": [
            None if not math.isfinite(v) else round(float(v), 3) for v in ph.home_counts
        ],
        "stops_needed": len(needed),
        "stops_lost": rejected,
        "lost_intervals": [_with_seconds(x, g.t_ns[0]) for x in streams.lost()],
    }
    files["phases"].write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    results = calibrate_files(files["sweep"], files["home"], robot, sopts)
    doc = scale_document(
        results,
        robot=robot.name,
        metadata={"sweep_file": "sweep.csv", "home_file": "home.csv", "source": "twin export"},
        counts_per_mm=sopts.counts_per_mm,
    )
    write_scale_toml(files["scale"], doc)
    scales = {r.joint: r.scale for r in results}
    missing = [j for j in range(1, n + 1) if j not in scales]
    summary.update(
        {
            "scale": {
                str(r.joint): {
                    "counts_per_deg": round(r.scale.counts_per_deg, 6),
                    "terms": list(r.scale.terms),
                    "residual_rms_arcsec": round(r.residual_rms_arcsec, 4),
                    "notes": list(r.notes),
                }
                for r in results
            },
            "uncalibrated_joints": missing,
        }
    )
    if missing or not ph.poses:
        files["phases"].write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        what = f"joints {missing} have no sweep" if missing else "no poses found"
        raise TwinRunError(f"{streams.source}: cannot write campaign.csv: {what}")
    pose_ok = [p for p in ph.poses if meas[p.dwell].ok]
    counts = np.array([meas[p.dwell].counts for p in pose_ok])
    q_deg = np.column_stack([scales[j + 1].counts_to_joint_deg(counts[:, j]) for j in range(n)])
    t0 = int(ph.dwells[0].t0_ns)
    enc_deg = None
    if streams.encoders is not None and all(
        meas[p.dwell].encoder_counts is not None for p in pose_ok
    ):
        enc_deg, offsets = _encoder_deg(
            ph, meas, streams, robot, scales, pose_ok, encoder_counts_per_rev
        )
        summary["encoder_zero"] = "mean encoder reading over the Home returns = Home angle"
        summary["encoder_counts_per_rev"] = encoder_counts_per_rev
        summary["encoder_offset_deg"] = [round(float(v), 9) for v in offsets]
    campaign = Campaign(
        source=str(files["campaign"]),
        pose=tuple(p.name for p in pose_ok),
        set=tuple(p.set for p in pose_ok),
        t_s=np.array([(meas[p.dwell].t_ns - t0) * 1e-9 for p in pose_ok]),
        q_deg=q_deg,
        xyz_mm=np.array([meas[p.dwell].point_mm for p in pose_ok]),
        encoder_deg=enc_deg,
    )
    write_campaign(files["campaign"], campaign)
    summary["campaign"] = {
        "identify": sum(p.set == "identify" for p in pose_ok),
        "validate": sum(p.set == "validate" for p in pose_ok),
        "t0_ns": t0,
    }
    files["phases"].write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    say(
        f"wrote {files['home'].name}, {files['sweep'].name}, {files['scale'].name}, "
        f"{files['campaign'].name} ({len(pose_ok)} poses)"
    )
    return ExportResult(out, ph, meas, files, summary)


def _with_seconds(entry: dict[str, Any], t0_ns: int) -> dict[str, Any]:
    e = dict(entry)
    e["t_start_s"] = round((entry["t_start_ns"] - int(t0_ns)) * 1e-9, 6)
    e["t_end_s"] = round((entry["t_end_ns"] - int(t0_ns)) * 1e-9, 6)
    return e


def _encoder_deg(ph, meas, streams, robot, scales, pose_ok, cpr):  # type: ignore[no-untyped-def]
    """Encoder joint angles (deg) of the poses; each joint's zero from the Home returns."""
    n = robot.n_joints
    gear = np.array([j.gear_ratio or 100.0 for j in robot.joints], dtype=float)
    raw = np.array([meas[p.dwell].encoder_counts for p in pose_ok]) / cpr * 360.0 / gear
    enc = streams.encoders
    offsets = np.zeros(n)
    for j in range(n):
        vals = []
        for h in ph.home_returns:
            if h.joint != j + 1:
                continue
            d = ph.dwells[h.dwell]
            a = int(np.searchsorted(enc.t_ns, d.t0_ns))
            b = int(np.searchsorted(enc.t_ns, d.t1_ns, side="right"))
            if b > a:
                vals.append(float(enc.values[a:b, j].mean()) / cpr * 360.0 / gear[j])
        if vals:
            offsets[j] = robot.home[j] - float(np.mean(vals))
        else:  # no Home return: the poses' mean difference to the gratings is zero
            offsets[j] = 0.0
    return raw + offsets[None, :], offsets


# -- the whole run -----------------------------------------------------------------------


def _scrub(obj: Any) -> Any:
    """``obj`` without the run's own timings (keys ``elapsed_s``)."""
    if isinstance(obj, dict):
        return {k: _scrub(v) for k, v in obj.items() if k != "elapsed_s"}
    if isinstance(obj, list):
        return [_scrub(v) for v in obj]
    return obj


def stage_table(doc: dict[str, Any]) -> str:
    """The before/after table: one row per closed-loop stage (validation set)."""
    loop = doc.get("closed_loop")
    rows = []
    if loop:
        stages = loop["stages"]
        set_name = "validate" if "validate" in stages[0]["sets"] else "identify"
        for st in stages:
            ap = st["sets"][set_name]["AP"]
            rows.append((st["label"], ap["mean"], ap["max"], ap["std"]))
    else:
        set_name = "validate" if "validate" in doc["sets"] else "identify"
        s = doc["sets"][set_name]
        rows = [
            (
                "nominal",
                s["before"]["AP"]["mean"],
                s["before"]["AP"]["max"],
                s["before"]["AP"]["std"],
            ),
            (
                "geometric",
                s["after"]["AP"]["mean"],
                s["after"]["AP"]["max"],
                s["after"]["AP"]["std"],
            ),
        ]
    w = max(12, *(len(r[0]) for r in rows))
    lines = [f"{'stage':<{w}}  {set_name + ' mean AP mm':>20}  {'max mm':>9}  {'std mm':>9}"]
    lines += [f"{r[0]:<{w}}  {r[1]:>20.4f}  {r[2]:>9.4f}  {r[3]:>9.4f}" for r in rows]
    return "\n".join(lines)


def run_twin(
    streams: CellStreams,
    robot: str | RobotDescription,
    out: str | Path,
    *,
    effects: bool = True,
    report: bool = True,
    say: Say = _quiet,
) -> dict[str, Any]:
    """Export, scale calibration, identification + closed loop, reports; a run summary."""
    from calibration.closed_loop import LoopSettings, run_closed_loop
    from calibration.identification import identify
    from calibration.identification_report import build_report, write_report
    from calibration.kinematics import KinematicModel

    started = time.perf_counter()
    desc = load_robot(robot) if isinstance(robot, str) else robot
    out = Path(out)
    exp = export_campaign(streams, desc, out, say=say)
    t_export = time.perf_counter() - started
    limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
    campaign = read_campaign(exp.files["campaign"], desc.n_joints, limits_deg=limits)
    campaign = replace(campaign, source="campaign.csv")  # no run paths in the report
    idm = campaign.mask("identify")
    start = "description" if desc.base is not None else "registration"
    say(f"identification: {int(idm.sum())} poses, validation {int((~idm).sum())}")
    nominal = KinematicModel.from_description(desc)
    geometric = identify(nominal, campaign.q_rad[idm], campaign.xyz_mm[idm], start=start)
    loop = None
    if effects:
        say("closed loop: searching the residuals for effects the geometry lacks")
        loop = run_closed_loop(
            desc, campaign, start=start, settings=LoopSettings(), geometric=geometric, say=say
        )
        result = loop.result
        calibrated = loop.calibrated_description(desc)
    else:
        result = geometric
        calibrated = replace(result.model.to_description(desc), effects=())
    calibrated_path = out / "calibrated.toml"
    calibrated.save(calibrated_path)
    doc, errors = build_report(
        result,
        desc,
        campaign,
        robot_source=desc.name if not isinstance(robot, str) else robot,
        calibrated_path="calibrated.toml",
        closed_loop=loop,
    )
    doc["solver"]["point_weights"] = "none (all points weigh the same)"
    doc["twin_run"] = {
        "phases": exp.summary["phases"],
        "stops_lost": len(exp.summary["stops_lost"]),
        "lost_intervals": exp.summary["lost_intervals"],
        "recording_complete": exp.summary["recording_complete"],
    }
    report_dir = out / "report"
    paths: list[Path] = []
    if report:
        say("writing the report (figures)")
        paths = list(write_report(report_dir, doc, errors, closed_loop=loop))
        scale_report = out / "scale-report"
        from calibration.cli_scale import calibrate_files
        from calibration.scale_report import write_report as write_scale_report

        results = calibrate_files(exp.files["sweep"], exp.files["home"], desc, ScaleOptions())
        write_scale_report(results, scale_report, robot=desc.name, metadata={"source": "twin run"})
        paths.append(scale_report)
    report_dir.mkdir(parents=True, exist_ok=True)
    (report_dir / "report.json").write_text(
        json.dumps(_scrub(doc), indent=2, allow_nan=False) + "\n", encoding="utf-8"
    )
    table = stage_table(doc)
    elapsed = time.perf_counter() - started
    run = {
        "calibrated": str(calibrated_path),
        "report": str(report_dir),
        "files": {k: str(v) for k, v in exp.files.items()},
        "stage_table": table,
        "export_s": round(t_export, 3),
        "total_s": round(elapsed, 3),
        "success": bool(result.success),
    }
    (out / "run.json").write_text(json.dumps(run, indent=2) + "\n", encoding="utf-8")
    return run
