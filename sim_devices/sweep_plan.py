"""Where a static scale sweep stops, which reflectors the swept link carries, and how each
joint last moved: the geometry of :mod:`sim_devices.scale_campaign`.

Units: degrees for commanded angles (as in the files), mm in link frames.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Tilt (deg) of a reflector set's plane out of the plane perpendicular to the joint axis,
#: so the reflectors sit at different heights along the axis.
TARGET_PLANE_TILT_DEG = 30.0


def commanded_stops_deg(lower_deg: float, upper_deg: float, step_deg: float) -> FloatArray:
    """Commanded angles of the forward pass: from the positive limit down in ``step_deg``."""
    n = math.floor((upper_deg - lower_deg) / step_deg + 1e-9) + 1
    return upper_deg - step_deg * np.arange(n, dtype=float)


def arc_limits_deg(
    lower_deg: float, upper_deg: float, home_deg: float, arc_deg: float | None
) -> tuple[float, float]:
    """The swept arc ``(low, high)``: limit to limit (``arc_deg`` None), else ``arc_deg``
    centred on Home, shifted inside the limits where Home is too close to one, and no
    longer than the joint's range."""
    if arc_deg is None:
        return lower_deg, upper_deg
    arc = min(float(arc_deg), upper_deg - lower_deg)
    low = min(max(home_deg - 0.5 * arc, lower_deg), upper_deg - arc)
    return low, low + arc


def sweep_stops_deg(
    lower_deg: float,
    upper_deg: float,
    home_deg: float,
    *,
    step_deg: float = 2.0,
    arc_deg: float | None = None,
    stops_per_arc: int | None = None,
) -> FloatArray:
    """Commanded angles ``(K,)`` of the forward pass, from the arc's high end down:
    ``stops_per_arc`` evenly spaced stops end to end, or one every ``step_deg``."""
    low, high = arc_limits_deg(lower_deg, upper_deg, home_deg, arc_deg)
    if stops_per_arc is not None:
        if stops_per_arc < 2:
            raise ValueError(f"stops_per_arc must be at least 2, got {stops_per_arc}")
        return np.linspace(high, low, stops_per_arc)
    return commanded_stops_deg(low, high, step_deg)


def target_set_mm(centre_mm: ArrayLike, count: int, spacing_mm: float = 360.0) -> FloatArray:
    """``count`` reflectors ``(T, 3)`` in a link's frame (its z is the joint axis).

    One: ``centre_mm`` itself. More: a regular polygon of side ``spacing_mm`` centred on
    it (T = 3: an equilateral triangle), in the plane through the centre spanned by the
    tangent of its circle and the outward radial direction tilted by
    :data:`TARGET_PLANE_TILT_DEG` towards +z (a plane that does not contain the axis);
    the first vertex points outward, so the others stay clear of the axis.
    """
    c = np.asarray(centre_mm, dtype=float)
    if count < 1:
        raise ValueError(f"need at least one target, got {count}")
    if count == 1:
        return c[None, :].copy()
    radial = np.array([c[0], c[1], 0.0])
    norm = np.linalg.norm(radial)
    if norm < 1e-9:
        raise ValueError("the target centre lies on the joint axis")
    radial /= norm
    tangent = np.cross([0.0, 0.0, 1.0], radial)
    tilt = math.radians(TARGET_PLANE_TILT_DEG)
    up = math.cos(tilt) * radial + math.sin(tilt) * np.array([0.0, 0.0, 1.0])
    circumradius = spacing_mm / (2.0 * math.sin(math.pi / count))
    phi = 0.5 * math.pi + 2.0 * math.pi * np.arange(count) / count
    return c + circumradius * (np.cos(phi)[:, None] * tangent + np.sin(phi)[:, None] * up)


def motion_direction(
    sequence: ArrayLike, start: float, last_direction: float
) -> NDArray[np.float64]:
    """Sign ``(K,)`` of the last move of one joint visiting ``sequence`` ``(K,)`` from
    ``start``; a stop without motion keeps the previous sign (``last_direction`` before
    the first move), as the live plant's trajectories do."""
    seq = np.asarray(sequence, dtype=float)
    step = np.sign(np.diff(np.concatenate([[start], seq])))
    index = np.where(step != 0, np.arange(seq.size), -1)
    index = np.maximum.accumulate(index)
    return np.where(index >= 0, step[np.maximum(index, 0)], float(last_direction))
