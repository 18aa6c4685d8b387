"""The live twin's zenoh keys and their column schemas (docs/topics.md, "Twin keys")."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from daq.columnar import StreamSchema

FloatArray = NDArray[np.float64]

TWIN_PREFIX = "twin"


def twin_keys(cell: str, robot: str) -> dict[str, str]:
    base = f"{TWIN_PREFIX}/{cell}/robot/{robot}"
    return {
        "state": f"{base}/state",
        "health": f"{base}/health",
        "frames": f"{base}/frames",
        "tracking": f"{base}/tracking",
    }


def state_schema(key: str, n: int, cell: str, robot: str, model: str) -> StreamSchema:
    """The columns of ``twin/<cell>/robot/<robot>/state`` (docs/topics.md, "Twin keys")."""
    from daq.columnar import Column, StreamSchema

    return StreamSchema(
        key,
        (
            Column("seq", "uint64", (), "", None, "twin sample number"),
            Column("t_mapped_ns", "int64", (), "ns", "host_utc", "grating sample time"),
            Column("t_publish_ns", "int64", (), "ns", "host_utc", "when published"),
            Column("q_deg", "float64", (n,), "deg", None, "joint angles from the gratings"),
            Column("tcp_mm", "float64", (3,), "mm", None, "TCP, tracker frame"),
            Column("flange_mm", "float64", (3,), "mm", None, "flange origin"),
            Column("flange_quat", "float64", (4,), "", None, "flange rotation w, x, y, z"),
            Column(
                "encoder_minus_grating_deg",
                "float64",
                (n,),
                "deg",
                None,
                "motor encoder joint angle minus grating angle (NaN: no encoder)",
            ),
        ),
        {"cell": cell, "robot": robot, "model": model, "source": "twin run"},
    )


#: ``state`` column codes of ``twin/.../tracking`` (the schema's ``meta.states``).
TRACKING_STATES = ("following", "step", "alarm")


def tracking_schema(
    key: str, names: tuple[str, ...], cell: str, robot: str, model: str
) -> StreamSchema:
    """The columns of ``twin/<cell>/robot/<robot>/tracking``: one row per production dwell
    that updated the tracked model (docs/topics.md, "Twin keys"; ``meta.parameters``: the
    tracked parameters' model names, ``meta.states``: the ``state`` codes)."""
    from daq.columnar import Column, StreamSchema

    k = len(names)
    return StreamSchema(
        key,
        (
            Column("seq", "uint64", (), "", None, "tracking update number"),
            Column("t_mapped_ns", "int64", (), "ns", "host_utc", "the dwell's tracker samples"),
            Column("t_publish_ns", "int64", (), "ns", "host_utc", "when published"),
            Column("point_mm", "float64", (3,), "mm", None, "the dwell's mean tracker point"),
            Column("predicted_mm", "float64", (3,), "mm", None, "a-priori prediction"),
            Column("error_mm", "float64", (), "mm", None, "one-step-ahead error"),
            Column("parameters", "float64", (k,), "", None, "tracked values, model units"),
            Column("standard_errors", "float64", (k,), "", None, "their standard errors"),
            Column("lambda", "float64", (), "", None, "forgetting factor"),
            Column("state", "uint8", (), "", None, "0 following, 1 step, 2 alarm"),
            Column("displacement_mm", "float64", (), "mm", None, "TCP move, validation poses"),
            Column("steps", "uint32", (), "", None, "steps detected so far"),
            Column("alarms", "uint32", (), "", None, "alarms raised so far"),
        ),
        {
            "cell": cell,
            "robot": robot,
            "model": model,
            "source": "twin run",
            "parameters": list(names),
            "states": list(TRACKING_STATES),
        },
    )


def frames_schema(
    key: str, names: tuple[str, ...], cell: str, robot: str, model: str
) -> StreamSchema:
    """The columns of ``twin/<cell>/robot/<robot>/frames``: every link frame of the
    calibrated model at one grating sample, in the tracker frame (``meta.frames``: their
    names, ``meta.parents``: each one's parent frame, the first one's is ``tracker``)."""
    from daq.columnar import Column, StreamSchema

    k = len(names)
    return StreamSchema(
        key,
        (
            Column("seq", "uint64", (), "", None, "frames sample number"),
            Column("t_mapped_ns", "int64", (), "ns", "host_utc", "grating sample time"),
            Column("frame_mm", "float64", (k, 3), "mm", None, "frame origins, tracker frame"),
            Column("frame_quat", "float64", (k, 4), "", None, "frame rotations w, x, y, z"),
        ),
        {
            "cell": cell,
            "robot": robot,
            "model": model,
            "source": "twin run",
            "frames": list(names),
            "parents": ["tracker", *names[:-1]],
        },
    )
