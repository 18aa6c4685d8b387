"""Foxglove (viewer) channels derived from the columnar streams while recording (docs/daq.md,
"Recording"): what Foxglove reads natively, beside the columnar data it cannot decode.

Per stream, by its columns (so the same code serves the daemon, its workers' streams,
``daq record`` and the live twin's keys):

* gratings, encoders (``grating<k>_counts``, ``encoder<k>_counts``): ``<key>/joints``,
  schema ``grating_twin.Joints`` (``counts.j1`` …, raw counts);
* tracker (``x_mm``, ``y_mm``, ``z_mm``): ``<key>/points``, ``foxglove.PointCloud``
  (``<key>/poses``, ``foxglove.PosesInFrame``, with ``foxglove = "poses"``);
* the twin's state (``q_deg``, ``tcp_mm``, ``flange_quat``): ``<key>/joints``
  (``grating_deg``, ``encoder_deg``, ``encoder_minus_grating_deg``) and ``<key>/tcp``,
  ``foxglove.PoseInFrame``;
* the twin's frames (``frame_mm``, ``frame_quat``): ``<key>/tf``,
  ``foxglove.FrameTransform``, one message per link frame;
* the twin's tracking (``parameters``, ``standard_errors``, ``error_mm``, ``state``):
  ``<key>/values``, schema ``grating_twin.Tracking`` (groups ``parameters``,
  ``standard_errors`` by parameter name, ``tracking``: error, λ, state code, steps, alarms).

**Bounded rate.** A stream's viewer messages are written at most ``rate_hz`` times a
second (``[recording] viewer_rate_hz``, 30): the newest sample's joints, TCP and
frames; the points of *every* sample since the last message (nothing the tracker measured
is left out of the viewer). Between two messages a stream costs the recorder one time
comparison, plus, for points, one copy of three columns, so the recorder's hot path
(one ``write`` of the columnar payload per message) stays as it was. Foxglove
interpolates nothing: 30 Hz is what a 3-D panel or a plot shows smoothly.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

import daq.foxglove as foxglove
from daq.columnar import StreamSchema
from edges.channel_names import counts_joint

#: default of ``[recording] viewer_rate_hz``
VIEWER_RATE_HZ = 30.0
KIND_FOXGLOVE = "foxglove"  # MCAP channel metadata ``daq.kind`` (daq.recording_writer)
#: the live twin's tracking columns in its viewer channel's ``tracking`` group
TRACKING_FIELDS = (
    "error_mm",
    "lambda",
    "displacement_mm",
    "state",
    "steps",
    "alarms",
)


def _joint_names(schema: StreamSchema, columns: list[str]) -> list[str]:
    """``j<joint>`` per column: the schema's ``meta.joints`` when it has one per column,
    else the number in the column's name."""
    joints = schema.meta.get("joints")
    if isinstance(joints, list) and len(joints) == len(columns):
        return [f"j{int(j)}" for j in joints]
    out = []
    for c in columns:
        j = counts_joint(c)
        out.append(f"j{j}" if j is not None else c)
    return out


class ViewerRecorder(Protocol):
    """Where the viewer channels go: :class:`~daq.recording_writer.McapRecorder`, or
    :class:`~daq.recording_writer.BackgroundRecorder` in front of one."""

    def add_json(
        self,
        topic: str,
        schema_name: str,
        json_schema: Mapping[str, Any] | bytes,
        metadata: Mapping[str, str] | None = None,
        /,
    ) -> int: ...

    def write(
        self, channel_id: int, data: bytes, log_time_ns: int, publish_time_ns: int, /
    ) -> None: ...


