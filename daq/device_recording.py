"""One device's channels in the daemon's recording, whichever mode runs the device.

:class:`DeviceRecording` registers them on the recorder, in this order: the device's
health key (JSON, ``daq.health.v1``), then per channel group its columnar key and the
Foxglove viewer channels derived from it (:mod:`daq.foxglove_channels`). A device stream in a thread
writes its messages as it publishes them (:mod:`daq.pipeline`); a device in a worker
process is written from the daemon's subscription to its keys (:mod:`daq.worker`); the
health loop writes the health documents (:mod:`daq.health`). The recording is the same.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import daq.foxglove as foxglove
from daq.bus import health_key
from daq.columnar import StreamSchema
from daq.config import DaqConfig, DeviceConfig
from daq.foxglove_channels import StreamViewer
from daq.recording_writer import HEALTH_SCHEMA, HEALTH_SCHEMA_NAME, KIND_HEALTH, BackgroundRecorder

log = logging.getLogger(__name__)


def recorder_meta(s: StreamSchema) -> dict[str, str]:
    """An MCAP channel's metadata: the schema's scalar meta entries, as strings."""
    return {k: str(v) for k, v in s.meta.items() if not isinstance(v, dict | list)}


def viewer_for(
    recorder: BackgroundRecorder, cfg: DaqConfig, dev: DeviceConfig, s: StreamSchema, first: bool
) -> StreamViewer | None:
    """The Foxglove viewer channels of one of the device's keys (``first``: the key that
    carries the points of an xyz device), or None when it has none (docs/daq.md)."""
    v = StreamViewer(
        recorder,
        s,
        rate_hz=cfg.recording.viewer_rate_hz,
        points=dev.foxglove if first else "none",
        frame_id=dev.frame_id,
    )
    if dev.foxglove in ("points", "poses") and foxglove.xyz_columns(list(s.names)) is None:
        log.warning("%s: foxglove=%s but no x_mm/y_mm/z_mm columns", s.key, dev.foxglove)
    return v if v.active else None


class DeviceRecording:
    """The recorder channels of ``dev``: its health channel, and per schema of
    ``schemas`` (the device's channel groups, :func:`daq.pipeline.build_schemas`) a
    columnar channel and its viewer channels. Thread-safe as the recorder is, per group."""

    def __init__(
        self,
        recorder: BackgroundRecorder,
        cfg: DaqConfig,
        dev: DeviceConfig,
        schemas: Sequence[StreamSchema],
    ) -> None:
        self.recorder = recorder
        self.health_channel = recorder.add_json(
            health_key(cfg.cell.name, dev.robot, dev.name),
            HEALTH_SCHEMA_NAME,
            HEALTH_SCHEMA,
            {"daq.kind": KIND_HEALTH},
        )
        self.data_channels: list[int] = []
        self.viewers: list[StreamViewer | None] = []
        for gi, s in enumerate(schemas):
            self.data_channels.append(recorder.add_columnar(s, recorder_meta(s)))
            self.viewers.append(viewer_for(recorder, cfg, dev, s, gi == 0))

    def write(
        self,
        group: int,
        payloads: Sequence[bytes],
        t_ns: int,
        first_seq: int,
        columns: dict[str, Any] | Callable[[], dict[str, Any]],
    ) -> None:
        """The messages of channel group ``group`` (batch_seq ``first_seq`` onwards),
        logged at ``t_ns`` (host UTC ns). ``columns``: their samples, or a function that
        decodes them, called only when a viewer message is due (a worker's payloads)."""
        channel = self.data_channels[group]
        for k, payload in enumerate(payloads):
            self.recorder.write(channel, payload, t_ns, t_ns, first_seq + k)
        viewer = self.viewers[group]
        if viewer is not None and viewer.due(t_ns):  # at a bounded rate (daq.foxglove_channels)
            viewer.add(columns() if callable(columns) else columns, t_ns)

    def write_health(self, doc: bytes) -> None:
        """One health document (JSON), logged now."""
        t = time.time_ns()
        self.recorder.write(self.health_channel, doc, t, t)

    def flush(self) -> None:
        """The points collected since the last viewer message (at the end of a run)."""
        t = time.time_ns()
        for v in self.viewers:
            if v is not None:
                v.flush(t)
