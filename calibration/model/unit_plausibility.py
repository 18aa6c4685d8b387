"""Are the numbers in a measurement file in the units its columns say?

A campaign with tracker coordinates in metres fits a robot shrunk 1000× and reports
"mean AP … → 0.0000 mm"; joint angles in radians give a 1.8 m error or a fit that runs
away. Neither is an error the parser can see: every value is a finite number. Two checks
catch them before anything is fitted, and say what the numbers look like:

* **Tracker points** (``x_mm, y_mm, z_mm``): their spread (median distance from their
  median point, so one stray row does not decide it) against the spread of the nominal
  robot's TCP over the same joint angles. A rigid base transform does not change a
  spread and the geometry errors change it by parts per thousand, so a ratio outside
  [1/5, 5] is a unit (metres 1e-3, inches 1/25.4, µm 1e3…), not a robot.
* **Joint angles** (``qK_deg``): every joint's angles within its limits converted to
  radians (±3.2 for a ±185° joint), while the joints can move much further, look like
  radians. Where the file also has tracker points the check is
  decisive: the points fit the angles read as radians and not as degrees.

Both raise :class:`UnitsError` with a hint; ``--no-unit-check`` lets a user who knows
better go on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from calibration.errors import UnitsError
from calibration.model.kinematics import KinematicModel, tcp_positions

FloatArray = NDArray[np.float64]

#: The option that turns the checks off.
OVERRIDE = "--no-unit-check"
#: A ratio of spreads outside [1/SPREAD_LIMIT, SPREAD_LIMIT] is a unit, not a robot.
SPREAD_LIMIT = 5.0
#: Known unit slips: the spread ratio they give, and what the numbers then are in.
_UNIT_SLIPS = {1e-3: "metres", 1e-2: "centimetres", 1 / 25.4: "inches", 1e3: "micrometres"}


def spread_mm(points: FloatArray) -> float:
    """RMS distance of ``(m, 3)`` points from their centroid (mm)."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))


