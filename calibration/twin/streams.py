"""The daemon's sample streams as whole column arrays: from an MCAP recording or live batches.

The twin needs three streams: the grating reader (``grating<k>_counts``), the laser tracker
(``x_mm, y_mm, z_mm``) and, optionally, the motor encoders (``encoder<k>_counts``). A
stream's kind is decided by its columns, not by the device's name, so any cell whose
drivers publish those columns works. Recordings are *streamed* with the project's reader
(``daq.recording_reader.read_recording``), which also reads a truncated file up to its last
complete chunk.

Lost data is never hidden: :func:`lost_intervals` lists, per stream, the mapped-time spans
with no samples (a ``seq`` jump within an epoch, a device restart, or a mapped-time step
over ``gap_factor`` median periods).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calibration.errors import StreamError
from edges.channel_names import ENCODER, GRATING, counts_joint, joint_columns

if TYPE_CHECKING:  # the reader (and mcap) load only when a recording is read
    from daq.recording_reader import RecordedMessage, Recording

KINDS = ("grating", "tracker", "encoders")


def stream_kind(column_names: Iterable[str]) -> str:
    """``grating``, ``tracker``, ``encoders`` or ``other`` from a schema's column names."""
    names = set(column_names)
    if any(counts_joint(n, GRATING) is not None for n in names):
        return "grating"
    if {"x_mm", "y_mm", "z_mm"} <= names:
        return "tracker"
    if any(counts_joint(n, ENCODER) is not None for n in names):
        return "encoders"
    return "other"


@dataclass
class Stream:
    """One device's samples, concatenated in arrival order.

    ``t_ns`` (N,) int64: mapped host-UTC time of each sample (``t_mapped_ns``);
    ``values`` (N, k): counts (int64) or tracker mm (float64); ``status`` (N, k) uint16 or
    None; ``seq`` (N,) uint64, ``epoch`` (N,) int32; ``t_rx_ns`` (N,) host receive time.
    """

    key: str
    kind: str
    device: str
    channels: list[str]
    t_ns: NDArray[np.int64]
    values: NDArray[Any]
    status: NDArray[np.uint16] | None
    seq: NDArray[np.uint64]
    epoch: NDArray[np.int32]
    t_rx_ns: NDArray[np.int64]
    mapped_ok: NDArray[np.uint8]
    t_device_us: NDArray[np.int64]
    meta: dict[str, Any] = field(default_factory=dict)
    lost_batches: int = 0

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def remapped(self) -> Stream:
        """The stream with ``t_ns`` re-derived from the settled clock fits, per epoch.

        The daemon maps device time online; its first seconds (``t_mapped_ok == 0``) can be
        off by a large amount. Afterwards the whole recording is known, so each epoch's
        device clock is mapped with one least-squares line (offset and drift) through its
        settled samples' mapped times. Epochs without settled samples keep their values.
        """
        t = self.t_ns.copy()
        for e in np.unique(self.epoch).tolist():
            sel = self.epoch == e
            ok = sel & (self.mapped_ok == 1)
            if np.count_nonzero(ok) < 2:
                continue
            dev0 = int(self.t_device_us[ok][0])
            map0 = int(self.t_ns[ok][0])
            x = (self.t_device_us[ok] - dev0).astype(np.float64)
            y = (self.t_ns[ok] - map0).astype(np.float64)
            if np.ptp(x) <= 0:
                continue
            b, a = np.polyfit(x, y, 1)
            xs = (self.t_device_us[sel] - dev0).astype(np.float64)
            t[sel] = map0 + np.rint(a + b * xs).astype(np.int64)
        return replace(self, t_ns=t)


