"""The twin on recorded (or collected live) streams: phases → maps → campaign → twin.

The data flow one way, in memory, as typed values:

1. :func:`measure_campaign`: the campaign's phases found in the streams, tracker and
   grating samples paired per dwell → :class:`CampaignMeasurements` (sweeps with every
   joint's reading at each stop, Home returns, poses);
2. :func:`calibrate_twin`: grating scales in chain order (:mod:`calibration.scales.chain_scale`),
   the poses read through them (:func:`campaign_from_scales`), the identification and the
   closed loop, whose gravity term knows the maps absorbed each swept link's deflection
   in its sweep configuration (the link turns after its ring under its own weight, which
   no grating sees); when the loop finds gravity deflection, the maps are refitted with
   it taken out of the sweeps and everything downstream runs again: a joint fit of the
   maps and the loop's gravity term;
3. the documents of the files, still in memory: :func:`export_campaign` (``twin
   export``) gives a :class:`CampaignExport`, :func:`run_twin` (``twin run``) a
   :class:`TwinRun`; nothing here writes a file (:mod:`calibration.cli.run_files` does, at
   the command line's edge).

Determinism: the same streams give bit-identical files. Nothing of the run's own clock goes
into ``calibrated.toml``, ``report.json``, ``phases.json`` or the CSV files (the solver
times are removed from ``report.json``; they stay in ``report.md`` and ``run.json``); the
closed loop's CV folds use its fixed seed; every list is in time or joint order.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration.effects.calibrate import calibrate
from calibration.errors import TwinRunError
from calibration.identify.campaign_files import Campaign
from calibration.model.description import RobotDescription, load_robot
from calibration.scales.chain_scale import ScaleCampaignResult, calibrate_scales, with_load_notes
from calibration.scales.grating_scale import COUNTER_MODULUS, JointSweep, ScaleOptions
from calibration.scales.scale_files import ScaleCalibration, scale_document
from calibration.twin.pairing import PairingOptions, StopMeasurement, pair_dwell
from calibration.twin.phase_detection import PhaseOptions, Phases, Pose, find_phases
from calibration.twin.streams import CellStreams

if TYPE_CHECKING:
    from calibration.effects.closed_loop import ClosedLoopResult, LoopSettings
    from calibration.effects.effect_base import EffectSpec
    from calibration.effects.effect_gravity import GravityDeflection
    from calibration.effects.identification_report import SetErrors
    from calibration.effects.learned_residual import LearnedStage
    from calibration.identify.identification import IdentificationResult
    from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Say = Callable[[str], None]

#: The joint fit's rounds at most: round 1 (maps from the sweeps as they are) and up to two
#: more with the loop's modelled gravity deflection taken out of the sweeps.
MAX_ROUNDS = 3


def quiet(_text: str) -> None:
    """A :data:`Say` that says nothing."""


#: The motor encoders' counts per turn unless told (17-bit single turn, the emulated cell's
#: and docs/protocols.md's default).
ENCODER_COUNTS_PER_REV = 131072


def _counter(value: float) -> int:
    return int(np.rint(value)) % COUNTER_MODULUS


# -- 1. measurements ------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CampaignMeasurements:
    """What the streams hold of the calibration campaign, as typed values.

    Sweeps per joint (rows in the order sweep.csv lists them, every joint's reading at
    each stop), Home readings per joint, and the paired poses: names, sets, times from
    the first dwell ``(m,)`` s, grating counts ``(m, n)``, tracker points ``(m, 3)`` mm and
    encoder angles ``(m, n)`` deg (None without encoders). ``summary``: what phases.json
    says of them (:func:`phases_document` adds the scale maps' part).
    """

    robot: RobotDescription
    phases: Phases
    stops: dict[int, StopMeasurement]  # by dwell
    sweeps: dict[int, JointSweep]
    home_counts: dict[int, IntArray]
    poses: tuple[Pose, ...]
    pose_t_s: FloatArray
    pose_counts: FloatArray
    pose_points_mm: FloatArray
    encoder_deg: FloatArray | None
    summary: dict[str, Any]

    @property
    def n_joints(self) -> int:
        return self.robot.n_joints


def measure_campaign(
    streams: CellStreams,
    robot: RobotDescription,
    *,
    phase_options: PhaseOptions | None = None,
    pairing_options: PairingOptions | None = None,
    encoder_counts_per_rev: int = ENCODER_COUNTS_PER_REV,
    say: Say = quiet,
) -> CampaignMeasurements:
    """Find the phases in the streams and pair every stop and pose that needs a point."""
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
    stops = _pair_stops(ph, streams, pairing_options or PairingOptions())
    lost = _lost_stops(stops)
    say(f"paired {len(stops) - len(lost)} of {len(stops)} stops ({len(lost)} lost)")
    sweeps = _sweeps(ph, stops)
    if not sweeps:
        raise TwinRunError(f"{streams.source}: no sweep found (see phases.json)")
    poses = tuple(p for p in ph.poses if stops[p.dwell].ok)
    summary = _phases_summary(streams, robot, ph, s, stops, lost)
    encoder = None
    if (
        streams.encoders is not None
        and poses
        and all(stops[p.dwell].encoder_counts is not None for p in poses)
    ):
        encoder, offsets = _encoder_deg(ph, stops, streams, robot, poses, encoder_counts_per_rev)
        summary["encoder_zero"] = "mean encoder reading over the Home returns = Home angle"
        summary["encoder_counts_per_rev"] = encoder_counts_per_rev
        summary["encoder_offset_deg"] = [round(float(v), 9) for v in offsets]
    t0 = int(ph.dwells[0].t0_ns)
    return CampaignMeasurements(
        robot=robot,
        phases=ph,
        stops=stops,
        sweeps=sweeps,
        home_counts=_home_counts(ph),
        poses=poses,
        pose_t_s=np.array([(stops[p.dwell].t_ns - t0) * 1e-9 for p in poses]),
        pose_counts=np.array([stops[p.dwell].counts for p in poses]).reshape(len(poses), n),
        pose_points_mm=np.array([stops[p.dwell].point_mm for p in poses]).reshape(-1, 3),
        encoder_deg=encoder,
        summary=summary,
    )


def _pair_stops(
    ph: Phases, streams: CellStreams, options: PairingOptions
) -> dict[int, StopMeasurement]:
    """Every sweep stop's and pose's dwell paired, by dwell (in dwell order)."""
    needed = sorted({st.dwell for st in ph.sweeps} | {p.dwell for p in ph.poses})
    return {
        k: pair_dwell(ph.dwells[k], streams.grating, streams.tracker, streams.encoders, options)
        for k in needed
    }


def _lost_stops(stops: dict[int, StopMeasurement]) -> list[dict[str, Any]]:
    """phases.json's ``stops_lost``: the stops that got no point, and why."""
    return [
        {
            "dwell": m.dwell,
            "t_ns": m.t_ns,
            "reason": m.reason,
            "pairs": m.n_pairs,
            "beam_broken": m.n_rejected_beam,
            "moving": m.n_rejected_moving,
        }
        for m in stops.values()
        if not m.ok
    ]


def _home_counts(ph: Phases) -> dict[int, IntArray]:
    """Per joint (in joint order), its counter value at each Home return (in trial order)."""
    home: dict[int, list[int]] = {}
    for h in sorted(ph.home_returns, key=lambda h: (h.joint, h.trial)):
        home.setdefault(h.joint, []).append(_counter(ph.dwells[h.dwell].counts[h.joint - 1]))
    return {j: np.array(c, dtype=np.int64) for j, c in home.items()}


def _phases_summary(
    streams: CellStreams,
    robot: RobotDescription,
    ph: Phases,
    found: dict[str, Any],
    stops: dict[int, StopMeasurement],
    lost: list[dict[str, Any]],
) -> dict[str, Any]:
    """What phases.json says of the measurements (``found``: the phases' summary; the
    scale maps' part is added by :func:`phases_document`)."""
    return {
        "format": "twin-phases/1",
        "source": Path(streams.source).name,
        "recording_complete": streams.complete,
        "note": streams.note,
        "robot": robot.name,
        "phases": found,
        "home_counts": [
            None if not math.isfinite(v) else round(float(v), 3) for v in ph.home_counts
        ],
        "stops_needed": len(stops),
        "stops_lost": lost,
        "lost_intervals": [_with_seconds(x, streams.grating.t_ns[0]) for x in streams.lost()],
    }


def _sweeps(ph: Phases, stops: dict[int, StopMeasurement]) -> dict[int, JointSweep]:
    """Per joint, its paired sweep stops in sweep.csv's order (forward first, by step);
    ``rows`` are the rows the stops have in sweep.csv."""
    ordered = sorted(ph.sweeps, key=lambda x: (x.joint, x.pass_name != "forward", x.step))
    ordered = [st for st in ordered if stops[st.dwell].ok]
    out: dict[int, JointSweep] = {}
    for j in sorted({st.joint for st in ordered}):
        rows = [(i, st) for i, st in enumerate(ordered) if st.joint == j]
        chain = np.array(
            [[_counter(c) for c in stops[st.dwell].counts] for _, st in rows], dtype=np.int64
        )
        out[j] = JointSweep(
            joint=j,
            pass_name=np.array([st.pass_name for _, st in rows]),
            step=np.array([st.step for _, st in rows], dtype=np.int64),
            counts=chain[:, j - 1].copy(),
            points_mm=np.array([stops[st.dwell].point_mm for _, st in rows]),
            rows=np.array([i + 2 for i, _ in rows], dtype=np.int64),
            chain_counts=chain,
        )
    return out


def campaign_from_scales(
    meas: CampaignMeasurements, scales: ScaleCampaignResult, source: str = "campaign.csv"
) -> Campaign:
    """The poses read through the scale maps: campaign.csv's rows, in memory."""
    by_joint = {r.joint: r.scale for r in scales}
    missing = [j for j in range(1, meas.n_joints + 1) if j not in by_joint]
    if missing or not meas.poses:
        what = f"joints {missing} have no sweep" if missing else "no poses found"
        raise TwinRunError(f"cannot read the poses: {what}")
    q = np.column_stack(
        [by_joint[j + 1].counts_to_joint_deg(meas.pose_counts[:, j]) for j in range(meas.n_joints)]
    )
    return Campaign(
        source=source,
        pose=tuple(p.name for p in meas.poses),
        set=tuple(p.set for p in meas.poses),
        t_s=meas.pose_t_s,
        q_deg=q,
        xyz_mm=meas.pose_points_mm,
        encoder_deg=meas.encoder_deg,
    )


def _with_seconds(entry: dict[str, Any], t0_ns: int) -> dict[str, Any]:
    e = dict(entry)
    e["t_start_s"] = round((entry["t_start_ns"] - int(t0_ns)) * 1e-9, 6)
    e["t_end_s"] = round((entry["t_end_ns"] - int(t0_ns)) * 1e-9, 6)
    return e


def _encoder_deg(
    ph: Phases,
    meas: dict[int, StopMeasurement],
    streams: CellStreams,
    robot: RobotDescription,
    pose_ok: tuple[Pose, ...],
    cpr: int,
) -> tuple[FloatArray, FloatArray]:
    """Encoder joint angles (deg) of the poses; each joint's zero from the Home returns."""
    n = robot.n_joints
    gear = np.array(robot.gear_ratios, dtype=float)
    raw = np.array([meas[p.dwell].encoder_counts for p in pose_ok]) / cpr * 360.0 / gear
    enc = streams.encoders
    assert enc is not None
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


# -- 2. the twin: maps and loop fitted jointly ----------------------------------------------
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
                "or the deflection moved beyond twice its standard error "
                f"(at most {MAX_ROUNDS} rounds)"
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
    (:func:`_sweep_deflections`). When that round's loop still finds a harmonic of a
    gravity-loaded joint beside the gravity term (load its map still carries), its own
    gravity deflection goes back into the sweeps once more, and so it does while the
    deflection itself still moves between rounds by more than twice its standard error
    (a first round whose maps carried the load can give a gravity term that lends one
    joint another's deflection; at most :data:`MAX_ROUNDS` rounds); otherwise a further
    round would only redraw the estimate's noise into the maps. The last round is the twin.
    """

    def one_round(deflection: dict[int, FloatArray] | None) -> TwinRound:
        return _twin_round(
            meas, deflection, effects=effects, scale_options=scale_options,
            loop_settings=loop_settings, say=say,
        )  # fmt: skip

    first = one_round(None)
    idm = first.campaign.mask("identify")
    say(f"identification: {int(idm.sum())} poses, validation {int((~idm).sum())}")
    found = _sweep_deflections(meas, first)
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
        refined = _sweep_deflections(meas, current)
        if refined is None:
            break
        moved = _deflection_moved(deflection, *refined)
        if not (moved or _load_left_in_maps(current, meas.robot)):
            break
        if moved:
            say(f"joint fit: the deflection of joint(s) {', '.join(map(str, moved))} moved "
                "beyond its noise: once more")  # fmt: skip
        deflection = refined[0]
    return tuple(rounds)


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


def _sweep_deflections(
    meas: CampaignMeasurements, rnd: TwinRound
) -> tuple[dict[int, FloatArray], FloatArray] | None:
    """The round's gravity deflection of every link ``(S, n)`` rad at each joint's sweep
    stops, and per joint its variance summed over all sweeps' stops ``(n,)`` (None when
    the round's loop found no gravity deflection).

    Only what the poses can tell from the maps goes back into them: a moment whose effect
    on joint j depends on q_j alone (it vanishes relative to j's sweep configuration, e.g.
    link 2's own moment about joint 2 when joint 1 is vertical) is left in j's map, and
    each joint's deflection is shrunk by its signal-to-noise ratio over the sweeps, by the
    factor ``max(0, 1 − 1/SNR²)`` (positive-part James-Stein): a deflection within its own
    standard error (a rigid joint's estimate is noise) is not taken out, a well determined
    one nearly all of it, and nothing switches on and off between rounds.
    """
    loop = rnd.loop
    term = None if loop is None else _gravity_term(loop)
    if loop is None or term is None:
        return None
    robot = meas.robot
    acting = _acting_moments(robot, rnd.campaign, term)
    sweeps = {
        j: _sweep_deflection(robot, rnd.scales, sweep, term, acting)
        for j, sweep in meas.sweeps.items()
    }
    n = meas.n_joints
    ratio_var = _compliance_ratio_variance(term.spec, loop, n)
    signal = np.zeros(n)
    noise = np.zeros(n)
    for value, var in sweeps.values():
        signal += np.sum(value**2, axis=0)
        noise += np.sum(var, axis=0) + np.sum(value**2, axis=0) * ratio_var
    # positive-part shrinkage by the joint's signal-to-noise ratio over the sweeps
    shrink = np.clip(1.0 - noise / np.maximum(signal, 1e-300), 0.0, 1.0)
    return {j: value * shrink[None, :] for j, (value, _) in sweeps.items()}, noise


@dataclass(frozen=True, eq=False)
class _GravityTerm:
    """A loop's fitted gravity deflection: its spec, values ``(k,)`` and their covariance
    ``(k, k)``, the kind that evaluates it and the loop's final model."""

    spec: EffectSpec
    values: FloatArray
    covariance: FloatArray
    kind: GravityDeflection
    model: KinematicModel


def _gravity_term(loop: ClosedLoopResult) -> _GravityTerm | None:
    """The loop's gravity deflection term (None: it found none)."""
    from calibration.effects.effect_gravity import GravityDeflection
    from calibration.effects.effect_kinds import KINDS, split_values

    final = loop.final
    gravity = [s for s in final.specs if s.kind == "gravity_deflection"]
    if not gravity:
        return None
    spec = gravity[0]
    index = list(final.specs).index(spec)
    assert final.result is not None  # a loop's final stage has its fit
    values = split_values(final.specs, final.result.effect_values)[index]
    cov = _effect_covariance(final.result, index, final.specs)
    kind = KINDS["gravity_deflection"]
    assert isinstance(kind, GravityDeflection)
    return _GravityTerm(spec, values, cov, kind, final.model)


def _acting_moments(
    robot: RobotDescription, campaign: Campaign, term: _GravityTerm
) -> NDArray[np.bool_]:
    """Which moments' share of each joint ``(n, P)`` the identification poses see apart
    from that joint's own angle (relative to Home): what the maps cannot hold."""
    from calibration.effects.effect_base import EffectContext, EffectData, ModelAtPoses

    q_poses = campaign.q_rad[campaign.mask("identify")]
    ref_ctx = EffectContext(robot, EffectData(q_poses, sweep_reference=np.radians(robot.home)))
    d_ref = term.kind.deflection_jacobian(term.spec, ref_ctx, ModelAtPoses.of(term.model, q_poses))
    rms = np.sqrt(np.mean(d_ref**2, axis=0))  # (n, P): what the poses see apart from maps
    acting: NDArray[np.bool_] = rms > 1e-9 * max(float(rms.max(initial=0.0)), 1e-300)
    return acting


def _sweep_deflection(
    robot: RobotDescription,
    scales: ScaleCampaignResult,
    sweep: JointSweep,
    term: _GravityTerm,
    acting: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray]:
    """The term's deflection of every link ``(S, n)`` rad at one sweep's stops (the stops
    read through ``scales``, the ``acting`` moments only) and its variance ``(S, n)``."""
    from calibration.effects.effect_base import EffectContext, EffectData, ModelAtPoses

    by_joint = {r.joint: r.scale for r in scales}
    assert sweep.chain_counts is not None
    q = np.radians(
        np.column_stack(
            [
                by_joint[i + 1].counts_to_joint_deg(sweep.chain_counts[:, i])
                for i in range(robot.n_joints)
            ]
        )
    )
    ctx = EffectContext(robot, EffectData(q))
    kin = ModelAtPoses.of(term.model, q)
    unit = np.eye(len(term.values))
    jac = np.stack(
        [term.kind.joint_deflections_rad(term.spec, u, ctx, kin, acting) for u in unit], axis=2
    )
    value: FloatArray = jac @ term.values
    variance: FloatArray = np.einsum("sjk,kl,sjl->sj", jac, term.covariance, jac)
    return value, variance


def _compliance_ratio_variance(spec: EffectSpec, loop: ClosedLoopResult, n: int) -> FloatArray:
    """Per joint ``(n,)``, the relative variance of its compliance ratio: the physical
    form's ratios are held fixed in the fit, and their own uncertainty (from the loop's
    profile of them) adds ``(d_j / ρ_j)²·var(ρ_j)`` to a deflection's variance."""
    ratio_var = np.zeros(n)
    if spec.parameter == "physical":
        form = next(
            (st.shape["gravity_form"] for st in loop.stages if "gravity_form" in st.shape), None
        )
        if form is not None:
            for j, r, se in zip(
                form["joints"], form["compliance_ratio"], form["compliance_ratio_se"], strict=True
            ):
                ratio_var[j - 1] = (se / r) ** 2 if r != 0 else np.inf
    return ratio_var


def _effect_covariance(
    result: IdentificationResult, index: int, specs: Sequence[EffectSpec]
) -> FloatArray:
    """Covariance ``(k, k)`` of one effect's parameters (zero rows for held ones)."""
    sizes = [len(s.parameter_names()) for s in specs]
    start = result.n_geometric + sum(sizes[:index])
    k = sizes[index]
    full = np.zeros((len(result.free), len(result.free)))
    idx = np.flatnonzero(result.free)
    full[np.ix_(idx, idx)] = result.covariance
    return full[start : start + k, start : start + k]


# -- 3. the documents of the files, in memory ---------------------------------------------------
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
    say: Say = quiet,
) -> TwinRun:
    """Measurements, the twin (maps and loop fitted jointly) and its documents; writes
    nothing (:mod:`calibration.cli.run_files` writes the files). ``robot``: a preset name, a
    description file or a description; ``max_effects``: at most this many effects (None:
    the loop's default)."""
    started = time.perf_counter()
    desc = load_robot(robot) if isinstance(robot, str) else robot
    meas = measure_campaign(streams, desc, say=say)
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
