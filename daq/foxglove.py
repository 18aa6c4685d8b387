"""Viewer channels in Foxglove's well-known JSON schemas (``foxglove.PointCloud``,
``foxglove.PosesInFrame``, ``foxglove.PoseInFrame``, ``foxglove.FrameTransform``) and
joint channels in a JSON schema of our own (named joint fields, for Foxglove's Plot
panel), so a recording shows tracker points, the twin's TCP and the arm in a 3-D panel
and plots joint angles without custom code. What derives them from the columnar streams:
:mod:`daq.foxglove_channels`.

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
POSE_IN_FRAME = "foxglove.PoseInFrame"
FRAME_TRANSFORM = "foxglove.FrameTransform"
#: our own schema of the joint channels (``<key>/joints``)
JOINTS = "grating_twin.Joints"
#: our own schema of the live twin's tracking channel (``<twin key>/tracking/values``):
#: the same layout (groups of named numbers), other groups
TRACKING = "grating_twin.Tracking"
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

SCHEMAS[POSE_IN_FRAME] = {
    "title": POSE_IN_FRAME,
    "description": "A timestamped pose for an object or reference frame in 3D space",
    "type": "object",
    "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE},
    "required": ["timestamp", "frame_id", "pose"],
}
SCHEMAS[FRAME_TRANSFORM] = {
    "title": FRAME_TRANSFORM,
    "description": "A transform between two reference frames in 3D space",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _VEC3,
        "rotation": _QUAT,
    },
    "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"],
}


def joints_schema(
    groups: dict[str, tuple[list[str], str]], description: str, title: str = JOINTS
) -> dict[str, Any]:
    """Our JSON schema of a joint channel: ``timestamp`` and, per group (``counts``,
    ``deg``, ``grating_deg`` …), an object of named joints ``j1`` … ``jN`` with a unit
    (``title`` :data:`TRACKING`: the tracking channel's groups of named numbers)."""
    props: dict[str, Any] = {"timestamp": _TIME}
    for group, (names, unit) in groups.items():
        props[group] = {
            "type": "object",
            "description": unit,
            "properties": {n: {"type": ["number", "null"], "description": unit} for n in names},
            "required": list(names),
            "additionalProperties": False,
        }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "description": description,
        "type": "object",
        "properties": props,
        "required": list(props),
        "additionalProperties": False,
    }


def _number(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None  # JSON has no NaN


def joints(t_ns: int, groups: dict[str, tuple[list[str], NDArray[Any]]]) -> bytes:
    """A joint message: per group, ``{name: value}`` of one sample's values ``(n,)``."""
    msg: dict[str, Any] = {"timestamp": _time(t_ns)}
    for group, (names, values) in groups.items():
        if np.issubdtype(values.dtype, np.integer):  # counts stay whole numbers
            msg[group] = dict(zip(names, values.tolist(), strict=True))
        else:
            msg[group] = {n: _number(v) for n, v in zip(names, values.tolist(), strict=True)}
    return json.dumps(msg).encode()


def pose_in_frame(t_ns: int, frame_id: str, xyz_mm: NDArray[Any], quat_wxyz: NDArray[Any]) -> bytes:
    """A ``foxglove.PoseInFrame`` JSON message: one position (mm) and rotation (w, x, y, z)."""
    p = (np.asarray(xyz_mm, dtype=float) / 1000.0).tolist()
    w, x, y, z = np.asarray(quat_wxyz, dtype=float).tolist()
    msg = {
        "timestamp": _time(t_ns),
        "frame_id": frame_id,
        "pose": {
            "position": {"x": p[0], "y": p[1], "z": p[2]},
            "orientation": {"x": x, "y": y, "z": z, "w": w},
        },
    }
    return json.dumps(msg).encode()


def _quat_mul(a: NDArray[Any], b: NDArray[Any]) -> NDArray[Any]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _rotate(q: NDArray[Any], v: NDArray[Any]) -> NDArray[Any]:
    """``v`` rotated by unit quaternion ``q`` (w, x, y, z)."""
    qv = np.concatenate(([0.0], v))
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    return _quat_mul(_quat_mul(q, qv), conj)[1:]


def frame_transforms(
    t_ns: int,
    names: list[str],
    parents: list[str],
    pos_mm: NDArray[Any],
    quat_wxyz: NDArray[Any],
) -> list[bytes]:
    """One ``foxglove.FrameTransform`` per frame: frames given by their poses in one
    common root (``pos_mm (k, 3)``, ``quat_wxyz (k, 4)``), each transform relative to its
    parent (the first one's parent is the root itself), metres."""
    out = []
    index = {n: i for i, n in enumerate(names)}
    for i, (name, parent) in enumerate(zip(names, parents, strict=True)):
        p, q = np.asarray(pos_mm[i], float), np.asarray(quat_wxyz[i], float)
        j = index.get(parent)
        if j is not None:  # relative to the parent: R_p^T (p - p_p), q_p^-1 q
            qp = np.asarray(quat_wxyz[j], float) * np.array([1.0, -1.0, -1.0, -1.0])
            p = _rotate(qp, p - np.asarray(pos_mm[j], float))
            q = _quat_mul(qp, q)
        p = p / 1000.0
        w, x, y, z = (q / np.linalg.norm(q)).tolist()
        msg = {
            "timestamp": _time(t_ns),
            "parent_frame_id": parent,
            "child_frame_id": name,
            "translation": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])},
            "rotation": {"x": x, "y": y, "z": z, "w": w},
        }
        out.append(json.dumps(msg).encode())
    return out


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
