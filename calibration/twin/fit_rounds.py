"""The twin's joint fit: scale maps, identification and closed loop, in rounds.

:func:`calibrate_twin` (the rules in its docstring) gives :class:`TwinCalibration`, the
rounds (:class:`TwinRound`) of which the last is the twin; what each round takes out of
the sweeps comes from :func:`~calibration.twin.sweep_deflections.sweep_deflections`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration.effects.calibrate import calibrate
from calibration.identify.campaign_files import Campaign
from calibration.model.description import RobotDescription
from calibration.scales.chain_scale import ScaleCampaignResult, calibrate_scales, with_load_notes
from calibration.scales.grating_scale import ScaleOptions
from calibration.twin.campaign_measurement import (
    CampaignMeasurements,
    Say,
    campaign_from_scales,
    quiet,
)
from calibration.twin.sweep_configuration import sweep_configurations
from calibration.twin.sweep_deflections import sweep_deflections

if TYPE_CHECKING:
    from calibration.effects.closed_loop import ClosedLoopResult, LoopSettings
    from calibration.effects.learned_residual import LearnedStage
    from calibration.identify.identification import IdentificationResult

FloatArray = NDArray[np.float64]

#: The joint fit's rounds at most: round 1 (maps from the sweeps as they are) and up to two
#: more with the loop's modelled gravity deflection taken out of the sweeps.
MAX_ROUNDS = 3

#: The share of a round's newly found deflection that the next round takes out, the rest
#: staying at what this round took out: ½, the mean of the two. The rounds over-correct
#: (a deflection taken out too large comes back too small, and so on: they alternate about
#: the fixed point), and the mean of two alternating estimates is the fixed point's own;
#: a fixed point of the damped rounds is one of the undamped ones.
DEFLECTION_STEP = 0.5


@dataclass(frozen=True, eq=False)
class TwinRound:
    """One round of the joint fit: maps, the campaign read through them, the twin."""

    scales: ScaleCampaignResult
    campaign: Campaign
    geometric: IdentificationResult
    loop: ClosedLoopResult | None
    deflection_rad: dict[int, FloatArray] | None  # taken out of each joint's sweep (S, n)
    calibrated: RobotDescription  # this round's twin (calibration.effects.calibrate)
    learned: LearnedStage | None = None  # its learned residual stage's decision

    @property
    def result(self) -> IdentificationResult:
        return self.geometric if self.loop is None else self.loop.result

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "deflection_taken_out_of_sweeps": self.deflection_rad is not None,
            "scale_residual_rms_arcsec": {
                str(r.joint): round(r.residual_rms_arcsec, 4) for r in self.scales
            },
            "scale_terms": {str(r.joint): list(r.scale.terms) for r in self.scales},
        }
        if self.deflection_rad is not None:
            own = {
                str(j): round(float(np.degrees(np.sqrt(np.mean(d[:, j - 1] ** 2))) * 3600), 3)
                for j, d in self.deflection_rad.items()
            }
            out["own_deflection_taken_out_rms_arcsec"] = own
        if self.loop is not None:
            out["added"] = [st.label for st in self.loop.stages[2:]]
            set_name = "validate" if "validate" in self.loop.final.errors_mm else "identify"
            out["mean_ap_mm"] = {
                st.label: round(st.mean_ap(set_name), 6) for st in self.loop.stages
            }
        return out


@dataclass(frozen=True, eq=False)
class TwinCalibration:
    """The rounds of the joint fit (one, or more when gravity was found); the last is the
    twin."""

    rounds: tuple[TwinRound, ...]

    @property
    def final(self) -> TwinRound:
        return self.rounds[-1]

    @property
    def calibrated(self) -> RobotDescription:
        """The twin: the last round's calibrated description."""
        return self.final.calibrated

    def summary(self) -> dict[str, Any]:
        return {
            "method": (
                "round 1: scale maps in chain order, identification and closed loop with "
                "the gravity term relative to each sweep's configuration; when it finds "
                "gravity deflection, the next round refits the maps with that deflection "
                "taken out of the sweeps and runs the identification and the loop again, "
                "once more while the loop still finds a harmonic of a gravity-loaded joint "
                "or the deflection moved beyond twice its standard error, each further "
                "round taking out the mean of what the round before took out and what its "
                f"loop found (at most {MAX_ROUNDS} rounds)"
            ),
            "rounds": [r.summary() for r in self.rounds],
        }