class StreamBuilder:
    """Collects decoded batches of one key (recording or live) into a :class:`Stream`."""

    def __init__(self, key: str, schema_doc: dict[str, Any]) -> None:
        names = [c["name"] for c in schema_doc["columns"]]
        self.key = key
        self.kind = stream_kind(names)
        self.meta = dict(schema_doc.get("meta") or {})
        self.device = str(self.meta.get("device") or key.rsplit("/", 2)[-2])
        if self.kind == "grating":
            self.channels = joint_columns(names, GRATING)
        elif self.kind == "encoders":
            self.channels = joint_columns(names, ENCODER)
        elif self.kind == "tracker":
            self.channels = ["x_mm", "y_mm", "z_mm"]
        else:
            self.channels = []
        status_channels = self.meta.get("status_channels") or []
        self._status_index = [
            status_channels.index(c) if c in status_channels else -1 for c in self.channels
        ]
        self._parts: dict[str, list[NDArray[Any]]] = {
            k: [] for k in ("t", "v", "s", "seq", "epoch", "rx", "ok", "dev")
        }
        self._last_batch_seq: int | None = None
        self.lost_batches = 0

    def add(self, batch_seq: int, cols: dict[str, NDArray[Any]]) -> None:
        if self._last_batch_seq is not None and batch_seq > self._last_batch_seq + 1:
            self.lost_batches += batch_seq - self._last_batch_seq - 1
        self._last_batch_seq = batch_seq
        p = self._parts
        p["t"].append(np.asarray(cols["t_mapped_ns"], dtype=np.int64))
        p["v"].append(np.column_stack([cols[c] for c in self.channels]))
        status = self.status_of(cols)
        if status is not None:
            p["s"].append(status)
        p["seq"].append(np.asarray(cols["seq"], dtype=np.uint64))
        p["epoch"].append(np.asarray(cols["epoch"], dtype=np.int32))
        p["rx"].append(np.asarray(cols["t_host_rx_ns"], dtype=np.int64))
        p["ok"].append(np.asarray(cols["t_mapped_ok"], dtype=np.uint8))
        p["dev"].append(np.asarray(cols["t_device_us"], dtype=np.int64))

    def status_of(self, cols: dict[str, NDArray[Any]]) -> NDArray[np.uint16] | None:
        """A batch's status ``(m, k)`` of this stream's channels (None: the batch has none)."""
        if "status" in cols and all(i >= 0 for i in self._status_index):
            out: NDArray[np.uint16] = np.asarray(cols["status"])[:, self._status_index]
            return out.astype(np.uint16)
        return None

    def build(self) -> Stream:
        p = self._parts
        k = len(self.channels)
        vdtype = np.float64 if self.kind == "tracker" else np.int64

        def cat(name: str, dtype: Any, shape: tuple[int, ...] = ()) -> NDArray[Any]:
            if not p[name]:
                return np.empty((0, *shape), dtype=dtype)
            return np.concatenate(p[name]).astype(dtype, copy=False)

        status = cat("s", np.uint16, (k,)) if len(p["s"]) == len(p["t"]) and p["s"] else None
        return Stream(
            self.key,
            self.kind,
            self.device,
            self.channels,
            cat("t", np.int64),
            cat("v", vdtype, (k,)),
            status,
            cat("seq", np.uint64),
            cat("epoch", np.int32),
            cat("rx", np.int64),
            cat("ok", np.uint8),
            cat("dev", np.int64),
            self.meta,
            self.lost_batches,
        ).remapped()


@dataclass
class CellStreams:
    """The streams of one cell: the grating, the tracker and (optional) the encoders."""

    grating: Stream
    tracker: Stream
    encoders: Stream | None
    source: str
    complete: bool = True
    note: str = ""

    def lost(self, gap_factor: float = 5.0) -> list[dict[str, Any]]:
        out = []
        for s in (self.grating, self.tracker, self.encoders):
            if s is not None:
                out.extend(lost_intervals(s, gap_factor))
        return out


def pick_streams(
    builders: dict[str, StreamBuilder], source: str, *, complete: bool = True, note: str = ""
) -> CellStreams:
    """The first (by key, sorted) stream of each kind; an error names what is missing."""
    by_kind: dict[str, Stream] = {}
    for key in sorted(builders):
        b = builders[key]
        if b.kind in KINDS and b.kind not in by_kind:
            by_kind[b.kind] = b.build()
    for kind in ("grating", "tracker"):
        if kind not in by_kind or len(by_kind[kind]) == 0:
            raise StreamError(
                f"{source}: no {kind} samples (need a stream with "
                + ("grating<k>_counts" if kind == "grating" else "x_mm, y_mm, z_mm")
                + " columns)"
            )
    return CellStreams(
        by_kind["grating"], by_kind["tracker"], by_kind.get("encoders"), source, complete, note
    )


#: The option that lets the twin use the readable part of a damaged recording.
ALLOW_PARTIAL = "--allow-partial"


def recording_damage(rec: Recording) -> str:
    """What a streaming pass over a damaged recording ``rec`` read and what it did not, in
    words ("" when nothing but the footer is missing: a recording that was not closed,
    every record in it read)."""
    lost = [d for d in rec.damaged if d.record != "footer"]
    if not lost:
        return ""
    skipped = sum(max(d.end - d.offset, 0) for d in lost)
    regions = "; ".join(str(d) for d in lost[:3]) + ("; ..." if len(lost) > 3 else "")
    return (
        f"damaged recording: read {rec.messages} messages in {rec.chunks} whole chunks; "
        f"{len(lost)} damaged region(s), {skipped} of {rec.size} bytes unreadable ({regions})"
    )


