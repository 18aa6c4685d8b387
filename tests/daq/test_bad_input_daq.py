"""Bad input to the ``daq`` commands (run, record, replay, recover, info, echo, schema) and
``python -m daq.demo``, as a user meets them: real processes, plus hypothesis fuzzing of
the MCAP streaming reader, ``recover`` and the configuration loader in process.

Every refused case runs in a fresh working directory holding valid inputs (a cell config,
a whole recording, a recording with a damaged chunk in the middle) and asserts: exit
status 2, the key words of the message (the file, or the option/table/key), exactly one
line on stderr, no "Traceback", and every file of the directory byte for byte as before,
nothing created (no output, no staging leftover). No refusal opens a network connection
except the replay cases marked (session), which listen on a free loopback port.

| category (command) | cases |
|---|---|
| not a recording: random bytes, a CSV, empty, magic only, a directory, missing, | 8 |
|   /dev/zero, an empty path (recover) | |
| nothing readable: magic + garbage, a file killed before its first chunk (recover) | 2 |
| outputs: -o onto the input (also through another spelling and a symlink), -o a | 7 |
|   directory, -o under a file, -o where nothing can be written, --in-place with a | |
|   backup already there (recover) | |
| options: -o with --in-place (recover) | 1 |
| not a recording: random bytes, CSV, empty, /dev/zero, directory, a named pipe (info) | 6 |
| not a recording: random bytes, empty, magic only (replay); nothing readable (session) | 4 |
| replay options: --speed 0/-1/nan/inf/text, --start -5/nan, --duration 0/nan, | 11 |
|   --wait-subscribers -1, --topic 'a//b' | |
| replay finds nothing to send: --topic matching no key, --start past the end (session) | 2 |
| config TOML bytes: binary, NUL, UTF-16, latin-1, bad syntax, duplicate key, deep nesting | 7 |
| config: unknown table/key, a table given as a value (+ env, the old function-object | 4 |
|   message), unknown env key | |
| config wrong types: string rate, int listen, list mode, string bool, device not a table | 5 |
| config NaN/inf/negative/zero: durations, rates, sizes; chunk size too large; path | 9 |
|   template with an unknown placeholder; a listen entry that is not an endpoint | |
| config file: missing, directory, /dev/zero, empty --config, over the size limit | 5 |
| run options: --duration -1/nan, --rate 0/nan, --record onto --config, --record '{x}' | 6 |
| record: -o into a missing directory, onto --config, a directory, /proc, --duration | 7 |
|   0/nan, bad key expression | |
| echo: --jsonl into a missing directory, onto --config, /proc, a directory; --count | 12 |
|   0/-1/x, --idle -1, bad key expression; --cell a/b and '*', a key outside --cell | |
| schema: --timeout 0/inf, bad key expression | 3 |
| zenoh endpoints: --listen garbage (replay), --connect without a protocol (echo) | 2 |
| demo: --speed 0, --port 0/70000, --rate nan, --seed -1, --robot unknown, --out a file | 7 |
| (round 2) replay: a damaged chunk, a key whose schema is cut, without --allow-partial | 2 |
| (round 2) run: rate_hz 1e9/100001/0 in cell.toml and as --rate; --rate, --sim-config, | 13 |
|   --no-record beside --config and $DAQ_CONFIG; --record with --no-record | |

Accepted on purpose, each checked for its result: a complete recording (recover: exit 0,
says complete, writes nothing), a recording with one corrupt chunk in the middle and a
truncated one (recover keeps every intact chunk, after the damage too, beside the
original; --in-place keeps a backup; info reports offset, record and reason with exit 1;
replay with --allow-partial sends every readable message of the keys it can decode and
warns), ``daq info F`` into a closed pipe (quiet,
exit 141), a config with a byte-order mark or CRLF line ends (same as the plain file).

The timed cases (a device absent at start, echo/record to nobody) are in
tests/test_bad_input_daq_live.py (``realtime``).

Total: 125 refused inputs as processes, 14 accepted ones checked for their result, and
the fuzz tests (reader, recover, config loader: random bytes, every truncation of a small
recording, byte mutations, records without a CRC; 150 examples each, ``FUZZ_EXAMPLES``
sets more). ``pytest -s`` prints the tally: tried, clear errors, tracebacks, hangs, silent
wrong results, runs that changed files.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from daq import config as cfg
from daq.columnar import Column, StreamSchema, encode
from daq.errors import ConfigError, DaqError, RecordingError
from daq.recording_reader import MAGIC, read_recording, scan
from daq.recording_recover import recover
from daq.recording_writer import McapRecorder
from tests import bad_input
from tests.bad_input import snapshot

pytestmark = pytest.mark.timeout(180)

BIN = Path(sys.executable).parent
DAQ = str(BIN / "daq")
PY = sys.executable
TIMEOUT_S = 60
FUZZ = settings(
    max_examples=int(os.environ.get("FUZZ_EXAMPLES", "150")),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
CAMPAIGN = Path(__file__).parents[1] / "data" / "campaign_small.mcap"

#: outcomes of the process cases, by kind (printed at the end of the module, ``-s``)
TALLY: Counter[str] = Counter()

SCHEMA = StreamSchema(
    "cell/c/robot/r/dev/ch",
    (Column("seq", "uint64"), Column("x_mm", "float64", unit="mm")),
    meta={"device": "dev"},
)
GOOD_TOML = """[cell]
name = "c1"

[zenoh]
listen = ["tcp/127.0.0.1:17999"]

[publish]
health_period_s = 1.0

[recording]
chunk_size_bytes = 4096

