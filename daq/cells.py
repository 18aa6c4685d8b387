"""Cells on one bus: the keys of one cell, and the cells a router carries.

Several cells share a router (docs/deployment.md, "Several cells"): a cell's daemon
publishes under ``cell/<name>/…`` and its live twin under ``twin/<name>/…``. A subscriber
picks a cell with ``--cell NAME`` (``daq echo``, ``twin view``); :func:`cells_on_bus`
says which cells are up: the cells of the devices' liveliness tokens
(``cell/<cell>/robot/<robot>/<device>``, held by every device of a daemon or a replay).
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from daq.config import NAME_RE

if TYPE_CHECKING:
    import zenoh

#: how long a command asks the bus for the cells that are up (s): the replies of the
#: devices already up come within milliseconds on a link, this bounds a silent one
CELLS_WAIT_S = 1.5


def cell_name(text: str) -> str:
    """An ``argparse`` ``type=``: a cell name, one chunk of a zenoh key (``cell2``)."""
    if not NAME_RE.match(text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a cell name (letters, digits, '_', '-', '.' only: one key chunk)"
        )
    return text


def cell_data_key(cell: str) -> str:
    """The key expression of every data and health key of ``cell``'s daemon."""
    return f"cell/{cell}/**"


def cell_twin_key(cell: str) -> str:
    """The key expression of every key of ``cell``'s live twin."""
    return f"twin/{cell}/**"


def cells_on_bus(session: zenoh.Session, wait_s: float = CELLS_WAIT_S) -> tuple[str, ...]:
    """The names of the cells with a device up (sorted), from the liveliness tokens the
    session can see within ``wait_s`` seconds (empty: none up, or none answered)."""
    names: set[str] = set()
    for reply in session.liveliness().get("cell/*/**", timeout=wait_s):
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) > 2:
                names.add(parts[1])
    return tuple(sorted(names))


def echo_key(key: str | None, cell: str | None) -> str:
    """The key expression ``daq echo`` subscribes to: ``key`` (default ``cell/**``, every
    cell), or with ``cell`` that cell's keys (``cell/<cell>/**``); a ``key`` given with
    ``cell`` must lie within the cell's daemon or twin keys (:class:`ConfigError`)."""
    import zenoh

    from daq.errors import ConfigError

    if cell is None:
        return key or "cell/**"
    if key is None:
        return cell_data_key(cell)
    given = zenoh.KeyExpr(key)
    if any(zenoh.KeyExpr(k).includes(given) for k in (cell_data_key(cell), cell_twin_key(cell))):
        return key
    raise ConfigError(
        f"KEYEXPR {key!r}: outside --cell {cell}'s keys ({cell_data_key(cell)}, "
        f"{cell_twin_key(cell)}); give one of them, or drop --cell"
    )
