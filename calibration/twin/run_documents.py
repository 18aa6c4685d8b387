"""The documents of the campaign's files and of the report, in memory (written by
:mod:`calibration.cli.run_files` at the command line's edge): home.csv and sweep.csv
tables, scale.toml and phases.json documents, :class:`CampaignExport` and
:func:`export_campaign` (``twin export``), the stage table and the report's document.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from calibration.identify.campaign_files import Campaign
from calibration.model.description import RobotDescription
from calibration.scales.chain_scale import ScaleCampaignResult, calibrate_scales
from calibration.scales.grating_scale import ScaleOptions
from calibration.scales.scale_files import ScaleCalibration, scale_document
from calibration.twin.campaign_measurement import (
    ENCODER_COUNTS_PER_REV,
    CampaignMeasurements,
    Say,
    campaign_from_scales,
    measure_campaign,
    quiet,
)
from calibration.twin.pairing import PairingOptions
from calibration.twin.phase_detection import PhaseOptions
from calibration.twin.streams import CellStreams

if TYPE_CHECKING:
    from calibration.effects.identification_report import SetErrors
    from calibration.twin.fit_rounds import TwinCalibration

#: The campaign's files (``twin export``, and ``twin run`` beside its other outputs) by key,
#: as phases.json, scale.toml and run.json name them.
CAMPAIGN_FILES = {
    "home": "home.csv",
    "sweep": "sweep.csv",
    "scale": "scale.toml",
    "campaign": "campaign.csv",
    "phases": "phases.json",
}
#: The twin's description, as the report names it.
CALIBRATED_FILE = "calibrated.toml"

#: A CSV file's header and rows.
Table = tuple[list[str], list[list[Any]]]


def home_table(meas: CampaignMeasurements) -> Table:
    """home.csv's header and rows: every Home return's counter value, by joint and trial."""
    rows = [
        [j, t + 1, int(c)]
        for j in sorted(meas.home_counts)
        for t, c in enumerate(meas.home_counts[j])
    ]
    return ["joint", "trial", "counts"], rows


def sweep_table(meas: CampaignMeasurements) -> Table:
    """sweep.csv's header and rows: every paired sweep stop, with every joint's counter
    value (the chain's motion)."""
    rows = []
    for j in sorted(meas.sweeps):
        sw = meas.sweeps[j]
        assert sw.chain_counts is not None
        for k in range(sw.n_stops):
            rows.append(
                [
                    j,
                    sw.pass_name[k],
                    int(sw.step[k]),
                    int(sw.counts[k]),
                    *(f"{v:.6f}" for v in sw.points_mm[k]),
                    *(int(c) for c in sw.chain_counts[k]),
                ]
            )
    chain_columns = [f"g{i}_counts" for i in range(1, meas.n_joints + 1)]
    return ["joint", "pass", "step", "counts", "x_mm", "y_mm", "z_mm", *chain_columns], rows


def scale_toml_document(meas: CampaignMeasurements, scales: ScaleCampaignResult) -> dict[str, Any]:
    """scale.toml's document: the maps, naming the sweep and Home files they came from."""
    return scale_document(
        scales,
        robot=meas.robot.name,
        metadata={
            "sweep_file": CAMPAIGN_FILES["sweep"],
            "home_file": CAMPAIGN_FILES["home"],
            "source": "twin",
        },
        counts_per_mm=ScaleOptions().counts_per_mm,
    )


def phases_document(meas: CampaignMeasurements, scales: ScaleCampaignResult) -> dict[str, Any]:
    """phases.json's document: what was found in the streams, the maps' summary per joint,
    the joints without a map and the campaign's sets and clock origin."""
    summary = dict(meas.summary)
    summary["scale"] = {
        str(r.joint): {
            "counts_per_deg": round(r.scale.counts_per_deg, 6),
            "terms": list(r.scale.terms),
            "residual_rms_arcsec": round(r.residual_rms_arcsec, 4),
            "circle_only_residual_rms_arcsec": round(
                scales.chain[r.joint].circle_only_residual_arcsec, 4
            )
            if r.joint in scales.chain
            else round(r.residual_rms_arcsec, 4),
            "notes": list(r.notes),
        }
        for r in scales
    }
    summary["uncalibrated_joints"] = [
        j for j in range(1, meas.n_joints + 1) if j not in meas.sweeps
    ]
    summary["campaign"] = {
        "identify": sum(p.set == "identify" for p in meas.poses),
        "validate": sum(p.set == "validate" for p in meas.poses),
        "t0_ns": int(meas.phases.dwells[0].t0_ns),
    }
    return summary


@dataclass(frozen=True, eq=False)
class CampaignExport:
    """The campaign as its files hold it, in memory: the measurements, the scale maps, the
    poses read through them, and the documents of phases.json and scale.toml
    (:data:`CAMPAIGN_FILES`; written by :mod:`calibration.cli.run_files`)."""

    measurements: CampaignMeasurements
    scales: ScaleCampaignResult
    campaign: Campaign
    phases: dict[str, Any]
    scale_document: dict[str, Any]

    @classmethod
    def of(
        cls, meas: CampaignMeasurements, scales: ScaleCampaignResult, campaign: Campaign
    ) -> CampaignExport:
        return cls(
            meas, scales, campaign, phases_document(meas, scales), scale_toml_document(meas, scales)
        )

    def scale_calibration(self) -> ScaleCalibration:
        """The maps as :func:`~calibration.scales.scale_files.read_scale_toml` reads scale.toml."""
        doc = self.scale_document
        ranges = {
            int(t["joint"]): (
                float(t["calibrated_range_deg"][0]),
                float(t["calibrated_range_deg"][1]),
            )
            for t in doc["joint"]
            if "calibrated_range_deg" in t
        }
        joints = {r.joint: r.scale for r in self.scales}
        return ScaleCalibration(joints, doc.get("robot"), dict(doc.get("calibration", {})), ranges)


def export_campaign(
    streams: CellStreams,
    robot: RobotDescription,
    *,
    phase_options: PhaseOptions | None = None,
    pairing_options: PairingOptions | None = None,
    scale_options: ScaleOptions | None = None,
    encoder_counts_per_rev: int = ENCODER_COUNTS_PER_REV,
    say: Say = quiet,
) -> CampaignExport:
    """``twin export``: the measurements and the scale maps in chain order, without the
    loop's gravity feedback (:func:`calibrate_twin` has it)."""
    meas = measure_campaign(
        streams,
        robot,
        phase_options=phase_options,
        pairing_options=pairing_options,
        encoder_counts_per_rev=encoder_counts_per_rev,
        say=say,
    )
    say("scale calibration")
    limits = [(j.lower_deg, j.upper_deg) for j in robot.joints]
    scales = calibrate_scales(
        meas.sweeps, meas.home_counts, home_deg=robot.home, limits_deg=limits,
        options=scale_options,
    )  # fmt: skip
    return CampaignExport.of(meas, scales, campaign_from_scales(meas, scales))


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


def report_document(
    robot: RobotDescription,
    robot_source: str,
    twin: TwinCalibration,
    phases: dict[str, Any],
) -> tuple[dict[str, Any], list[SetErrors]]:
    """The identification report of the twin (the last round), with what ``twin run``
    adds (``twin_run``: phases, lost stops and intervals, the joint fit's rounds), and the
    per-set errors it was made from (``phases``: phases.json's document)."""
    from calibration.effects.identification_report import build_report

    final = twin.final
    doc, errors = build_report(
        final.result,
        robot,
        final.campaign,
        robot_source=robot_source,
        calibrated_path=CALIBRATED_FILE,
        closed_loop=final.loop,
        learned=final.learned,
    )
    doc["solver"]["point_weights"] = "none (all points weigh the same)"
    doc["twin_run"] = {
        "phases": phases["phases"],
        "stops_lost": len(phases["stops_lost"]),
        "lost_intervals": phases["lost_intervals"],
        "recording_complete": phases["recording_complete"],
        "recording_note": phases["note"],
        "joint_fit": twin.summary(),
    }
    return doc, errors