[[device]]
name = "grating"
driver = "grating_modbus"
url = "socket://127.0.0.1:5020"
rate_hz = 1000
"""


@pytest.fixture(scope="module", autouse=True)
def tally():
    yield
    print(
        "\nbad input (daq): tried {tried}, clear errors {clear}, tracebacks {traceback}, "
        "hangs {hang}, silent wrong results {silent}, runs that changed files {changed}; "
        "accepted inputs checked {accepted}".format(
            **{
                k: TALLY[k]
                for k in ("tried", "clear", "traceback", "hang", "silent", "changed", "accepted")
            }
        )
    )


# -- recordings ---------------------------------------------------------------------------


def write_recording(path: Path, n: int = 60, *, chunk: int = 2048, close: bool = True) -> Path:
    """``n`` messages of 10 samples on one channel, in chunks of about ``chunk`` bytes."""
    rec = McapRecorder(path, metadata={"daq": {"cell": "c"}}, chunk_size_bytes=chunk)
    cid = rec.add_columnar(SCHEMA, {"device": "dev"})
    for i in range(n):
        cols = {"seq": np.arange(i * 10, i * 10 + 10), "x_mm": np.ones(10) * i}
        rec.write(cid, encode(SCHEMA, cols, i), 1_000_000_000 + i * 10_000_000, sequence=i)
    if close:
        rec.close()
    else:
        rec.flush()
    return path


def top_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level records of a whole file."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, length))
        pos += 9 + length
        if op == 0x02:
            break
    return out


def chunk_messages(data: bytes) -> list[tuple[int, list[Message]]]:
    """(offset, messages) of every chunk, read with the mcap library (an independent
    reader to check this project's against)."""
    out = []
    for pos, op, length in top_records(data):
        if op == 0x06:
            chunk = Chunk.read(ReadDataStream(io.BytesIO(data[pos + 9 : pos + 9 + length])))
            msgs = [r for r in breakup_chunk(chunk, validate_crc=True) if isinstance(r, Message)]
            out.append((pos, msgs))
    return out


def damage_chunk(data: bytes, k: int) -> tuple[bytes, int, int]:
    """``data`` with a byte of its ``k``-th chunk's compressed records flipped: the new
    bytes, the chunk's offset and its message count."""
    pos, msgs = chunk_messages(data)[k]
    b = bytearray(data)
    b[pos + 9 + 60] ^= 0xFF  # past the 9 + 41 bytes of header fields, inside the zstd data
    return bytes(b), pos, len(msgs)


def message_set(path: Path) -> set[tuple[str, int, int, bytes]]:
    """Every message this project's reader yields, as (topic, sequence, log_time, data)."""
    rec = read_recording(path)
    return {(m.topic, m.sequence, m.log_time, m.data) for m in rec.messages_iter()}


def library_count(path: Path) -> int:
    """Messages of a whole file by a seeking reader using the summary (common tooling)."""
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        n = reader.get_summary().statistics.message_count
        assert sum(1 for _ in reader.iter_messages()) == n
    return n


# -- processes ----------------------------------------------------------------------------


@pytest.fixture
def work(tmp_path: Path) -> Path:
    """A working directory with valid inputs: a config, a whole and a damaged recording."""
    (tmp_path / "cell.toml").write_text(GOOD_TOML, encoding="utf-8")
    whole = write_recording(tmp_path / "whole.mcap")
    data = whole.read_bytes()
    (tmp_path / "damaged.mcap").write_bytes(damage_chunk(data, 2)[0])
    (tmp_path / "data.csv").write_text("seq,x_mm\n1,2.5\n", encoding="utf-8")
    return tmp_path


def run(argv: list[str], cwd: Path, env: dict[str, str] | None = None):
    return bad_input.run(argv, cwd, env, timeout=TIMEOUT_S)


def refused(work: Path, argv: list[str], words: list[str], env: dict[str, str] | None = None):
    """Run ``argv`` in ``work`` and assert the clean refusal (tests/bad_input.py)."""
    return bad_input.refused(work, argv, words, env=env, timeout=TIMEOUT_S, tally=TALLY)


def accepted(proc: subprocess.CompletedProcess, status: int = 0) -> None:
    TALLY["accepted"] += 1
    assert proc.returncode == status, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def daq(*args: str) -> list[str]:
    return [DAQ, *args]


def nowhere() -> list[str]:
    """zenoh settings of a sink that would reach nothing (no refusal gets that far)."""
    return ["--connect", f"tcp/127.0.0.1:{free_port()}"]


# -- daq recover ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda w: (w / "x.mcap").write_bytes(os.urandom(3000)), ["x.mcap", "not an MCAP file"]),
        (lambda w: (w / "x.mcap").write_bytes((w / "data.csv").read_bytes()), ["x.mcap", "text"]),
        (lambda w: (w / "x.mcap").write_bytes(b""), ["x.mcap", "empty"]),
        (lambda w: (w / "x.mcap").write_bytes(MAGIC[:5]), ["x.mcap", "magic"]),
        (lambda w: (w / "x.mcap").mkdir(), ["x.mcap", "directory"]),
        (lambda w: None, ["x.mcap", "no such file"]),
    ],
    ids=["random-bytes", "a-csv", "empty", "magic-only", "directory", "missing"],
)
def test_recover_refuses_what_is_not_a_recording(work, make, words):
    make(work)
    refused(work, daq("recover", "x.mcap"), words)


def test_recover_refuses_a_device_and_an_empty_path(work):
    refused(work, daq("recover", "/dev/zero"), ["/dev/zero", "not a regular file"])
    refused(work, daq("recover", ""), ["empty path"])


def test_recover_refuses_a_file_with_nothing_readable(work):
    (work / "garbage.mcap").write_bytes(MAGIC + os.urandom(4000))
    refused(work, daq("recover", "garbage.mcap"), ["garbage.mcap", "no readable message"])
    # killed after its header and metadata, before its first chunk was closed
    data = (work / "whole.mcap").read_bytes()
    first_chunk = chunk_messages(data)[0][0]
    (work / "early.mcap").write_bytes(data[: first_chunk + 100])
    refused(work, daq("recover", "early.mcap"), ["early.mcap", "no readable message"])