def read_recording_streams(path: str | Path, *, allow_partial: bool = False) -> CellStreams:
    """Stream an MCAP recording (``daq run --record``) into whole column arrays.

    A recording with a damaged region (not only a missing footer) is refused with a
    :class:`StreamError` saying what was readable and what not, unless ``allow_partial``:
    then its readable part is used and ``note`` says so (phases.json, report.json)."""
    from daq.columnar import StreamSchema, decode
    from daq.errors import DaqError
    from daq.recording_reader import HOLES_TOPIC, read_recording

    side = _SideRecords(HOLES_TOPIC)
    try:
        rec = read_recording(path)
    except DaqError as exc:
        raise StreamError(str(exc)) from exc
    builders: dict[str, StreamBuilder] = {}
    schemas: dict[str, StreamSchema] = {}
    m = None
    try:
        for m in rec.messages_iter():
            if side.take(m):
                continue
            if m.channel.message_encoding != "daq.columnar.v1" or m.schema is None:
                continue
            b = builders.get(m.topic)
            if b is None:
                doc = json.loads(m.schema.data)
                if stream_kind(c["name"] for c in doc["columns"]) not in KINDS:
                    continue
                b = builders[m.topic] = StreamBuilder(m.topic, doc)
                schemas[m.topic] = StreamSchema.loads(m.schema.data)
            _header, cols = decode(schemas[m.topic], m.data)
            b.add(m.sequence, cols)
    except DaqError as exc:
        raise StreamError(f"{path}: {exc}") from None
    except (ValueError, KeyError, TypeError, IndexError) as exc:  # a schema or batch that
        # passed the CRC but is not what daq writes (hand-made or foreign files)
        where = f"channel {m.topic!r}, message {m.sequence}" if m is not None else "schema"
        raise StreamError(f"{path}: {where}: not a daq.columnar.v1 batch: {exc}") from None
    if rec.messages == 0 and rec.truncated:
        raise StreamError(f"{path}: not a readable MCAP recording ({rec.error or 'no records'})")
    damage = recording_damage(rec)
    if damage and not allow_partial:
        raise StreamError(
            f"{path}: {damage}: refused; pass {ALLOW_PARTIAL} to use the readable part "
            "(`daq recover` writes it to a whole file)"
        )
    if damage:
        note = f"{damage}; the readable part used ({ALLOW_PARTIAL})"
    elif rec.truncated:
        note = f"not closed ({rec.error}); every record read"
    else:
        note = ""
    if side.holes:
        note = "; ".join(x for x in (note, holes_note(side.holes)) if x)
    streams = pick_streams(builders, str(path), complete=rec.complete, note=note)
    check_host_clocks(streams, side.clocks)
    return streams


class _SideRecords:
    """What a recording says beside the samples: a subscriber's hole records (on
    ``holes_topic``) and each device's latest ``host_clock`` (by health key)."""

    def __init__(self, holes_topic: str) -> None:
        self.holes_topic = holes_topic
        self.holes: list[dict[str, Any]] = []
        self.clocks: dict[str, dict[str, float]] = {}

    def take(self, m: RecordedMessage) -> bool:
        """Keep what recorded message ``m`` says; True: it is one of these (not samples)."""
        if m.topic == self.holes_topic:
            self.holes.append(json.loads(m.data))
            return True
        if m.topic.endswith("/health") and m.channel.message_encoding == "json":
            clock = host_clock_of(m.data)
            if clock is not None:
                self.clocks[m.topic] = clock
            return True
        return False


#: host clocks (``host_clock`` of the devices' health) further apart than this, beyond
#: their measurement uncertainty, and the twin refuses to pair the streams by time (ms)
HOST_CLOCK_TOLERANCE_MS = 10.0


def host_clock_of(data: bytes) -> dict[str, float] | None:
    """``host_clock`` of a health document (its ``offset_ms`` and ``uncertainty_ms``;
    None: not there, or not numbers)."""
    try:
        doc = json.loads(data)
    except ValueError:
        return None
    clock = doc.get("host_clock") if isinstance(doc, dict) else None
    if not isinstance(clock, dict):
        return None
    got = {k: clock.get(k) for k in ("offset_ms", "uncertainty_ms")}
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in got.values()):
        return None
    return {k: float(v) for k, v in got.items() if v is not None}


