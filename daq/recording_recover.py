"""``recover``: the readable messages of a damaged MCAP recording as a whole file.

:func:`recover` writes every message that :mod:`daq.recording_reader` can read (all whole
chunks, those after a damaged one included) as a whole file with a summary, beside the
original (``F.recovered.mcap``, ``-o``) or, with ``--in-place``, in its place keeping
``F.mcap.bak``; a complete file is left alone.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from daq.errors import RecordingError
from daq.recording_reader import Recording, read_recording
from daq.recording_writer import LIBRARY, PROFILE
from edges.outputs import OutputSet


def recovered_path(src: str | Path) -> Path:
    """Where ``daq recover F.mcap`` writes by default: ``F.recovered.mcap`` beside it."""
    p = Path(src)
    stem = p.name[: -len(".mcap")] if p.name.endswith(".mcap") else p.name
    return p.with_name(stem + ".recovered.mcap")


def backup_path(src: str | Path) -> Path:
    """The copy of the original that ``recover --in-place`` keeps: ``F.mcap.bak``."""
    p = Path(src)
    return p.with_name(p.name + ".bak")


@dataclass
class Recovery:
    """What :func:`recover` did: ``recording`` is what the pass read; ``output`` the file
    written (None: nothing written, the input was complete); ``backup`` the original's
    copy of an in-place recovery."""

    recording: Recording
    output: Path | None
    backup: Path | None = None

    def as_dict(self, src: str | Path) -> dict[str, Any]:
        rec = self.recording
        return {
            "input": str(src),
            "complete": rec.complete,
            "output": None if self.output is None else str(self.output),
            "backup": None if self.backup is None else str(self.backup),
            "messages": rec.messages,
            "channels": len(rec.channels),
            "chunks": rec.chunks,
            "chunks_damaged": rec.chunks_damaged,
            "orphans": rec.orphans,
            "damaged": [d.as_dict() for d in rec.damaged],
            "input_state": "complete" if rec.complete else "damaged: " + rec.error,
        }


def _copy_messages(rec: Recording, out: Path) -> None:
    """Write every readable message of ``rec`` (one streaming pass) to ``out`` as a whole
    MCAP file: chunks, indexes, summary."""
    with open(out, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile=PROFILE, library=LIBRARY)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        meta_done: set[str] = set()
        for m in rec.messages_iter():
            for name, data in rec.metadata.items():
                if name not in meta_done:
                    w.add_metadata(name, data)
                    meta_done.add(name)
            ch = m.channel
            if ch.id not in channel_ids:
                sid = 0
                if m.schema is not None:
                    if m.schema.id not in schema_ids:
                        schema_ids[m.schema.id] = w.register_schema(
                            m.schema.name, m.schema.encoding, m.schema.data
                        )
                    sid = schema_ids[m.schema.id]
                channel_ids[ch.id] = w.register_channel(
                    ch.topic, ch.message_encoding, sid, dict(ch.metadata)
                )
            w.add_message(
                channel_ids[ch.id],
                log_time=m.log_time,
                data=m.data,
                publish_time=m.publish_time,
                sequence=m.sequence,
            )
        for name, data in rec.metadata.items():
            if name not in meta_done:
                w.add_metadata(name, data)
        w.finish()
        fh.flush()
        os.fsync(fh.fileno())


def recover(
    src: str | Path,
    dst: str | Path | None = None,
    *,
    in_place: bool = False,
    option: str = "-o/--output",
) -> Recovery:
    """Write every readable message of ``src`` (all whole chunks, those after a damaged
    one included) to a whole MCAP file with a summary; ``src`` is never changed.

    ``dst``: the output (default :func:`recovered_path`); ``in_place``: replace ``src``
    instead, after keeping the original as :func:`backup_path` (a hard link, else a
    copy). A complete ``src`` is left alone and nothing is written (``output`` None).
    The output is staged and moved into place only when whole (:class:`OutputSet`); an
    output that is ``src`` without ``in_place``, or a file without one readable message,
    is refused with :class:`RecordingError`."""
    src = Path(src)
    rec = read_recording(src)
    if in_place and dst is not None:
        raise RecordingError(f"{option} and --in-place: give one of them")
    target = src if in_place else Path(dst) if dst is not None else recovered_path(src)
    outputs = OutputSet(inputs=[] if in_place else [src], error=RecordingError)
    with outputs:
        staged = outputs.file(target, "--in-place" if in_place else option)
        _copy_messages(rec, staged)
        if rec.complete:
            outputs.discard()
            return Recovery(rec, None)
        if rec.messages == 0:
            raise RecordingError(
                f"{src}: no readable message ({rec.error}); nothing written"
                + (f" ({rec.orphans} messages lost their channel record)" if rec.orphans else "")
            )
        backup = None
        if in_place:
            backup = backup_path(src)
            if backup.exists() or backup.is_symlink():
                raise RecordingError(
                    f"--in-place: the backup {backup} exists already; move it away or "
                    "recover to another file with -o"
                )
            try:
                os.link(src, backup)
            except OSError:
                shutil.copy2(src, backup)
    return Recovery(rec, target, backup)
