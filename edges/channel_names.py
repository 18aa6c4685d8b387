"""The names of the joint columns in the daemon's data, written once.

``grating<k>_counts`` is a grating reader's raw strip counter of joint ``k`` (1-based),
``encoder<k>_counts`` a motor encoder's position value (docs/topics.md). Drivers name their
channels with :func:`counts_column`; every reader (the twin's streams, the Foxglove
channels of a recording, the browser view) finds them with :func:`counts_joint` or
:func:`joint_columns`.

It lives in ``edges`` because that is the one package both sides may import
(``tests/test_import_graph.py``): drivers import only ``edges``, and the twin imports
``edges`` and the daemon's formats but never ``drivers``. A name is where the daemon's data
meets its readers, as a file's column is where a file meets its user.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

#: the kinds of joint counts columns: a grating reader's strips, the motor encoders
GRATING = "grating"
ENCODER = "encoder"
COUNTS_KINDS: tuple[str, ...] = (GRATING, ENCODER)

_COUNTS = re.compile(r"^(grating|encoder)(\d+)_counts$")


def counts_column(kind: str, joint: int) -> str:
    """The column of joint ``joint`` (1-based) of ``kind`` (:data:`COUNTS_KINDS`)."""
    if kind not in COUNTS_KINDS:
        raise ValueError(f"unknown counts kind {kind!r} (known: {', '.join(COUNTS_KINDS)})")
    return f"{kind}{joint}_counts"


def counts_joint(name: str, kind: str | None = None) -> int | None:
    """The joint (1-based) whose counts column ``name`` is, of ``kind`` (either kind when
    None); None when ``name`` is no such column."""
    m = _COUNTS.match(name)
    if m is None or (kind is not None and m.group(1) != kind):
        return None
    return int(m.group(2))


def joint_columns(names: Iterable[str], kind: str) -> list[str]:
    """The counts columns of ``kind`` among ``names``, in joint order."""
    found = sorted((j, n) for n in names if (j := counts_joint(n, kind)) is not None)
    return [n for _, n in found]