def test_recover_refuses_bad_outputs(work):
    refused(work, daq("recover", "damaged.mcap", "-o", "damaged.mcap"), ["is an input"])
    refused(work, daq("recover", "damaged.mcap", "-o", "./x/../damaged.mcap"), ["is an input"])
    (work / "link.mcap").symlink_to("damaged.mcap")
    refused(work, daq("recover", "damaged.mcap", "-o", "link.mcap"), ["is an input"])
    (work / "out").mkdir()
    refused(work, daq("recover", "damaged.mcap", "-o", "out"), ["-o/--output", "directory"])
    refused(work, daq("recover", "damaged.mcap", "-o", "data.csv/x.mcap"), ["data.csv"])
    refused(work, daq("recover", "damaged.mcap", "-o", "/proc/x.mcap"), ["/proc"])
    (work / "damaged.mcap.bak").write_bytes(b"an earlier backup")
    refused(work, daq("recover", "damaged.mcap", "--in-place"), ["damaged.mcap.bak", "exists"])


def test_recover_options_exclusive(work):
    refused(
        work, daq("recover", "damaged.mcap", "-o", "a.mcap", "--in-place"), ["--in-place", "-o"]
    )


def test_recover_leaves_a_complete_file_alone(work):
    before = snapshot(work)
    proc = run(daq("recover", "whole.mcap"), work)
    accepted(proc)
    doc = json.loads(proc.stdout)
    assert doc["complete"] is True and doc["output"] is None and doc["messages"] == 60
    assert snapshot(work) == before  # nothing written, nothing changed


def test_recover_keeps_every_intact_chunk_beside_the_original(work):
    """The issue: a corrupt chunk in the middle used to cost every message after it."""
    whole = (work / "whole.mcap").read_bytes()
    _, offset, lost = damage_chunk(whole, 2)
    before = (work / "damaged.mcap").read_bytes()
    proc = run(daq("recover", "damaged.mcap"), work)
    accepted(proc)
    doc = json.loads(proc.stdout)
    out = work / "damaged.recovered.mcap"
    assert doc["output"] == "damaged.recovered.mcap" and doc["complete"] is False
    assert doc["messages"] == 60 - lost and doc["chunks_damaged"] == 1
    assert doc["damaged"][0]["offset"] == offset and doc["damaged"][0]["record"] == "chunk"
    assert (work / "damaged.mcap").read_bytes() == before  # never touched
    assert library_count(out) == 60 - lost
    assert message_set(out) < message_set(work / "whole.mcap")
    # the last chunk's messages are there: resynchronised past the damage
    last = {m.sequence for m in chunk_messages(whole)[-1][1]}
    assert last <= {s for _, s, _, _ in message_set(out)}
    assert not [p for p in work.iterdir() if ".partial-" in p.name]


def test_recover_in_place_keeps_a_backup(work):
    before = (work / "damaged.mcap").read_bytes()
    proc = run(daq("recover", "damaged.mcap", "--in-place"), work)
    accepted(proc)
    doc = json.loads(proc.stdout)
    assert doc["backup"] == "damaged.mcap.bak" and doc["output"] == "damaged.mcap"
    assert (work / "damaged.mcap.bak").read_bytes() == before
    assert read_recording(work / "damaged.mcap") is not None
    rec, _ = scan(work / "damaged.mcap")
    assert rec.complete
    # complete now: a second run changes nothing
    snap = snapshot(work)
    accepted(run(daq("recover", "damaged.mcap", "--in-place"), work))
    assert snapshot(work) == snap


