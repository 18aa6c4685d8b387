"""The twin on recorded (or collected live) streams: phases → maps → campaign → twin.

The data flow one way, in memory, as typed values:

1. :func:`measure_campaign`: the campaign's phases found in the streams, tracker and
   grating samples paired per dwell → :class:`CampaignMeasurements` (sweeps with every
   joint's reading at each stop, Home returns, poses);
2. :func:`calibrate_twin`: grating scales in chain order (:mod:`calibration.chain_scale`),
   the poses read through them (:func:`campaign_from_scales`), the identification and the
   closed loop, whose gravity term knows the maps absorbed each swept link's deflection
   in its sweep configuration (the link turns after its ring under its own weight, which
   no grating sees); when the loop finds gravity deflection, the maps are refitted with
   it taken out of the sweeps and everything downstream runs again: a joint fit of the
   maps and the loop's gravity term;
3. files only at the edges: :func:`export_campaign` (``twin export``) and :func:`run_twin`
   (``twin run``) write them.

Determinism: the same streams give bit-identical files. Nothing of the run's own clock goes
into ``calibrated.toml``, ``report.json``, ``phases.json`` or the CSV files (the solver
times are removed from ``report.json``; they stay in ``report.md`` and ``run.json``); the
closed loop's CV folds use its fixed seed; every list is in time or joint order.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration.calibrate import calibrate
from calibration.campaign_files import Campaign, write_campaign
from calibration.chain_scale import ScaleCampaignResult, calibrate_scales, with_load_notes
from calibration.description import RobotDescription, load_robot
from calibration.errors import TwinRunError
from calibration.grating_scale import COUNTER_MODULUS, JointSweep, ScaleOptions
from calibration.pairing import PairingOptions, StopMeasurement, pair_dwell
from calibration.phase_detection import PhaseOptions, Phases, Pose, find_phases
from calibration.scale_files import write_csv
from calibration.streams import CellStreams

if TYPE_CHECKING:
    from calibration.closed_loop import ClosedLoopResult
    from calibration.effect_library import EffectSpec
    from calibration.identification import IdentificationResult

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Say = Callable[[str], None]

#: The joint fit's rounds at most: round 1 (maps from the sweeps as they are) and up to two
#: more with the loop's modelled gravity deflection taken out of the sweeps.
MAX_ROUNDS = 3
#: run.json's ``paths_relative_to``: its paths are relative to its own directory
RUN_PATHS_RELATIVE_TO = "run.json"


def _quiet(_text: str) -> None:
    pass


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
    encoder angles ``(m, n)`` deg (None without encoders). ``summary`` is phases.json.
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
    say: Say = _quiet,
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
    popts = pairing_options or PairingOptions()
    needed = sorted({st.dwell for st in ph.sweeps} | {p.dwell for p in ph.poses})
    stops = {
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
        for m in stops.values()
        if not m.ok
    ]
    say(f"paired {len(needed) - len(rejected)} of {len(needed)} stops ({len(rejected)} lost)")
    sweeps = _sweeps(ph, stops)
    if not sweeps:
        raise TwinRunError(f"{streams.source}: no sweep found (see phases.json)")
    home: dict[int, list[int]] = {}
    for h in sorted(ph.home_returns, key=lambda h: (h.joint, h.trial)):
        home.setdefault(h.joint, []).append(_counter(ph.dwells[h.dwell].counts[h.joint - 1]))
    poses = tuple(p for p in ph.poses if stops[p.dwell].ok)
    t0 = int(ph.dwells[0].t0_ns)
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
    return CampaignMeasurements(
        robot=robot,
        phases=ph,
        stops=stops,
        sweeps=sweeps,
        home_counts={j: np.array(c, dtype=np.int64) for j, c in home.items()},
        poses=poses,
        pose_t_s=np.array([(stops[p.dwell].t_ns - t0) * 1e-9 for p in poses]),
        pose_counts=np.array([stops[p.dwell].counts for p in poses]).reshape(len(poses), n),
        pose_points_mm=np.array([stops[p.dwell].point_mm for p in poses]).reshape(-1, 3),
        encoder_deg=encoder,
        summary=summary,
    )


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
    gear = np.array([j.gear_ratio or 100.0 for j in robot.joints], dtype=float)
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
    calibrated: RobotDescription  # this round's twin (calibration.calibrate)

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
    loop_settings: Any = None,
    say: Say = _quiet,
) -> TwinCalibration:
    """Scale maps, identification and closed loop, fitted jointly (module docstring).

    Round 1: maps in chain order, the poses read through them, the identification and the
    closed loop, whose gravity term models each joint's deflection relative to its sweep
    configuration, where the maps absorbed it
    (:func:`~calibration.closed_loop.campaign_effect_data`): to first order the joint fit
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
    robot = meas.robot
    limits = [(j.lower_deg, j.upper_deg) for j in robot.joints]

    def one_round(deflection: dict[int, FloatArray] | None) -> TwinRound:
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
        return TwinRound(scales, campaign, cal.geometric, cal.loop, deflection, cal.description)

    first = one_round(None)
    idm = first.campaign.mask("identify")
    say(f"identification: {int(idm.sum())} poses, validation {int((~idm).sum())}")
    found = _sweep_deflections(meas, first)
    if found is None:  # no gravity deflection found: nothing to take out
        return TwinCalibration((first,))
    deflection, _ = found
    say("closed loop found gravity deflection: refitting the scale maps without it")
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
        if not (moved or _load_left_in_maps(current, robot)):
            break
        if moved:
            say(f"joint fit: the deflection of joint(s) {', '.join(map(str, moved))} moved "
                "beyond its noise: once more")  # fmt: skip
        deflection = refined[0]
    return TwinCalibration(tuple(rounds))


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
    from calibration.gravity_regressor import base_moments

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
    from calibration.effect_library import (
        KINDS,
        EffectContext,
        EffectData,
        GravityDeflection,
        Kinematics,
        split_values,
    )

    loop = rnd.loop
    if loop is None:
        return None
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
    robot = meas.robot
    # which moments' share of each joint the poses see apart from that joint's own angle
    q_poses = rnd.campaign.q_rad[rnd.campaign.mask("identify")]
    ref_ctx = EffectContext(robot, EffectData(q_poses, sweep_reference=np.radians(robot.home)))
    d_ref = kind.deflection_jacobian(spec, ref_ctx, Kinematics.of(final.model, q_poses))
    rms = np.sqrt(np.mean(d_ref**2, axis=0))  # (n, P): what the poses see apart from maps
    acting = rms > 1e-9 * max(float(rms.max(initial=0.0)), 1e-300)
    by_joint = {r.joint: r.scale for r in rnd.scales}
    sweeps: dict[int, tuple[FloatArray, FloatArray]] = {}
    unit = np.eye(len(values))
    for j, sweep in meas.sweeps.items():
        assert sweep.chain_counts is not None
        q = np.radians(
            np.column_stack(
                [
                    by_joint[i + 1].counts_to_joint_deg(sweep.chain_counts[:, i])
                    for i in range(meas.n_joints)
                ]
            )
        )
        ctx = EffectContext(robot, EffectData(q))
        kin = Kinematics.of(final.model, q)
        jac = np.stack(
            [kind.joint_deflections_rad(spec, u, ctx, kin, acting) for u in unit], axis=2
        )
        sweeps[j] = (jac @ values, np.einsum("sjk,kl,sjl->sj", jac, cov, jac))
    n = meas.n_joints
    # the physical form's compliance ratios are held fixed in the fit: their own
    # uncertainty (from the loop's profile of them) adds (d_j / ρ_j)²·var(ρ_j)
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
    signal = np.zeros(n)
    noise = np.zeros(n)
    for value, var in sweeps.values():
        signal += np.sum(value**2, axis=0)
        noise += np.sum(var, axis=0) + np.sum(value**2, axis=0) * ratio_var
    # positive-part shrinkage by the joint's signal-to-noise ratio over the sweeps
    shrink = np.clip(1.0 - noise / np.maximum(signal, 1e-300), 0.0, 1.0)
    return {j: value * shrink[None, :] for j, (value, _) in sweeps.items()}, noise


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


