"""The twin on recorded (or collected live) streams: phases → maps → campaign → twin.

The data flow one way, in memory, as typed values:

1. :func:`~calibration.twin.campaign_measurement.measure_campaign`: the campaign's phases
   found in the streams, tracker and grating samples paired per dwell →
   ``CampaignMeasurements`` (sweeps with every joint's reading at each stop, Home
   returns, poses);
2. :func:`~calibration.twin.fit_rounds.calibrate_twin`: grating scales in chain order
   (:mod:`calibration.scales.chain_scale`), the poses read through them
   (``campaign_from_scales``), the identification and the closed loop, whose gravity term
   knows the maps absorbed each swept link's deflection in its sweep configuration (the
   link turns after its ring under its own weight, which no grating sees); when the loop
   finds gravity deflection, the maps are refitted with it taken out of the sweeps
   (:mod:`calibration.twin.sweep_deflections`) and everything downstream runs again: a
   joint fit of the maps and the loop's gravity term;
3. the documents of the files, still in memory (:mod:`calibration.twin.run_documents`):
   ``export_campaign`` (``twin export``) gives a ``CampaignExport``, :func:`run_twin`
   (``twin run``) a :class:`TwinRun`; nothing here writes a file
   (:mod:`calibration.cli.run_files` does, at the command line's edge).

Determinism: the same streams give bit-identical files. Nothing of the run's own clock goes
into ``calibrated.toml``, ``report.json``, ``phases.json`` or the CSV files (the solver
times are removed from ``report.json``; they stay in ``report.md`` and ``run.json``); the
closed loop's CV folds use its fixed seed; every list is in time or joint order.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from calibration.model.description import RobotDescription, load_robot
from calibration.twin.campaign_measurement import (
    CampaignMeasurements,
    Say,
    measure_campaign,
    quiet,
)
from calibration.twin.fit_rounds import TwinCalibration, calibrate_twin
from calibration.twin.phase_detection import PhaseOptions
from calibration.twin.run_documents import CampaignExport, report_document, stage_table
from calibration.twin.streams import CellStreams

if TYPE_CHECKING:
    from calibration.effects.identification_report import SetErrors


@dataclass(frozen=True, eq=False)
class TwinRun:
    """``twin run``'s result, in memory: the nominal robot, the campaign's files
    (:class:`CampaignExport`, of the last round's maps), the joint fit, the report's
    document (the solver times included: report.md shows them) and per-set errors, the
    stage table, and the wall times (s) of the measurements and of the whole run."""

    robot: RobotDescription
    export: CampaignExport
    calibration: TwinCalibration
    report: dict[str, Any]
    errors: tuple[SetErrors, ...]
    stage_table: str
    export_s: float
    elapsed_s: float

    @property
    def measurements(self) -> CampaignMeasurements:
        return self.export.measurements

    @property
    def calibrated(self) -> RobotDescription:
        """The twin: the calibrated description (calibrated.toml)."""
        return self.calibration.calibrated

    @property
    def success(self) -> bool:
        """Whether the twin's identification converged (``twin run``'s exit code)."""
        return bool(self.calibration.final.result.success)


def run_twin(
    streams: CellStreams,
    robot: str | RobotDescription,
    *,
    effects: bool = True,
    max_effects: int | None = None,
    phase_options: PhaseOptions | None = None,
    say: Say = quiet,
) -> TwinRun:
    """Measurements, the twin (maps and loop fitted jointly) and its documents; writes
    nothing (:mod:`calibration.cli.run_files` writes the files). ``robot``: a preset name, a
    description file or a description; ``max_effects``: at most this many effects (None:
    the loop's default); ``phase_options``: how the phases are found (None: defaults)."""
    started = time.perf_counter()
    desc = load_robot(robot) if isinstance(robot, str) else robot
    meas = measure_campaign(streams, desc, phase_options=phase_options, say=say)
    export_s = time.perf_counter() - started
    say("scale calibration (chain order), identification and closed loop")
    settings = None
    if max_effects is not None:
        from calibration.effects.closed_loop import (
            LoopSettings,  # loaded with the loop, as calibrate does
        )

        settings = LoopSettings(max_effects=max_effects)
    twin = calibrate_twin(meas, effects=effects, loop_settings=settings, say=say)
    export = CampaignExport.of(meas, twin.final.scales, twin.final.campaign)
    source = robot if isinstance(robot, str) else desc.name
    doc, errors = report_document(desc, source, twin, export.phases)
    elapsed_s = time.perf_counter() - started
    return TwinRun(desc, export, twin, doc, tuple(errors), stage_table(doc), export_s, elapsed_s)