def calibrate_twin(
    meas: CampaignMeasurements,
    *,
    effects: bool = True,
    scale_options: ScaleOptions | None = None,
    loop_settings: LoopSettings | None = None,
    say: Say = quiet,
) -> TwinCalibration:
    """Scale maps, identification and closed loop, fitted jointly (module docstring).

    Round 1: maps in chain order, the poses read through them, the identification and the
    closed loop, whose gravity term models each joint's deflection relative to its sweep
    configuration, where the maps absorbed it
    (:func:`~calibration.effects.closed_loop.campaign_effect_data`): to first order the joint fit
    of maps and gravity. When it finds gravity deflection, round 2 refits the maps with
    that deflection taken out of the sweeps (every link's, upstream ones through the
    chain), so that they read the rings, and runs the identification and the loop again.
    A joint's share that depends on its own angle alone stays in its map (the poses cannot
    tell the two apart), and a share the fit did not determine is shrunk away
    (:func:`~calibration.twin.sweep_deflections.sweep_deflections`). When that round's
    loop still finds a harmonic of a gravity-loaded joint beside the gravity term (load its
    map still carries), its own gravity deflection goes back into the sweeps once more, and
    so it does while the deflection itself still moves between rounds by more than twice
    its standard error (a first round whose maps carried the load can give a gravity term
    that lends one joint another's deflection; at most :data:`MAX_ROUNDS` rounds);
    otherwise a further round would only redraw the estimate's noise into the maps. From
    round 3 on, a round takes out the mean of what the round before took out and what that
    round's loop found (:data:`DEFLECTION_STEP`): taken out whole, the rounds over-correct
    and alternate instead of settling (docs/twin-run.md, "The joint fit"). The last round
    is the twin.
    """

    def one_round(deflection: dict[int, FloatArray] | None) -> TwinRound:
        return _twin_round(
            meas, deflection, effects=effects, scale_options=scale_options,
            loop_settings=loop_settings, say=say,
        )  # fmt: skip

    first = one_round(None)
    idm = first.campaign.mask("identify")
    say(f"identification: {int(idm.sum())} poses, validation {int((~idm).sum())}")
    found = sweep_deflections(meas, first.scales, first.campaign, first.loop)
    if found is None:  # no gravity deflection found: nothing to take out
        return TwinCalibration((first,))
    say("closed loop found gravity deflection: refitting the scale maps without it")
    return TwinCalibration(_refitted_rounds(meas, first, found[0], one_round, say))


def _twin_round(
    meas: CampaignMeasurements,
    deflection: dict[int, FloatArray] | None,
    *,
    effects: bool,
    scale_options: ScaleOptions | None,
    loop_settings: LoopSettings | None,
    say: Say,
) -> TwinRound:
    """One round: maps from the sweeps (``deflection`` taken out, rad ``(S, n)`` per joint;
    None: as they are), the poses read through them, identification and closed loop."""
    robot = meas.robot
    limits = [(j.lower_deg, j.upper_deg) for j in robot.joints]
    scales = calibrate_scales(
        meas.sweeps, meas.home_counts, home_deg=robot.home, limits_deg=limits,
        options=scale_options, link_rotations_rad=deflection,
    )  # fmt: skip
    scales = with_load_notes(scales, robot, deflection_taken_out=deflection is not None)
    campaign = campaign_from_scales(meas, scales)
    cal = calibrate(
        robot, campaign, effects=effects, loop_settings=loop_settings, say=say,
        sweep_referenced=deflection is None,
        sweep_configurations=sweep_configurations(robot, meas.sweeps, scales),
    )  # fmt: skip
    return TwinRound(
        scales, campaign, cal.geometric, cal.loop, deflection, cal.description, cal.learned
    )


def _refitted_rounds(
    meas: CampaignMeasurements,
    first: TwinRound,
    deflection: dict[int, FloatArray],
    one_round: Callable[[dict[int, FloatArray] | None], TwinRound],
    say: Say,
) -> tuple[TwinRound, ...]:
    """``first`` and the rounds after it, each with the previous round's gravity deflection
    taken out of the sweeps, while :func:`calibrate_twin`'s rules ask for one more."""
    rounds = [first]
    while True:
        current = one_round(deflection)
        rounds.append(current)
        added = ", ".join(st.label for st in current.loop.stages[2:]) if current.loop else ""
        say(f"joint fit round {len(rounds)}: the twin adds {added or 'nothing'}")
        if len(rounds) >= MAX_ROUNDS:
            break
        refined = sweep_deflections(meas, current.scales, current.campaign, current.loop)
        if refined is None:
            break
        moved = _deflection_moved(deflection, *refined)
        if not (moved or _load_left_in_maps(current, meas.robot)):
            break
        if moved:
            say(f"joint fit: the deflection of joint(s) {', '.join(map(str, moved))} moved "
                "beyond its noise: once more")  # fmt: skip
        deflection = _damped(deflection, refined[0])
    return tuple(rounds)


def _damped(taken: dict[int, FloatArray], found: dict[int, FloatArray]) -> dict[int, FloatArray]:
    """What the next round takes out of each joint's sweep ``(S, n)`` rad: ``taken`` (this
    round's) moved by :data:`DEFLECTION_STEP` of the way to ``found`` (its loop's); a joint
    this round took nothing out of starts from zero."""
    out: dict[int, FloatArray] = {}
    for j, f in found.items():
        t = taken.get(j, np.zeros_like(f))
        out[j] = t + DEFLECTION_STEP * (f - t)
    return out


def _deflection_moved(
    old: dict[int, FloatArray], new: dict[int, FloatArray], noise: FloatArray
) -> list[int]:
    """Joints (1-based) whose deflection over all sweeps moved between rounds by more than
    twice its standard error (sum of squares over the stops against ``4·noise``, ``noise``
    ``(n,)`` the summed variance): the maps and the gravity term have not settled."""
    change = sum(np.sum((new[j] - old[j]) ** 2, axis=0) for j in new)
    return [int(i) + 1 for i in np.flatnonzero(change > 4.0 * noise)]


def _load_left_in_maps(rnd: TwinRound, robot: RobotDescription) -> bool:
    """Whether the round's loop still found a harmonic of a gravity-loaded joint's own
    angle beside the gravity term: what the maps still carry of the load (the round's
    gravity deflection then goes back into the sweeps once more)."""
    from calibration.model.gravity_regressor import base_moments

    if rnd.loop is None:
        return False
    loaded = set(base_moments(robot).loaded_joints)
    specs = rnd.loop.final.specs
    return any(s.kind == "gravity_deflection" for s in specs) and any(
        s.kind in ("joint_harmonic", "link_harmonic") and s.joint in loaded for s in specs
    )
