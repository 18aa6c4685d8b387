"""The campaign in the streams: phases found, tracker and grating samples paired per dwell.

:func:`measure_campaign` gives :class:`CampaignMeasurements` (sweeps with every joint's
reading at each stop, Home returns, poses); :func:`campaign_from_scales` reads the poses
through the scale maps (the :class:`~calibration.identify.campaign_files.Campaign` the
identification fits). The first step of ``twin run`` and ``twin export``
(:mod:`calibration.twin.twin_run`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.errors import TwinRunError
from calibration.identify.campaign_files import Campaign
from calibration.model.description import RobotDescription
from calibration.scales.chain_scale import ScaleCampaignResult
from calibration.scales.grating_scale import COUNTER_MODULUS, JointSweep
from calibration.twin.pairing import PairingOptions, StopMeasurement, pair_dwell
from calibration.twin.phase_detection import PhaseOptions, Phases, Pose, find_phases
from calibration.twin.streams import CellStreams

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Say = Callable[[str], None]


def quiet(_text: str) -> None:
    """A :data:`Say` that says nothing."""


#: The motor encoders' counts per turn unless told (17-bit single turn, the emulated cell's
#: and docs/protocols.md's default).
ENCODER_COUNTS_PER_REV = 131072


def _counter(value: float) -> int:
    return int(np.rint(value)) % COUNTER_MODULUS


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
