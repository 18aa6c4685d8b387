"""The one way from a campaign to a calibrated robot: identification, then the closed loop.

``twin identify`` (a campaign file), ``twin run`` (each round of its joint fit with the
scale maps) and library users call :func:`calibrate`; it returns a
:class:`CalibrationResult` holding the geometric identification, the closed loop (None
without effects) and the calibrated description. Like ``scipy.optimize.least_squares``: a
plain function over typed values, a rich result, no files.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from calibration.identify.campaign_files import Campaign
from calibration.model.description import RobotDescription, TrackingDescription

if TYPE_CHECKING:  # the solvers load when calibrate runs
    from calibration.effects.closed_loop import ClosedLoopResult, LoopSettings
    from calibration.effects.learned_residual import LearnedStage
    from calibration.identify.identification_result import IdentificationResult
    from calibration.identify.levenberg_marquardt import ProgressCallback


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """``geometric``: the identification of the geometry alone; ``loop``: the closed loop
    (None when effects were not asked for); ``description``: the calibrated robot (the
    loop's model with its ``[[effect]]`` tables, or the geometry alone)."""

    geometric: IdentificationResult
    loop: ClosedLoopResult | None
    description: RobotDescription
    #: the learned residual stage's decision (None: not tried; it follows the loop)
    learned: LearnedStage | None = None

    @property
    def result(self) -> IdentificationResult:
        """The final identification: the loop's, or the geometric one without it."""
        return self.geometric if self.loop is None else self.loop.result


def start_for(description: RobotDescription, start: str = "auto") -> str:
    """The identification's base start: ``auto`` is the description's base when it states
    one, else a registration of the points."""
    if start != "auto":
        return start
    return "description" if description.base is not None else "registration"


def calibrate(
    description: RobotDescription,
    campaign: Campaign,
    *,
    effects: bool = True,
    start: str = "auto",
    loss: str = "linear",
    f_scale_mm: float | None = None,
    point_sigma_mm: ArrayLike | None = None,
    loop_settings: LoopSettings | None = None,
    sweep_referenced: bool = False,
    sweep_configurations: ArrayLike | None = None,
    learned: bool = True,
    progress: ProgressCallback | None = None,
    say: Callable[[str], None] | None = None,
    on_geometric: Callable[[IdentificationResult], None] | None = None,
) -> CalibrationResult:
    """Identify ``description``'s geometry from the campaign's ``identify`` rows, then (with
    ``effects``) run the closed loop on the whole campaign.

    ``loss``, ``f_scale_mm``, ``point_sigma_mm`` ``(m_identify,)`` and ``progress`` go to
    the identification (:func:`~calibration.identify.identification.identify`) and the loop;
    ``sweep_referenced`` and ``sweep_configurations`` ``(n, n)`` rad (each joint's sweep
    configuration; None: Home) to the loop
    (:func:`~calibration.effects.closed_loop.run_closed_loop`).
    ``on_geometric`` sees the geometric result before the loop starts (a caller's checks
    and messages, in order). With ``effects`` and ``learned``, the learned residual stage
    follows the loop (:func:`learned_stage_of`). Long for its keyword options, each handed to
    the identification or the loop."""
    from calibration.effects.closed_loop import LoopSettings, run_closed_loop
    from calibration.identify.identification import identify
    from calibration.model.kinematics import KinematicModel

    start = start_for(description, start)
    idm = campaign.mask("identify")
    geometric = identify(
        KinematicModel.from_description(description),
        campaign.q_rad[idm],
        campaign.xyz_mm[idm],
        start=start,
        loss=loss,
        f_scale_mm=f_scale_mm,
        point_sigma_mm=point_sigma_mm,
        progress=progress,
    )
    if on_geometric is not None:
        on_geometric(geometric)
    if not effects:
        calibrated = replace(geometric.model.to_description(description), effects=())
        return CalibrationResult(geometric, None, _tracked(calibrated, geometric, campaign))
    loop = run_closed_loop(
        description,
        campaign,
        start=start,
        loss=loss,
        f_scale_mm=f_scale_mm,
        point_sigma_mm=point_sigma_mm,
        settings=loop_settings or LoopSettings(),
        geometric=geometric,
        say=say,
        sweep_referenced=sweep_referenced,
        sweep_configurations=sweep_configurations,
    )
    calibrated = loop.calibrated_description(description)
    calibrated = _tracked(calibrated, loop.result, campaign)
    if not learned:
        return CalibrationResult(geometric, loop, calibrated)
    stage, calibrated = learned_stage_of(loop, campaign, calibrated)
    if say is not None:
        say(f"learned residual stage: {'accepted' if stage.accepted else 'rejected'}, "
            f"{stage.reason} ({stage.fit_s:.1f} s)")  # fmt: skip
    return CalibrationResult(geometric, loop, calibrated, stage)


def _tracked(
    calibrated: RobotDescription, result: IdentificationResult, campaign: Campaign
) -> RobotDescription:
    return replace(calibrated, tracking=tracking_description(result, campaign))


def tracking_description(result: IdentificationResult, campaign: Campaign) -> TrackingDescription:
    """What ``twin track`` needs from this calibration (``[tracking]``): the identified
    geometric parameters, the fit's σ, the identification poses and the validation poses
    (the identification poses when the campaign has none) for the alarm."""
    names = result.identifiability.parameter_names
    n_geo = result.model.n_parameters
    identified = tuple(names[i] for i in result.identifiability.free_indices if i < n_geo)
    idm, val = campaign.mask("identify"), campaign.mask("validate")
    reference = campaign.q_deg[val] if val.any() else campaign.q_deg[idm]

    def rows(q_deg: ArrayLike) -> tuple[tuple[float, ...], ...]:
        return tuple(tuple(round(float(v), 9) for v in r) for r in np.asarray(q_deg))

    return TrackingDescription(
        identified=identified,
        sigma_mm=float(result.sigma_mm),
        identify_deg=rows(campaign.q_deg[idm]),
        reference_deg=rows(reference),
    )


def learned_stage_of(
    loop: ClosedLoopResult, campaign: Campaign, calibrated: RobotDescription
) -> tuple[LearnedStage, RobotDescription]:
    """The learned residual stage on the loop's final residuals (identification poses fit,
    validation poses check), and ``calibrated`` with its ``[residual]`` table: the traced
    model's standard deviation (from the validation residuals when there are any) and the
    stage when accepted."""
    import numpy as np

    from calibration.effects.learned_residual import learned_stage
    from calibration.model.description import ResidualDescription

    errors = loop.final.errors_mm
    val = "validate" in errors
    stage = learned_stage(
        campaign.q_rad[campaign.mask("identify")],
        errors["identify"],
        campaign.q_rad[campaign.mask("validate")] if val else None,
        errors["validate"] if val else None,
    )
    traced_sd = float(np.sqrt(np.mean(errors["validate" if val else "identify"] ** 2)))
    residual = ResidualDescription(traced_sd_mm=traced_sd, learned=stage.description)
    return stage, replace(calibrated, residual=residual)