# -- 3. files at the edge ---------------------------------------------------------------------
@dataclass
class ExportResult:
    out: Path
    measurements: CampaignMeasurements
    scales: ScaleCampaignResult
    files: dict[str, Path]
    summary: dict[str, Any]

    @property
    def phases(self) -> Phases:
        return self.measurements.phases


def _write_campaign_files(
    out: Path, meas: CampaignMeasurements, scales: ScaleCampaignResult, campaign: Campaign
) -> tuple[dict[str, Path], dict[str, Any]]:
    """home.csv, sweep.csv, scale.toml, campaign.csv and phases.json into ``out``."""
    from calibration.scale_files import scale_document, write_scale_toml

    out.mkdir(parents=True, exist_ok=True)
    n = meas.n_joints
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
            [j, t + 1, int(c)]
            for j in sorted(meas.home_counts)
            for t, c in enumerate(meas.home_counts[j])
        ),
    )
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
                    *(int(c) for c in sw.chain_counts[k]),  # every joint: the chain's motion
                ]
            )
    chain_columns = [f"g{i}_counts" for i in range(1, n + 1)]
    write_csv(
        files["sweep"],
        ["joint", "pass", "step", "counts", "x_mm", "y_mm", "z_mm", *chain_columns],
        rows,
    )
    sopts = ScaleOptions()
    doc = scale_document(
        scales,
        robot=meas.robot.name,
        metadata={"sweep_file": "sweep.csv", "home_file": "home.csv", "source": "twin"},
        counts_per_mm=sopts.counts_per_mm,
    )
    write_scale_toml(files["scale"], doc)
    write_campaign(files["campaign"], campaign)
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
    summary["uncalibrated_joints"] = [j for j in range(1, n + 1) if j not in meas.sweeps]
    summary["campaign"] = {
        "identify": sum(p.set == "identify" for p in meas.poses),
        "validate": sum(p.set == "validate" for p in meas.poses),
        "t0_ns": int(meas.phases.dwells[0].t0_ns),
    }
    files["phases"].write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return files, summary


