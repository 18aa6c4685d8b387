"""Whether the emulated tracker sees the reflector: the cell's geometry on the true robot.

The view test itself is the twin's (:mod:`calibration.model.cell_geometry`, the same keys of
``cell.toml``); what the emulator adds is its truth: the true geometry of the arm and the
tracker where the emulator really put it (the instrument frame's origin, placed by the
true base), not where a cell file's ``[station]`` says a person measured it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.cell_geometry import (
    CellGeometry,
    CellGeometrySpec,
    collision_codes,
    default_station_mm,
    reflector_in_base,
    resolve,
    view_codes,
)
from sim_devices.truth import TrueCell


def cell_geometry(cell: TrueCell, spec: CellGeometrySpec) -> CellGeometry:
    """The cell's geometry (defaults from the nominal robot, as a planner sees them)."""
    return resolve(spec, cell.nominal)


def true_station_mm(cell: TrueCell) -> NDArray[np.float64]:
    """Where the emulated tracker is, in the true robot base frame (mm, ``(3,)``)."""
    return default_station_mm(cell.truth)


def true_view_codes(cell: TrueCell, geometry: CellGeometry, q_rad: ArrayLike) -> NDArray[np.int8]:
    """Per joint vector ``(N, n)`` rad: 0 when the emulated tracker sees the TCP reflector,
    else the reason code of :data:`calibration.model.cell_geometry.VIEW_REASONS`."""
    pos, axis = reflector_in_base(cell.model, geometry, q_rad)
    return view_codes(geometry, pos, axis, station_mm=true_station_mm(cell))


def true_collision_codes(
    cell: TrueCell, geometry: CellGeometry, q_rad: ArrayLike
) -> NDArray[np.int8]:
    """:func:`calibration.model.cell_geometry.collision_codes` on the true arm."""
    return collision_codes(cell.model, geometry, q_rad)