def median_spread_mm(points: FloatArray) -> float:
    """Median distance of ``(m, 3)`` points from their per-axis median (mm): a spread one
    stray point (a typo, an unreachable target) does not move."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    return float(np.median(np.linalg.norm(p - np.median(p, axis=0), axis=1)))


def _slip_name(ratio: float) -> str:
    best = min(_UNIT_SLIPS, key=lambda r: abs(np.log(ratio / r)))
    return _UNIT_SLIPS[best] if abs(np.log(ratio / best)) < np.log(1.5) else ""


def _similar(measured: float, expected: float) -> bool:
    return expected > 0 and 1 / SPREAD_LIMIT < measured / expected < SPREAD_LIMIT


def _looks_like_radians(q_deg: FloatArray, limits_deg: Sequence[tuple[float, float]]) -> bool:
    """Every joint's angles within its limits converted to radians (and not all ~0), while
    some joint can move over 90°: degrees would be a robot that hardly moved."""
    q = np.abs(np.asarray(q_deg, dtype=float))
    if q.size == 0 or float(q.max()) <= 0.1:
        return False
    reach = np.radians([max(abs(lo), abs(hi)) for lo, hi in limits_deg])
    wide = any(hi - lo > 90.0 for lo, hi in limits_deg)
    return wide and bool(np.all(q.max(axis=0) <= reach * (1 + 1e-9)))


def check_joint_angle_units(
    source: str, q_deg: FloatArray, limits_deg: Sequence[tuple[float, float]]
) -> None:
    """Refuse joint angles ``(m, n)`` that look like radians (no tracker to decide)."""
    if _looks_like_radians(q_deg, limits_deg):
        raise UnitsError(
            f"{source}: columns q1_deg..q{np.shape(q_deg)[1]}_deg: every angle is within "
            "the joint limits converted to radians (the largest is "
            f"{float(np.max(np.abs(q_deg))):.4g}): give degrees (or pass {OVERRIDE} if these "
            "really are degrees)"
        )


def check_campaign_units(
    source: str,
    q_deg: FloatArray,
    xyz_mm: FloatArray,
    model: KinematicModel,
    limits_deg: Sequence[tuple[float, float]],
) -> None:
    """Refuse a campaign whose tracker points ``(m, 3)`` mm or joint angles ``(m, n)`` deg
    are in other units (the nominal ``model`` gives the expected spread)."""
    measured = median_spread_mm(xyz_mm)
    nominal = median_spread_mm(tcp_positions(model, np.radians(q_deg)))
    if _looks_like_radians(q_deg, limits_deg):
        as_radians = median_spread_mm(tcp_positions(model, np.asarray(q_deg, dtype=float)))
        if _similar(measured, as_radians) and not _similar(measured, nominal):
            raise UnitsError(
                f"{source}: columns q1_deg..q{np.shape(q_deg)[1]}_deg are in radians: the "
                f"tracker points spread {measured:.0f} mm, the robot over these angles read "
                f"as radians {as_radians:.0f} mm, read as degrees {nominal:.1f} mm; give "
                f"degrees (or pass {OVERRIDE})"
            )
    if nominal < 1.0 or measured == 0.0:
        # the robot moved and the points did not (at one pose, one point is right)
        if nominal >= 1.0 and spread_mm(xyz_mm) == 0.0 and len(xyz_mm) > 1:
            raise UnitsError(f"{source}: columns x_mm,y_mm,z_mm: every tracker point is the same")
        return  # one pose or no motion: nothing to compare
    if _similar(measured, nominal):
        return
    ratio = measured / nominal
    slip = _slip_name(ratio)
    guess = f"; they look like {slip}" if slip else ""
    raise UnitsError(
        f"{source}: columns x_mm,y_mm,z_mm: the tracker points spread {measured:.4g} but the "
        f"robot's TCP over these joint angles spreads {nominal:.0f} mm (ratio {ratio:.3g})"
        f"{guess}: give millimetres (or pass {OVERRIDE})"
    )


#: A joint's sweep moves its tracker target by more than this (mm RMS about the centroid):
#: a reflector on the arm sits at least centimetres from the joint axis, and the sweeps run
#: limit to limit. Metres make the spread a few units.
MIN_SWEEP_SPREAD_MM = 5.0


def check_sweep_units(source: str, points_by_joint: Mapping[int, FloatArray]) -> None:
    """Refuse sweep points ``(S, 3)`` per joint that do not move like millimetres."""
    for joint, points in sorted(points_by_joint.items()):
        spread = spread_mm(points)
        if 0.0 < spread < MIN_SWEEP_SPREAD_MM:
            raise UnitsError(
                f"{source}: columns x_mm,y_mm,z_mm: joint {joint}'s sweep moves the target by "
                f"{spread:.4g} RMS, a robot's joint sweep moves it by hundreds of mm; are the "
                f"coordinates in metres? Give millimetres (or pass {OVERRIDE})"
            )


def check_measurement_units(
    source: str,
    q_deg: FloatArray,
    limits_deg: Sequence[tuple[float, float]],
    *,
    xyz_mm: FloatArray | None = None,
    model: KinematicModel | None = None,
) -> None:
    """The one check of every command that reads joint angles ``(m, n)`` deg, with their
    tracker points ``(m, 3)`` mm when the file has them (then ``model``, the nominal
    robot, gives the expected spread): radians refused, points in other units refused.
    With points the check of the angles is decisive (the points fit them as radians and
    not as degrees); without (or at poses too close to compare spreads), angles that all
    lie within the limits in radians are."""
    if xyz_mm is not None and model is not None:
        check_campaign_units(source, q_deg, xyz_mm, model, limits_deg)
        if median_spread_mm(tcp_positions(model, np.radians(q_deg))) >= 1.0:
            return
    check_joint_angle_units(source, q_deg, limits_deg)