def export_campaign(
    streams: CellStreams,
    robot: RobotDescription,
    out: str | Path,
    *,
    phase_options: PhaseOptions | None = None,
    pairing_options: PairingOptions | None = None,
    scale_options: ScaleOptions | None = None,
    encoder_counts_per_rev: int = ENCODER_COUNTS_PER_REV,
    say: Say = _quiet,
) -> ExportResult:
    """Write ``home.csv``, ``sweep.csv``, ``scale.toml``, ``campaign.csv``, ``phases.json``
    (the scale maps in chain order, without the loop's gravity feedback)."""
    out = Path(out)
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
    campaign = campaign_from_scales(meas, scales)
    files, summary = _write_campaign_files(out, meas, scales, campaign)
    say(
        f"wrote {files['home'].name}, {files['sweep'].name}, {files['scale'].name}, "
        f"{files['campaign'].name} ({len(campaign)} poses)"
    )
    return ExportResult(out, meas, scales, files, summary)


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
    write_to: str | Path | None = None,
) -> dict[str, Any]:
    """Measurements, the twin (maps and loop fitted jointly), files and reports; a summary.

    ``out``: the output directory the documents name; ``write_to``: where the files are
    written now (a staging directory moved to ``out`` afterwards; default ``out``)."""
    from calibration.identification_report import build_report, write_report
    from calibration.scale_report import write_report as write_scale_report

    started = time.perf_counter()
    desc = load_robot(robot) if isinstance(robot, str) else robot
    out = Path(out)
    dest = Path(write_to) if write_to is not None else out

    def named(path: Path) -> str:
        return str(out / path.relative_to(dest))

    meas = measure_campaign(streams, desc, say=say)
    t_export = time.perf_counter() - started
    say("scale calibration (chain order), identification and closed loop")
    twin = calibrate_twin(meas, effects=effects, say=say)
    final = twin.final
    files, summary = _write_campaign_files(dest, meas, final.scales, final.campaign)
    calibrated = twin.calibrated
    calibrated_path = dest / "calibrated.toml"
    calibrated.save(calibrated_path)
    doc, errors = build_report(
        final.result,
        desc,
        final.campaign,
        robot_source=desc.name if not isinstance(robot, str) else robot,
        calibrated_path="calibrated.toml",
        closed_loop=final.loop,
    )
    doc["solver"]["point_weights"] = "none (all points weigh the same)"
    doc["twin_run"] = {
        "phases": summary["phases"],
        "stops_lost": len(summary["stops_lost"]),
        "lost_intervals": summary["lost_intervals"],
        "recording_complete": summary["recording_complete"],
        "joint_fit": twin.summary(),
    }
    report_dir = dest / "report"
    if report:
        say("writing the report (figures)")
        write_report(report_dir, doc, errors, closed_loop=final.loop)
        write_scale_report(
            final.scales, dest / "scale-report", robot=desc.name, metadata={"source": "twin run"}
        )
    report_dir.mkdir(parents=True, exist_ok=True)
    (report_dir / "report.json").write_text(
        json.dumps(_scrub(doc), indent=2, allow_nan=False) + "\n", encoding="utf-8"
    )
    table = stage_table(doc)
    elapsed = time.perf_counter() - started
    run = {
        "calibrated": named(calibrated_path),
        "report": named(report_dir),
        "files": {k: named(v) for k, v in files.items()},
        "stage_table": table,
        "joint_fit_rounds": len(twin.rounds),
        "export_s": round(t_export, 3),
        "total_s": round(elapsed, 3),
        "success": bool(final.result.success),
    }

    # run.json names its files relative to its own directory, so that ``twin run --from
    # DIR`` finds them from any working directory (the summary returned names them as
    # ``out`` does, for this process)
    def beside(path: Path) -> str:
        return path.relative_to(dest).as_posix()

    stored = dict(
        run,
        calibrated=beside(calibrated_path),
        report=beside(report_dir),
        files={k: beside(v) for k, v in files.items()},
        paths_relative_to=RUN_PATHS_RELATIVE_TO,
    )
    (dest / "run.json").write_text(json.dumps(stored, indent=2) + "\n", encoding="utf-8")
    return run


def resolve_run_path(run_dir: str | Path, name: str, relative_to_run: bool) -> Path:
    """Where a path named in ``run_dir/run.json`` is, from this process's working directory.

    run.json written since ``paths_relative_to = "run.json"`` names its files relative to
    its own directory. An older one named them relative to the working directory of the
    run that wrote it: such a path is taken as it is if it exists from here, else found
    beside run.json by its longest tail that exists there (``demo-out/twin/scale.toml``
    from elsewhere: ``<run_dir>/scale.toml``); else the path is returned as written (the
    caller says it is missing)."""
    path = Path(name)
    run_dir = Path(run_dir)
    if path.is_absolute():
        return path
    if relative_to_run:
        return run_dir / path
    if path.exists():
        return path
    parts = path.parts
    for k in range(len(parts)):
        candidate = run_dir.joinpath(*parts[k:])
        if candidate.exists():
            return candidate
    return path
