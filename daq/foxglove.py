"""Viewer channels in Foxglove's well-known JSON schemas (``foxglove.PointCloud``,
``foxglove.PosesInFrame``), so a recording shows tracker points and TCP poses in a 3-D
panel without custom code.

Foxglove's convention is metres; our columns are millimetres, so positions are divided by
1000 here. The schemas below follow the published JSON schemas' field names and types
(timestamp {sec, nsec}, frame_id, pose, point_stride, fields, base64 data; poses[]).
"""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np
from numpy.typing import NDArray

POINT_CLOUD = "foxglove.PointCloud"
POSES_IN_FRAME = "foxglove.PosesInFrame"
FLOAT64 = 8  # foxglove.NumericType

_TIME = {
    "type": "object",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}
_VEC3 = {
    "title": "foxglove.Vector3",
    "type": "object",
    "properties": {k: {"type": "number"} for k in "xyz"},
    "required": ["x", "y", "z"],
}
_QUAT = {
    "title": "foxglove.Quaternion",
    "type": "object",
    "properties": {k: {"type": "number"} for k in "xyzw"},
    "required": ["x", "y", "z", "w"],
}
_POSE = {
    "title": "foxglove.Pose",
    "type": "object",
    "properties": {"position": _VEC3, "orientation": _QUAT},
    "required": ["position", "orientation"],
}

SCHEMAS: dict[str, dict[str, Any]] = {
    POINT_CLOUD: {
        "title": POINT_CLOUD,
        "description": "A collection of N-dimensional points",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": _POSE,
            "point_stride": {"type": "integer", "minimum": 0},
            "fields": {
                "type": "array",
                "items": {
                    "title": "foxglove.PackedElementField",
                    "type": "object",
                    "properties": {
                        "name": {"type": "string"},
                        "offset": {"type": "integer", "minimum": 0},
                        "type": {"title": "foxglove.NumericType", "type": "integer"},
                    },
                    "required": ["name", "offset", "type"],
                },
            },
            "data": {"type": "string", "contentEncoding": "base64"},
        },
        "required": ["timestamp", "frame_id", "pose", "point_stride", "fields", "data"],
    },
    POSES_IN_FRAME: {
        "title": POSES_IN_FRAME,
        "description": "An array of timestamped poses in 3D space",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "poses": {"type": "array", "items": _POSE},
        },
        "required": ["timestamp", "frame_id", "poses"],
    },
}

_IDENTITY_POSE = {
    "position": {"x": 0.0, "y": 0.0, "z": 0.0},
    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
}


def schema_bytes(name: str) -> bytes:
    return json.dumps(SCHEMAS[name]).encode()


def _time(t_ns: int) -> dict[str, int]:
    t_ns = max(0, int(t_ns))
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def xyz_columns(names: tuple[str, ...] | list[str]) -> tuple[str, str, str] | None:
    """The first ``(…x_mm, …y_mm, …z_mm)`` triple among column ``names``, if any."""
    for n in names:
        if n.endswith("x_mm"):
            prefix = n[: -len("x_mm")]
            y, z = f"{prefix}y_mm", f"{prefix}z_mm"
            if y in names and z in names:
                return n, y, z
    return None


def point_cloud(t_ns: int, frame_id: str, xyz_mm: NDArray[Any]) -> bytes:
    """A ``foxglove.PointCloud`` JSON message of the finite points ``(N, 3)`` mm."""
    pts = np.asarray(xyz_mm, dtype="<f8").reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)] / 1000.0
    msg = {
        "timestamp": _time(t_ns),
        "frame_id": frame_id,
        "pose": _IDENTITY_POSE,
        "point_stride": 24,
        "fields": [
            {"name": "x", "offset": 0, "type": FLOAT64},
            {"name": "y", "offset": 8, "type": FLOAT64},
            {"name": "z", "offset": 16, "type": FLOAT64},
        ],
        "data": base64.b64encode(np.ascontiguousarray(pts).tobytes()).decode(),
    }
    return json.dumps(msg).encode()


def poses_in_frame(
    t_ns: int, frame_id: str, xyz_mm: NDArray[Any], quat_xyzw: NDArray[Any] | None = None
) -> bytes:
    """A ``foxglove.PosesInFrame`` JSON message: positions ``(N, 3)`` mm, quats ``(N, 4)``."""
    pts = np.asarray(xyz_mm, dtype=float).reshape(-1, 3)
    q = (
        np.tile([0.0, 0.0, 0.0, 1.0], (len(pts), 1))
        if quat_xyzw is None
        else np.asarray(quat_xyzw, dtype=float).reshape(-1, 4)
    )
    ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(q), axis=1)
    poses = [
        {
            "position": dict(zip("xyz", (p / 1000.0).tolist(), strict=True)),
            "orientation": dict(zip("xyzw", qq.tolist(), strict=True)),
        }
        for p, qq in zip(pts[ok], q[ok], strict=True)
    ]
    return json.dumps({"timestamp": _time(t_ns), "frame_id": frame_id, "poses": poses}).encode()