def test_recover_a_truncated_file_and_the_campaign(work):
    whole = (work / "whole.mcap").read_bytes()
    (work / "cut.mcap").write_bytes(whole[: len(whole) // 2])
    proc = run(daq("recover", "cut.mcap", "-o", "sub/fixed.mcap"), work)
    accepted(proc)
    doc = json.loads(proc.stdout)
    assert doc["damaged"][0]["reason"].startswith("truncated")
    assert library_count(work / "sub" / "fixed.mcap") == doc["messages"] > 0
    # the campaign recording with one chunk damaged in the middle: all others kept
    data = CAMPAIGN.read_bytes()
    chunks = chunk_messages(data)
    total = sum(len(m) for _, m in chunks)
    k = len(chunks) // 2
    bad, offset, lost = damage_chunk(data, k)
    (work / "campaign.mcap").write_bytes(bad)
    proc = run(daq("recover", "campaign.mcap"), work)
    accepted(proc)
    doc = json.loads(proc.stdout)
    assert doc["messages"] == total - lost
    assert [d["offset"] for d in doc["damaged"]] == [offset]
    assert library_count(work / "campaign.recovered.mcap") == total - lost


# -- daq info ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "target, words",
    [
        ("data.csv", ["data.csv", "not an MCAP file"]),
        ("/dev/zero", ["/dev/zero", "not a regular file"]),
        (".", ["directory"]),
        ("empty.mcap", ["empty.mcap", "empty"]),
        ("rand.mcap", ["rand.mcap", "not an MCAP file"]),
    ],
)
def test_info_refuses_what_is_not_a_recording(work, target, words):
    (work / "empty.mcap").write_bytes(b"")
    (work / "rand.mcap").write_bytes(os.urandom(500))
    refused(work, daq("info", target), words)


def test_info_refuses_a_named_pipe_without_waiting(work):
    os.mkfifo(work / "fifo.mcap")  # opening it would wait for a writer for ever
    refused(work, daq("info", "fifo.mcap"), ["fifo.mcap", "named pipe"])


def test_info_says_where_and_why(work):
    whole = (work / "whole.mcap").read_bytes()
    _, offset, lost = damage_chunk(whole, 2)
    proc = run(daq("info", "damaged.mcap"), work)
    accepted(proc, 1)
    doc = json.loads(proc.stdout)
    assert doc["complete"] is False and doc["messages"] == 60 - lost
    (d,) = doc["damaged"]
    assert d["offset"] == offset and d["record"] == "chunk" and d["end"] > offset
    assert "zstd" in d["reason"] or "CRC" in d["reason"]
    assert f"byte {offset}" in doc["error"]
    # a flipped length field: named as a bad length, not as the end of the file
    b = bytearray(whole)
    b[offset + 1] ^= 0x40
    (work / "len.mcap").write_bytes(b)
    doc = json.loads(run(daq("info", "len.mcap"), work).stdout)
    assert doc["damaged"][0]["reason"].startswith("bad length")
    assert doc["messages"] == 60 - lost
    # truncated: where it ends, and everything before
    (work / "cut.mcap").write_bytes(whole[:3000])
    doc = json.loads(run(daq("info", "cut.mcap"), work).stdout)
    assert doc["damaged"][-1]["reason"].startswith("truncated") and doc["messages"] > 0
    # whole
    proc = run(daq("info", "whole.mcap"), work)
    accepted(proc)
    assert json.loads(proc.stdout)["complete"] is True


def test_info_into_a_closed_pipe_is_quiet(work):
    r, w = os.pipe()
    os.close(r)  # the reader is gone before anything is written (`daq info F | true`)
    try:
        proc = subprocess.run(
            daq("info", str(CAMPAIGN)), stdout=w, stderr=subprocess.PIPE, text=True, timeout=60
        )
    finally:
        os.close(w)
    accepted(proc, 141)
    assert proc.stderr == ""
    # and through a shell pipeline whose reader stops after one line
    proc = subprocess.run(
        [
            "bash",
            "-c",
            f"'{DAQ}' info '{CAMPAIGN}' | head -c 10 >/dev/null; exit ${{PIPESTATUS[0]}}",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode in (0, 141) and "Traceback" not in proc.stderr and not proc.stderr


# -- daq replay ----------------------------------------------------------------------------


def test_replay_refuses_what_is_not_a_recording(work):
    listen = ["--listen", f"tcp/127.0.0.1:{free_port()}"]
    (work / "empty.mcap").write_bytes(b"")
    (work / "magic.mcap").write_bytes(MAGIC[:3])
    refused(work, daq("replay", "data.csv", *listen), ["data.csv", "not an MCAP file"])
    refused(work, daq("replay", "empty.mcap", *listen), ["empty.mcap", "empty"])
    refused(work, daq("replay", "magic.mcap", *listen), ["magic.mcap", "magic"])
    # (session) a recording cut before its first chunk: nothing to replay
    data = (work / "whole.mcap").read_bytes()
    (work / "early.mcap").write_bytes(data[: chunk_messages(data)[0][0] + 50])
    refused(
        work, daq("replay", "early.mcap", "--fast", *listen), ["early.mcap", "no readable message"]
    )


@pytest.mark.parametrize(
    "option, value",
    [
        ("--speed", "0"),
        ("--speed", "-1"),
        ("--speed", "nan"),
        ("--speed", "inf"),
        ("--speed", "fast"),
        ("--start", "-5"),
        ("--start", "nan"),
        ("--duration", "0"),
        ("--duration", "nan"),
        ("--wait-subscribers", "-1"),
        ("--topic", "a//b"),
    ],
)
def test_replay_refuses_bad_options(work, option, value):
    refused(work, daq("replay", "whole.mcap", f"{option}={value}"), [option])


def test_replay_refuses_a_pass_that_sends_nothing(work):
    """(session) with --loop these used to spin for ever."""
    listen = ["--listen", f"tcp/127.0.0.1:{free_port()}"]
    refused(
        work,
        daq("replay", "whole.mcap", "--fast", "--loop", "--topic", "other/**", *listen),
        ["--topic", "matches none", "cell/c/robot/r/dev/ch"],
    )
    refused(
        work,
        daq("replay", "whole.mcap", "--fast", "--loop", "--start", "1000", *listen),
        ["--start", "past the end"],
    )


def test_replay_reads_past_a_damaged_chunk_only_when_allowed(work):
    """(session) a damaged recording is refused before anything is published, saying what
    was readable; --allow-partial replays the rest, said on stderr and in the result."""
    whole = (work / "whole.mcap").read_bytes()
    _, offset, lost = damage_chunk(whole, 2)
    listen = ["--listen", f"tcp/127.0.0.1:{free_port()}"]
    proc = refused(
        work,
        daq("replay", "damaged.mcap", "--fast", *listen),
        ["damaged.mcap", f"read {60 - lost} messages", f"byte {offset}", "--allow-partial"],
    )
    assert proc.stdout == ""  # nothing announced, nothing published
    proc = run(daq("replay", "damaged.mcap", "--fast", "--allow-partial", *listen), work)
    accepted(proc)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["truncated"] is True and result["damaged"][0]["offset"] == offset
    assert result["allow_partial"] is True
    assert result["topics"]["cell/c/robot/r/dev/ch"]["messages"] == 60 - lost
    assert "warning" in proc.stderr and f"byte {offset}" in proc.stderr


def _cut_schema_recording(path: Path, *, cut: bool) -> None:
    """A recording (no chunks: no CRC guards its records) of two keys; with ``cut`` the
    first key's schema is cut in half (its messages are intact)."""
    from mcap.writer import CompressionType, Writer

    other = StreamSchema("cell/c/robot/r/dev/other", SCHEMA.columns, meta={"device": "dev"})
    with open(path, "wb") as fh:
        w = Writer(fh, use_chunking=False, compression=CompressionType.NONE)
        w.start()
        channels = []
        for schema in (SCHEMA, other):
            text = schema.dumps()
            data = text[: len(text) // 2] if cut and schema is SCHEMA else text
            sid = w.register_schema(schema.key, "jsonschema", data)
            channels.append(w.register_channel(schema.key, "daq.columnar.v1", sid, {}))
        for i in range(10):
            for ch, schema in zip(channels, (SCHEMA, other), strict=True):
                payload = encode(schema, {"seq": np.arange(3) + 3 * i, "x_mm": np.ones(3)}, i)
                w.add_message(ch, log_time=i * 1000, data=payload, publish_time=i, sequence=i)
        w.finish()


def test_replay_never_republishes_a_key_whose_schema_is_cut(work):
    """(session) every subscriber fails to decode such a key (twin export refuses the
    file): refused, and with --allow-partial the other keys only."""
    _cut_schema_recording(work / "cut.mcap", cut=True)
    listen = ["--listen", f"tcp/127.0.0.1:{free_port()}"]
    refused(
        work,
        daq("replay", "cut.mcap", "--fast", *listen),
        ["cut.mcap", "key cell/c/robot/r/dev/ch", "schema does not parse", "--allow-partial"],
    )
    proc = run(daq("replay", "cut.mcap", "--fast", "--allow-partial", *listen), work)
    accepted(proc)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert list(result["topics"]) == ["cell/c/robot/r/dev/other"], result
    assert "cell/c/robot/r/dev/ch" in result["not_republished"]
    assert "schema does not parse" in proc.stderr
    _cut_schema_recording(work / "whole2.mcap", cut=False)  # the same file, whole: replayed
    proc = run(daq("replay", "whole2.mcap", "--fast", *listen), work)
    accepted(proc)
    assert len(json.loads(proc.stdout.strip().splitlines()[-1])["topics"]) == 2


# -- configuration ------------------------------------------------------------------------


CONFIG_CASES = [
    # bytes
    ("binary", os.urandom(64) + b"\x00\xff", ["cell.toml"]),
    ("nul", b'[cell]\nname = "a\x00b"\n', ["cell.toml", "line 2"]),
    ("utf16", GOOD_TOML.encode("utf-16"), ["cell.toml", "UTF-16"]),
    ("latin1", '[cell]\nname = "Zürich"\n'.encode("latin-1"), ["cell.toml", "line 2", "UTF-8"]),
    ("syntax", b"[cell\nname = 1\n", ["cell.toml", "line 1"]),
    ("duplicate", b'[cell]\nname = "a"\nname = "b"\n', ["cell.toml", "line 3"]),
    ("nested", b"x = " + b"[" * 5000 + b"]" * 5000 + b"\n", ["cell.toml", "nested"]),
    # tables and keys
    ("unknown-table", b"[bogus]\nx = 1\n", ["cell.toml", "unknown key 'bogus'"]),
    ("unknown-key", b"[zenoh]\nbogus = 1\n", ["cell.toml", "[zenoh]", "'bogus'"]),
    # wrong types
    ("rate-string", GOOD_TOML.replace("rate_hz = 1000", 'rate_hz = "1000"').encode(), ["rate_hz"]),
    ("listen-int", b"[zenoh]\nlisten = 5\n", ["[zenoh]", "'listen'"]),
    ("mode-list", b"[zenoh]\nmode = []\n", ["[zenoh]", "'mode'", "must be one of"]),
    ("bool-string", b'[recording]\nenabled = "yes"\n', ["[recording]", "'enabled'"]),
    ("device-not-table", b"device = [1]\n", ["[[device]] #1", "table"]),
    # numbers
    ("nan", b"[publish]\nhealth_period_s = nan\n", ["'health_period_s'", "finite"]),
    ("inf", b"[recording]\nchunk_interval_s = inf\n", ["'chunk_interval_s'", "finite"]),
    ("negative", b"[publish]\nmax_batch_age_s = -1.0\n", ["'max_batch_age_s'", ">= 0"]),
    ("zero", b"[publish]\nread_timeout_s = 0\n", ["'read_timeout_s'", "> 0"]),
    (
        "rate-negative",
        GOOD_TOML.replace("rate_hz = 1000", "rate_hz = -5").encode(),
        ["'rate_hz'", "> 0"],
    ),
    ("chunk-small", b"[recording]\nchunk_size_bytes = 10\n", ["'chunk_size_bytes'", ">= 1024"]),
    ("chunk-huge", b"[recording]\nchunk_size_bytes = 1_000_000_000_000\n", ["'chunk_size_bytes'"]),
    ("path-template", b'[recording]\npath = "{bogus}.mcap"\n', ["'path'", "{bogus}"]),
    ("endpoint", b'[zenoh]\nlisten = ["garbage"]\n', ["'listen'", "'garbage'", "endpoint"]),
]


@pytest.mark.parametrize("name, content, words", CONFIG_CASES, ids=[c[0] for c in CONFIG_CASES])
def test_config_refused(work, name, content, words):
    (work / "cell.toml").write_bytes(content)
    refused(work, daq("run", "--config", "cell.toml", "--duration", "1"), ["cell.toml", *words])


def test_config_table_given_as_a_value_with_an_environment_key(work):
    """Issue 22: this printed '<function _env_origin ...>: [zenoh] in the file is not a table'."""
    (work / "cell.toml").write_text('zenoh = "peer"\n', encoding="utf-8")
    proc = refused(
        work,
        daq("run", "--config", "cell.toml", "--duration", "1"),
        ["cell.toml", "[zenoh] must be a table", "DAQ_ZENOH_MODE"],
        env={"DAQ_ZENOH_MODE": "peer"},
    )
    assert "<function" not in proc.stderr
    refused(
        work,
        daq("run", "--config", "cell.toml", "--duration", "1"),
        ["DAQ_ZENOH_NOPE"],
        env={"DAQ_ZENOH_NOPE": "1"},
    )


def test_config_file_refused(work):
    argv = ["--duration", "1"]
    refused(work, daq("run", "--config", "missing.toml", *argv), ["missing.toml", "cannot read"])
    (work / "dir.toml").mkdir()
    refused(work, daq("run", "--config", "dir.toml", *argv), ["dir.toml", "directory"])
    refused(work, daq("run", "--config", "/dev/zero", *argv), ["/dev/zero", "device"])
    refused(work, daq("run", "--config", "", *argv), ["--config", "empty"])
    refused(
        work,
        daq("run", "--config", "cell.toml", *argv),
        ["cell.toml", "limit"],
        env={"GRATING_TWIN_MAX_INPUT_MB": "0.0001"},
    )


def test_config_bom_and_crlf_accepted(tmp_path):
    plain = tmp_path / "plain.toml"
    plain.write_text(GOOD_TOML, encoding="utf-8")
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + GOOD_TOML.encode())
    crlf = tmp_path / "crlf.toml"
    crlf.write_bytes(GOOD_TOML.replace("\n", "\r\n").encode())
    want = cfg.load(plain, environ={})
    for p in (bom, crlf):
        TALLY["accepted"] += 1
        assert cfg.load(p, environ={}).devices == want.devices
        assert cfg.load(p, environ={}).zenoh == want.zenoh


# -- run, record, echo, schema: options and outputs ---------------------------------------


def test_run_options(work):
    refused(work, daq("run", "--duration", "-1"), ["--duration", "> 0"])
    refused(work, daq("run", "--duration", "nan"), ["--duration", "finite"])
    refused(work, daq("run", "--rate", "0"), ["--rate"])
    refused(work, daq("run", "--rate", "nan"), ["--rate"])
    refused(
        work,
        daq("run", "--config", "cell.toml", "--record", "cell.toml", "--duration", "1"),
        ["--record", "is an input"],
    )
    refused(work, daq("run", "--record", "{nope}.mcap"), ["--record", "{nope}"])


def test_a_device_rate_has_one_bound_wherever_it_comes_from(work):
    """cell.toml's rate_hz = 1e9 was accepted (--rate refused over 100 kHz) and every
    sample was then counted as a gap: the same range for both."""
    for rate in ("1e9", "100001", "0"):
        (work / "fast.toml").write_text(GOOD_TOML.replace("rate_hz = 1000", f"rate_hz = {rate}"))
        refused(work, daq("run", "--config", "fast.toml", "--duration", "1"),
                ["fast.toml", "'rate_hz'", "100000", "Hz"])  # fmt: skip
        refused(work, daq("run", "--rate", rate), ["--rate"])
    doc = cfg.load(work / "cell.toml", environ={})
    assert doc.devices[0].rate_hz == 1000.0  # the bound itself and below: accepted
    (work / "edge.toml").write_text(GOOD_TOML.replace("rate_hz = 1000", "rate_hz = 100000"))
    assert cfg.load(work / "edge.toml", environ={}).devices[0].rate_hz == 100000.0


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--rate", "500"], ["--rate", "emulated cell only", "rate_hz"]),
        (["--sim-config", "cell.toml"], ["--sim-config", "emulated cell only"]),
        (["--no-record"], ["--no-record", "[recording] enabled = false"]),
    ],
)
def test_options_that_do_not_apply_beside_a_configuration_are_refused(work, extra, words):
    """They were silently ignored; refused before any device is opened (no network)."""
    refused(work, daq("run", "--config", "cell.toml", "--duration", "1", *extra), words)
    refused(work, daq("run", "--duration", "1", *extra), ["$DAQ_CONFIG", *words[1:]],
            env={"DAQ_CONFIG": "cell.toml"})  # fmt: skip


def test_record_and_no_record_together_are_refused(work):
    refused(work, daq("run", "--record", "x.mcap", "--no-record"), ["--no-record", "--record"])


def _processes_with(marker: str) -> list[int]:
    """The processes whose environment holds ``marker`` (Linux /proc)."""
    pids = []
    for environ in Path("/proc").glob("[0-9]*/environ"):
        try:
            if marker.encode() in environ.read_bytes():
                pids.append(int(environ.parent.name))
        except OSError:  # gone, or not ours to read
            continue
    return pids


def test_a_refused_run_of_the_emulated_cell_leaves_no_emulator_behind(work):
    """``daq run`` without a configuration starts the emulated cell before it reads its
    zenoh options and its recording path: a refusal of either stops the emulator too (it
    was left running, orphaned)."""
    marker = f"GRATING_TEST_MARKER=refused-run-{os.getpid()}"
    for argv, words in (
        (daq("run", "--mode", "client", "--connect", "none", "--duration", "5"), ["connect"]),
        (daq("run", "--record", "{nope}.mcap", "--duration", "5"), ["--record", "{nope}"]),
    ):
        refused(work, argv, words, env={"GRATING_TEST_MARKER": marker.split("=", 1)[1]})
        deadline = time.monotonic() + 10.0
        while _processes_with(marker) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = _processes_with(marker)
        for pid in left:  # not to leave them to the rest of the run
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        assert not left, f"{argv[1:]}: emulator processes left running: {left}"


def test_record_outputs_checked_before_subscribing(work):
    z = nowhere()
    refused(work, daq("record", "-o", "missing/x.mcap", *z), ["missing", "does not exist"])
    refused(
        work,
        daq("record", "-o", "cell.toml", "--config", "cell.toml", *z),
        ["cell.toml", "is an input"],
    )
    (work / "dir.mcap").mkdir()
    refused(work, daq("record", "-o", "dir.mcap", *z), ["dir.mcap", "directory"])
    refused(work, daq("record", "-o", "/proc/x.mcap", *z), ["/proc", "cannot write"])
    refused(work, daq("record", "-o", "x.mcap", "--duration", "0", *z), ["--duration"])
    refused(work, daq("record", "-o", "x.mcap", "--duration", "nan", *z), ["--duration"])
    refused(work, daq("record", "cell//x", "-o", "x.mcap", *z), ["key expression"])


def test_echo_outputs_and_options(work):
    z = nowhere()
    refused(work, daq("echo", "--jsonl", "missing/x.jsonl", *z), ["--jsonl", "does not exist"])
    refused(
        work,
        daq("echo", "--jsonl", "cell.toml", "--config", "cell.toml", *z),
        ["--jsonl", "is an input"],
    )
    refused(work, daq("echo", "--jsonl", "/proc/x.jsonl", *z), ["--jsonl", "/proc"])
    (work / "dir").mkdir()
    refused(work, daq("echo", "--jsonl", "dir", *z), ["--jsonl", "directory"])
    refused(work, daq("echo", "--count", "0", *z), ["--count", ">= 1"])
    refused(work, daq("echo", "--count", "-1", *z), ["--count"])
    refused(work, daq("echo", "--count", "x", *z), ["--count", "integer"])
    refused(work, daq("echo", "--idle", "-1", *z), ["--idle"])
    refused(work, daq("echo", "a/**/**", *z), ["key expression"])
    refused(work, daq("echo", "--cell", "a/b", *z), ["--cell", "'a/b'", "cell name"])
    refused(work, daq("echo", "--cell", "*", *z), ["--cell", "cell name"])
    # a key outside the cell's keys, with --cell: no subscription to nothing
    refused(work, daq("echo", "cell/c2/**", "--cell", "c1", *z), ["cell/c2/**", "--cell c1"])


def test_zenoh_endpoint_options(work):
    refused(work, daq("replay", "whole.mcap", "--listen", "garbage"), ["--listen", "garbage"])
    refused(work, daq("echo", "--connect", "127.0.0.1:7447"), ["--connect", "<protocol>"])


def test_schema_options(work):
    z = nowhere()
    refused(work, daq("schema", "cell/**", "--timeout", "0", *z), ["--timeout"])
    refused(work, daq("schema", "cell/**", "--timeout", "inf", *z), ["--timeout"])
    refused(work, daq("schema", "", *z), ["key expression"])


@pytest.mark.parametrize(
    "args, words",
    [
        (["--speed", "0"], ["--speed"]),
        (["--port", "0"], ["--port"]),
        (["--port", "70000"], ["--port"]),
        (["--rate", "nan"], ["--rate"]),
        (["--seed", "-1"], ["--seed"]),
        (["--robot", "nope"], ["--robot", "nope"]),
        (["--out", "data.csv"], ["--out", "data.csv", "not a directory"]),
    ],
)
def test_demo_options(work, args, words):
    argv = [PY, "-m", "daq.demo", "--out", "demo", *args]
    refused(work, argv, words)


# -- fuzz: the reader, recover, the config loader (in process) ------------------------------


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> tuple[bytes, set]:
    """A small whole recording in several chunks, and its messages."""
    p = write_recording(tmp_path_factory.mktemp("small") / "small.mcap", 24, chunk=600)
    data = p.read_bytes()
    assert len(chunk_messages(data)) >= 4
    return data, message_set(p)


def read_bytes_as_recording(tmp: Path, content: bytes):
    """The reader on ``content``: (Recording, messages) or RecordingError."""
    path = tmp / "f.mcap"
    path.write_bytes(content)
    try:
        rec = read_recording(path)
        got = {(m.topic, m.sequence, m.log_time, m.data) for m in rec.messages_iter()}
    except DaqError as exc:
        assert isinstance(exc, RecordingError)
        return exc
    return rec, got


def test_fuzz_reader_truncated_at_every_offset(tmp_path, small):
    data, whole = small
    previous = 0
    for cut in range(len(data) + 1):
        out = read_bytes_as_recording(tmp_path, data[:cut])
        if isinstance(out, DaqError):
            assert cut < len(MAGIC), cut
            continue
        rec, got = out
        assert got <= whole, cut  # nothing that was not recorded
        assert len(got) >= previous, cut  # a longer prefix never reads less
        previous = len(got)
        assert rec.complete == (cut == len(data))
        assert rec.messages == len(got)
    assert previous == len(whole)


def _check_recover(tmp: Path, content: bytes, whole: set) -> None:
    src = tmp / "in.mcap"
    src.write_bytes(content)
    out = tmp / "out.mcap"
    out.unlink(missing_ok=True)
    try:
        result = recover(src, out)
    except DaqError as exc:
        assert isinstance(exc, RecordingError)
        assert not out.exists()
    else:
        if result.output is None:
            assert result.recording.complete and not out.exists()
        else:
            assert library_count(out) == result.recording.messages
            assert message_set(out) <= whole
    assert src.read_bytes() == content  # never touched
    assert not [p for p in tmp.iterdir() if ".partial-" in p.name]


@FUZZ
@given(st.data())
def test_fuzz_recover_truncated(tmp_path_factory, small, data):
    content, whole = small
    cut = data.draw(st.integers(0, len(content)))
    _check_recover(tmp_path_factory.mktemp("r"), content[:cut], whole)


@FUZZ
@given(
    st.one_of(
        st.binary(max_size=3000),
        st.binary(max_size=3000).map(lambda b: MAGIC + b),
    )
)
def test_fuzz_reader_random_bytes(tmp_path_factory, blob):
    tmp = tmp_path_factory.mktemp("b")
    out = read_bytes_as_recording(tmp, blob)
    if not isinstance(out, DaqError):
        _rec, got = out
        assert blob.startswith(MAGIC) and not got  # random bytes hold no whole chunk
    _check_recover(tmp, blob, set())


@FUZZ
@given(st.data())
def test_fuzz_reader_and_recover_mutated(tmp_path_factory, small, data):
    content, whole = small
    changes = data.draw(
        st.lists(st.tuples(st.integers(0, len(content) - 1), st.integers(0, 255)), max_size=6)
    )
    b = bytearray(content)
    for i, v in changes:
        b[i] = v
    tmp = tmp_path_factory.mktemp("m")
    out = read_bytes_as_recording(tmp, bytes(b))
    if not isinstance(out, DaqError):
        _rec, got = out
        assert got <= whole  # a damaged chunk is skipped whole, never read wrong
    _check_recover(tmp, bytes(b), whole)


@pytest.fixture(scope="module")
def unchecked(tmp_path_factory) -> list[tuple[bytes, list[tuple[int, int]]]]:
    """Recordings whose records no CRC guards: chunks stored uncompressed with their CRC
    field zero (a writer that computes none), and a file without chunks (top-level
    schema, channel and message records); each with the byte ranges to mutate."""
    from mcap.writer import CompressionType, Writer

    tmp = tmp_path_factory.mktemp("unchecked")
    p = tmp / "plain.mcap"
    rec = McapRecorder(p, compression="none", chunk_size_bytes=600)
    cid = rec.add_columnar(SCHEMA)
    for i in range(12):
        rec.write(cid, encode(SCHEMA, {"seq": np.arange(3), "x_mm": np.ones(3)}, i), 1 + i)
    rec.close()
    b = bytearray(p.read_bytes())
    ranges = []
    for pos, op, length in top_records(bytes(b)):
        if op == 0x06:
            b[pos + 9 + 24 : pos + 9 + 28] = bytes(4)  # uncompressed_crc = 0: not computed
            ranges.append((pos + 9 + 40, pos + 9 + length))
    out = [(bytes(b), ranges)]
    q = tmp / "unchunked.mcap"
    with open(q, "wb") as fh:
        w = Writer(fh, use_chunking=False, compression=CompressionType.NONE)
        w.start()
        sid = w.register_schema(SCHEMA.key, "jsonschema", SCHEMA.dumps())
        ch = w.register_channel(SCHEMA.key, "daq.columnar.v1", sid, {"k": "v"})
        w.add_metadata("daq", {"cell": "c"})
        for i in range(8):
            w.add_message(ch, log_time=i, data=bytes([i]) * 5, publish_time=i, sequence=i)
        w.finish()
    data = q.read_bytes()
    out.append((data, [(len(MAGIC), len(data))]))
    return out


@FUZZ
@given(st.data())
def test_fuzz_records_no_crc_guards(tmp_path_factory, unchecked, data):
    """Inside a chunk without a CRC, or in a file without chunks, a mutation can change
    what is read; it must never raise anything but RecordingError, and recover's output
    must be a whole file."""
    content, ranges = data.draw(st.sampled_from(unchecked))
    lo, hi = data.draw(st.sampled_from(ranges))
    changes = data.draw(
        st.lists(st.tuples(st.integers(lo, hi - 1), st.integers(0, 255)), min_size=1, max_size=6)
    )
    b = bytearray(content)
    for i, v in changes:
        b[i] = v
    tmp = tmp_path_factory.mktemp("u")
    read_bytes_as_recording(tmp, bytes(b))
    src, out = tmp / "in.mcap", tmp / "out.mcap"
    src.write_bytes(bytes(b))
    try:
        result = recover(src, out)
    except RecordingError:
        assert not out.exists()
    else:
        if result.output is not None:
            assert library_count(out) == result.recording.messages
    assert src.read_bytes() == bytes(b)


def test_fuzz_one_damaged_chunk_costs_that_chunk_only(tmp_path, small):
    content, whole = small
    for k, (pos, _msgs) in enumerate(chunk_messages(content)):
        bad, _, lost = damage_chunk(content, k)
        rec, got = read_bytes_as_recording(tmp_path, bad)
        assert len(got) == len(whole) - lost, k
        assert [d.offset for d in rec.damaged] == [pos]


def test_a_length_that_swallows_a_chunk_is_caught(tmp_path, small):
    """A metadata record (no CRC) whose length field grew over the first chunk: the
    chunk is still read, the record is reported."""
    content, whole = small
    records = top_records(content)
    meta = next(r for r in records if r[1] == 0x0C)
    first_chunk = next(r for r in records if r[1] == 0x06)
    b = bytearray(content)
    struct.pack_into("<Q", b, meta[0] + 1, meta[2] + 9 + first_chunk[2])
    rec, got = read_bytes_as_recording(tmp_path, bytes(b))
    assert got == whole
    (d,) = rec.damaged
    assert (d.offset, d.end, d.record) == (meta[0], first_chunk[0], "metadata")
    assert d.reason.startswith("bad length")


def _load_config(tmp: Path, content: bytes):
    p = tmp / "cell.toml"
    p.write_bytes(content)
    try:
        return cfg.load(p, environ={})
    except DaqError as exc:
        assert isinstance(exc, ConfigError) and str(exc).strip()
        return exc


@FUZZ
@given(st.binary(max_size=400))
def test_fuzz_config_random_bytes(tmp_path_factory, blob):
    out = _load_config(tmp_path_factory.mktemp("c"), blob)
    assert isinstance(out, cfg.DaqConfig | ConfigError)


@FUZZ
@given(st.data())
def test_fuzz_config_mutated(tmp_path_factory, data):
    text = GOOD_TOML
    edits = data.draw(
        st.lists(
            st.tuples(
                st.integers(0, len(text)),
                st.integers(0, 3),
                st.text(alphabet='[]{}=",.#\n 0-9aenfitrux_', max_size=4),
            ),
            max_size=5,
        )
    )
    for at, drop, insert in edits:
        at = min(at, len(text))
        text = text[:at] + insert + text[at + drop :]
    out = _load_config(tmp_path_factory.mktemp("c"), text.encode())
    if isinstance(out, cfg.DaqConfig):
        for d in out.devices:
            assert d.rate_hz is None or (math.isfinite(d.rate_hz) and d.rate_hz > 0)
        assert math.isfinite(out.publish.health_period_s)