def host_clocks_apart(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether two hosts' clocks, each ``(offset_ms, uncertainty_ms)`` against the same
    reference (``host_clock`` of their health), are further apart than
    :data:`HOST_CLOCK_TOLERANCE_MS` beyond both uncertainties: samples they stamped must
    not be paired by time (the replay refuses them, the live twin learns no tracking
    update from them)."""
    return abs(a[0] - b[0]) - a[1] - b[1] > HOST_CLOCK_TOLERANCE_MS


def check_host_clocks(streams: CellStreams, clocks: dict[str, dict[str, float]]) -> None:
    """Refuse (:class:`StreamError`, saying why) streams stamped by host clocks that
    disagree: each device's latest ``host_clock`` in ``clocks`` (by health key; devices
    of a daemon that measured none are not compared). Pairing the tracker's samples with
    the gratings' by time would be off by the clocks' difference."""
    said = []
    for s in (streams.grating, streams.tracker, streams.encoders):
        if s is not None:
            clock = clocks.get(s.key.rsplit("/", 1)[0] + "/health")
            if clock is not None:
                said.append((s, clock["offset_ms"], clock["uncertainty_ms"]))
    for i, (a, off_a, unc_a) in enumerate(said):
        for b, off_b, unc_b in said[i + 1 :]:
            if host_clocks_apart((off_a, unc_a), (off_b, unc_b)):
                raise StreamError(
                    f"{streams.source}: the {a.kind} ({a.device}) and the {b.kind} "
                    f"({b.device}) were stamped by host clocks {abs(off_a - off_b):.1f} ms "
                    f"apart (host_clock in their health: {off_a:+.1f} ± {unc_a:.1f} and "
                    f"{off_b:+.1f} ± {unc_b:.1f} ms against the router's; tolerance "
                    f"{HOST_CLOCK_TOLERANCE_MS:.0f} ms): pairing them by time would be off "
                    "by as much; set the hosts' clocks (NTP/PTP) and record again"
                )


def holes_note(holes: list[dict[str, Any]]) -> str:
    """One phrase for the hole records of a subscriber's recording (daq.recording_holes):
    messages lacking per key, and why."""
    per_key: dict[str, tuple[int, set[str]]] = {}
    for h in holes:
        n, why = per_key.get(str(h.get("key")), (0, set()))
        per_key[str(h.get("key"))] = (n + int(h.get("count", 0)), why | {str(h.get("reason"))})
    said = ", ".join(
        f"{k}: {n} messages ({'/'.join(sorted(why))})" for k, (n, why) in sorted(per_key.items())
    )
    return f"the recorder marked {len(holes)} hole(s) ({said})"


def lost_intervals(
    stream: Stream, gap_factor: float = 5.0, min_gap_s: float = 0.05
) -> list[dict[str, Any]]:
    """Spans of mapped time with no samples of ``stream``.

    A span is reported where consecutive samples (arrival order) are more than
    ``gap_factor`` median sample periods and ``min_gap_s`` apart (bus devices such as the
    CAN encoders deliver irregularly), or where ``seq`` jumps within an epoch, or
    at a device restart (``epoch`` change). Each entry: device, kind, ``t_start_ns``,
    ``t_end_ns`` (last sample before and first after), ``duration_s``, ``samples_missing``
    (from ``seq`` when it can tell, else from the median period), reason.
    """
    t = stream.t_ns
    if t.shape[0] < 3:
        return []
    dt = np.diff(t)
    period = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 0.0
    if period <= 0:
        return []
    seq = stream.seq.astype(np.int64)
    dseq = np.diff(seq)
    same_epoch = stream.epoch[1:] == stream.epoch[:-1]
    seq_jump = same_epoch & (dseq > 1)
    restart = ~same_epoch
    time_gap = dt > max(gap_factor * period, min_gap_s * 1e9)
    out = []
    for i in np.flatnonzero(seq_jump | restart | time_gap).tolist():
        if restart[i]:
            reason, missing = "device restart", round(dt[i] / period) - 1
        elif seq_jump[i]:
            reason, missing = "sequence gap", int(dseq[i] - 1)
        else:
            reason, missing = "time gap", round(dt[i] / period) - 1
        out.append(
            {
                "device": stream.device,
                "kind": stream.kind,
                "t_start_ns": int(t[i]),
                "t_end_ns": int(t[i + 1]),
                "duration_s": round(float(dt[i]) * 1e-9, 6),
                "samples_missing": max(missing, 0),
                "reason": reason,
            }
        )
    return out