class StreamViewer:
    """The viewer channels of one columnar stream, registered on ``recorder`` (anything
    with ``add_json`` and ``write``: :class:`~daq.recording_writer.McapRecorder`,
    :class:`~daq.recording_writer.BackgroundRecorder`). ``points``: the device's ``foxglove``
    setting (``auto``, ``points``, ``poses``, ``none``) for xyz streams."""

    def __init__(
        self,
        recorder: ViewerRecorder,
        schema: StreamSchema,
        *,
        rate_hz: float = VIEWER_RATE_HZ,
        points: str = "auto",
        frame_id: str = "tracker",
    ) -> None:
        self.rec = recorder
        self.schema = schema
        self.key = schema.key
        self.frame_id = frame_id
        self.period_ns = int(1e9 / rate_hz) if rate_hz > 0 else 0
        self.next_ns = 0
        self.messages = 0
        names = list(schema.names)
        meta = {"daq.kind": KIND_FOXGLOVE, "derived_from": schema.key}
        self._joints: tuple[int, list[tuple[str, str, list[str]]]] | None = None
        self._points: tuple[int, str, tuple[str, str, str]] | None = None
        self._pts: list[np.ndarray] = []
        self._last_stamp = 0
        self._tcp: int | None = None
        self._tf: tuple[int, list[str], list[str]] | None = None
        if not self.period_ns:
            return
        counts = [n for n in names if counts_joint(n) is not None]
        if {"q_deg", "tcp_mm", "flange_quat"} <= set(names):  # the live twin's state
            self._add_twin_state(names, meta)
        elif {"frame_mm", "frame_quat"} <= set(names):  # the live twin's link frames
            self._add_twin_frames(meta)
        elif {"parameters", "standard_errors", "error_mm", "state"} <= set(names):
            self._add_twin_tracking(meta)
        elif counts:  # gratings, encoders: raw counts per named joint
            self._add_counts(counts, meta)
        xyz = foxglove.xyz_columns(names)
        if xyz is not None and points in ("points", "poses", "auto"):
            self._add_points(xyz, points, meta)

    def _add_twin_state(self, names: list[str], meta: dict[str, str]) -> None:
        """The live twin's joints (grating angles, and the encoders' when it has them)
        and its TCP pose."""
        n = int(self.schema.column("q_deg").shape[0])
        j = [f"j{i + 1}" for i in range(n)]
        groups = {"grating_deg": (j, "deg, from the gratings through the scale maps")}
        spec = [("grating_deg", "q_deg", j)]
        if "encoder_minus_grating_deg" in names:
            groups["encoder_deg"] = (j, "deg, motor encoder (NaN/null: none yet)")
            groups["encoder_minus_grating_deg"] = (j, "deg")
            spec += [("encoder_deg", "", j), ("encoder_minus_grating_deg", "", j)]
        cid = self.rec.add_json(
            f"{self.key}/joints",
            foxglove.JOINTS,
            foxglove.joints_schema(groups, f"joint angles of {self.key}"),
            meta,
        )
        self._joints = (cid, spec)
        self._tcp = self.rec.add_json(
            f"{self.key}/tcp",
            foxglove.POSE_IN_FRAME,
            foxglove.schema_bytes(foxglove.POSE_IN_FRAME),
            {**meta, "frame_id": self.frame_id},
        )

    def _add_twin_frames(self, meta: dict[str, str]) -> None:
        """The live twin's link frames as transforms (when the schema names them and
        their parents)."""
        frames = [str(f) for f in self.schema.meta.get("frames", [])]
        parents = [str(p) for p in self.schema.meta.get("parents", [])]
        if frames and len(parents) == len(frames):
            cid = self.rec.add_json(
                f"{self.key}/tf",
                foxglove.FRAME_TRANSFORM,
                foxglove.schema_bytes(foxglove.FRAME_TRANSFORM),
                meta,
            )
            self._tf = (cid, frames, parents)

    def _add_twin_tracking(self, meta: dict[str, str]) -> None:
        """The live twin's tracking updates: the tracked parameters, their standard errors
        and the one-step-ahead error, λ, state code, steps and alarms (plottable)."""
        params = [str(p) for p in self.schema.meta.get("parameters", [])]
        states = ", ".join(f"{i} {s}" for i, s in enumerate(self.schema.meta.get("states", [])))
        groups = {
            "parameters": (params, "tracked values, model units"),
            "standard_errors": (params, "their standard errors"),
            "tracking": (list(TRACKING_FIELDS), f"mm, λ, state code ({states}), counts"),
        }
        cid = self.rec.add_json(
            f"{self.key}/values",
            foxglove.TRACKING,
            foxglove.joints_schema(groups, f"tracking of {self.key}", foxglove.TRACKING),
            meta,
        )
        spec = [("parameters", "", params), ("standard_errors", "", params)]
        self._joints = (cid, [*spec, ("tracking", "", list(TRACKING_FIELDS))])

    def _add_counts(self, counts: list[str], meta: dict[str, str]) -> None:
        """A device's raw counts per named joint."""
        j = _joint_names(self.schema, counts)
        unit = "counts (raw; angles: the live twin's <twin key>/joints)"
        cid = self.rec.add_json(
            f"{self.key}/joints",
            foxglove.JOINTS,
            foxglove.joints_schema({"counts": (j, unit)}, f"joint counters of {self.key}"),
            meta,
        )
        self._joints = (cid, [("counts", "", j)])
        self._counts_columns = counts

    def _add_points(self, xyz: tuple[str, str, str], points: str, meta: dict[str, str]) -> None:
        """The xyz columns as a point cloud, or as poses (``points`` "poses")."""
        name = foxglove.POSES_IN_FRAME if points == "poses" else foxglove.POINT_CLOUD
        cid = self.rec.add_json(
            f"{self.key}/{'poses' if points == 'poses' else 'points'}",
            name,
            foxglove.schema_bytes(name),
            {**meta, "frame_id": self.frame_id},
        )
        self._points = (cid, name, xyz)

    @property
    def active(self) -> bool:
        """Whether this stream has any viewer channel."""
        return any(x is not None for x in (self._joints, self._points, self._tcp, self._tf))

    def due(self, t_ns: int) -> bool:
        """Whether a batch logged at ``t_ns`` needs decoding: points are collected from
        every batch, the rest only once per period."""
        return self.active and (self._points is not None or t_ns >= self.next_ns)

    def add(self, cols: dict[str, Any], t_ns: int) -> None:
        """A decoded batch, logged at ``t_ns`` (host UTC ns); writes when a period is over."""
        if not self.active or not len(cols.get("t_mapped_ns", ())):
            return
        if self._points is not None:
            x, y, z = self._points[2]
            self._pts.append(np.column_stack([cols[x], cols[y], cols[z]]).astype(float))
            self._last_stamp = int(cols["t_mapped_ns"][-1])
        if t_ns < self.next_ns:
            return
        self.next_ns = t_ns + self.period_ns
        stamp = int(cols["t_mapped_ns"][-1])
        if self._points is not None:
            cid, name, _ = self._points
            xyz = np.concatenate(self._pts) if len(self._pts) > 1 else self._pts[0]
            self._pts = []
            msg = (
                foxglove.poses_in_frame(stamp, self.frame_id, xyz)
                if name == foxglove.POSES_IN_FRAME
                else foxglove.point_cloud(stamp, self.frame_id, xyz)
            )
            self._write(cid, msg, t_ns)
        if self._joints is not None:
            cid, spec = self._joints
            groups: dict[str, tuple[list[str], np.ndarray]] = {}
            for group, column, names in spec:
                if group == "counts":
                    values = np.array([cols[c][-1] for c in self._counts_columns], np.int64)
                elif group == "encoder_deg":
                    values = cols["q_deg"][-1] + cols["encoder_minus_grating_deg"][-1]
                elif group == "tracking":
                    values = np.array([float(cols[c][-1]) for c in TRACKING_FIELDS])
                else:
                    values = np.asarray(cols[column or group][-1], dtype=float)
                groups[group] = (names, values)
            self._write(cid, foxglove.joints(stamp, groups), t_ns)
        if self._tcp is not None:
            msg = foxglove.pose_in_frame(
                stamp, self.frame_id, cols["tcp_mm"][-1], cols["flange_quat"][-1]
            )
            self._write(self._tcp, msg, t_ns)
        if self._tf is not None:
            cid, frames, parents = self._tf
            for msg in foxglove.frame_transforms(
                stamp, frames, parents, cols["frame_mm"][-1], cols["frame_quat"][-1]
            ):
                self._write(cid, msg, t_ns)

    def flush(self, t_ns: int) -> None:
        """Write the points collected since the last message (at the end of a recording)."""
        if self._points is not None and self._pts:
            cid, name, _ = self._points
            xyz = np.concatenate(self._pts)
            self._pts = []
            stamp = self._last_stamp
            msg = (
                foxglove.poses_in_frame(stamp, self.frame_id, xyz)
                if name == foxglove.POSES_IN_FRAME
                else foxglove.point_cloud(stamp, self.frame_id, xyz)
            )
            self._write(cid, msg, t_ns)

    def _write(self, cid: int, msg: bytes, t_ns: int) -> None:
        self.rec.write(cid, msg, t_ns, t_ns)
        self.messages += 1
