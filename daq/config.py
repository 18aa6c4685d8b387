"""The daemon's TOML configuration: devices, zenoh settings, recording.

Resolution order (style rule 9): command-line arguments, then ``DAQ_*`` environment
variables, then the file, then the defaults below. An environment variable
``DAQ_<TABLE>_<KEY>`` sets ``[table] key`` for the tables ``cell``, ``zenoh``,
``publish`` and ``recording`` (``DAQ_ZENOH_CONNECT='["tcp/10.0.0.2:7447"]'``,
``DAQ_RECORDING_PATH=/data/run.mcap``); its value is read as a TOML value when it parses
as one, as a plain string otherwise (a comma-separated string for a list key).
``DAQ_CONFIG`` names the file itself.

Every error names where the value came from, the table and the key, e.g.::

    cell.toml: [[device]] #2 'tracker': key 'rate_hz': expected a number, got str '1000'

See docs/daq.md for the full list of keys, types and defaults.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from daq.errors import ConfigError
from edges.inputs import MAX_TOML_BYTES, read_input_bytes

ENV_PREFIX = "DAQ_"
ENV_CONFIG = "DAQ_CONFIG"
#: the largest ``[recording] chunk_size_bytes`` (the reader loads one chunk at a time and
#: refuses records over ``daq.recording.MAX_RECORD_BYTES``, 256 MiB)
MAX_CHUNK_BYTES = 64 << 20
#: characters allowed in a name that becomes one chunk of a zenoh key expression
NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")
#: a zenoh endpoint: ``<protocol>/<address>[?<metadata>][#<config>]``
ENDPOINT_RE = re.compile(r"^[A-Za-z0-9+_-]+/\S+$")
#: channel names the daemon uses itself under each device's key
RESERVED_CHANNELS = ("health",)

ZENOH_MODES: dict[str, str] = {
    "peer": "peer on explicit endpoints (default; loopback listen, no scouting)",
    "client": "connect to one or more zenoh routers (zenohd) listed in connect",
    "router": "route for others (tests; deployments run zenohd)",
}
CONGESTION: dict[str, str] = {
    "block": "publisher waits when the queue is full (no loss; default for acquisition)",
    "drop": "publisher drops when the queue is full (zenoh's default; loses data)",
}
COMPRESSIONS: dict[str, str] = {"zstd": "zstandard", "lz4": "lz4 frame", "none": "uncompressed"}
FOXGLOVE_KINDS: dict[str, str] = {
    "auto": "points when the device has x_mm, y_mm, z_mm channels, else none",
    "points": "foxglove.PointCloud of the points since the last one (tracker points)",
    "poses": "foxglove.PosesInFrame of the poses since the last one (TCP poses)",
    "none": "no viewer channel",
}


@dataclass(frozen=True)
class CellConfig:
    name: str = "cell1"
    robot: str = "robot1"  # the robot a device belongs to unless it names another


@dataclass(frozen=True)
class ZenohConfig:
    mode: str = "peer"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    gossip_scouting: bool = False
    shared_memory: bool = False
    congestion_control: str = "block"
    #: zenoh's transmit queue for data, in batches of up to 64 KiB (zenoh allows 1-16,
    #: default 2). The daemon puts in bursts, one read's messages back to back; a queue
    #: that outlasts encoding the next read keeps the link busy meanwhile (docs/daq.md)
    tx_queue_batches: int = 16
    #: extra zenoh config entries, path -> JSON value (``insert_json5``), applied last
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PublishConfig:
    max_batch_samples: int = 500
    max_batch_age_s: float = 0.0  # publish each read: a fast device's read holds many samples
    health_period_s: float = 1.0
    read_timeout_s: float = 0.002
    gil_switch_s: float = 0.0005  # sys.setswitchinterval for the daemon (0: Python's 5 ms)
    # each device's acquisition in a process of its own (daq.worker): true, false, or
    # "auto": when the daemon runs more than one device (one device has no GIL to share)
    process_per_device: bool | str = "auto"
    #: SCHED_FIFO priority (1-99) of the daemon and its device workers; 0: normal
    #: scheduling (daq.scheduling; docs/daq.md "Real-time scheduling")
    realtime_priority: int = 0


@dataclass(frozen=True)
class RecordingConfig:
    enabled: bool = False
    path: str = "daq-{cell}-{start}.mcap"
    compression: str = "zstd"
    chunk_size_bytes: int = 1 << 20
    chunk_interval_s: float = 1.0
    #: Foxglove viewer channels (joints, points, TCP, frame transforms) at most this
    #: often per stream; 0: none (docs/daq.md "Recording")
    viewer_rate_hz: float = 30.0
    #: also record the live twin's keys (``twin/<cell>/**``) when a twin publishes
    twin: bool = True


@dataclass(frozen=True)
class ChannelGroup:
    """One published key under a device: a name and the driver channels it carries."""

    name: str
    channels: tuple[str, ...] = ()  # driver channel names; empty: all of them


@dataclass(frozen=True)
class DeviceConfig:
    name: str
    driver: str
    url: str
    robot: str
    rate_hz: float | None = None
    joints: tuple[int, ...] | None = None
    channels: tuple[ChannelGroup, ...] = ()
    options: Mapping[str, Any] = field(default_factory=dict)
    enabled: bool = True
    open_timeout_s: float = 5.0
    clock_latency_us: float = 0.0
    clock_window_s: float = 60.0
    foxglove: str = "auto"
    frame_id: str = "tracker"


@dataclass(frozen=True)
class DaqConfig:
    cell: CellConfig = field(default_factory=CellConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    publish: PublishConfig = field(default_factory=PublishConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    devices: tuple[DeviceConfig, ...] = ()
    source: str = "<defaults>"

    def device(self, name: str) -> DeviceConfig:
        for d in self.devices:
            if d.name == name:
                return d
        raise ConfigError(f"no device named {name!r}")


# -- value checking ---------------------------------------------------------------------------


class _Where:
    """Formats 'origin: [table] key' for error messages; origins per (table, key)."""

    def __init__(self, source: str, origins: Mapping[tuple[str, str], str]) -> None:
        self.source = source
        self.origins = origins

    def __call__(self, table: str, key: str) -> str:
        origin = self.origins.get((table, key), self.source)
        return f"{origin}: {table}: key {key!r}"


def _typename(v: Any) -> str:
    return type(v).__name__


def _number(v: Any, where: str, *, positive: bool = False, minimum: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ConfigError(f"{where}: expected a number, got {_typename(v)} {v!r}")
    x = float(v)
    if not math.isfinite(x):
        raise ConfigError(f"{where}: expected a finite number, got {v!r}")
    if positive and x <= 0:
        raise ConfigError(f"{where}: must be > 0, got {v!r}")
    if minimum is not None and x < minimum:
        raise ConfigError(f"{where}: must be >= {minimum}, got {v!r}")
    return x


def _integer(v: Any, where: str, *, minimum: int | None = None, maximum: int | None = None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(f"{where}: expected an integer, got {_typename(v)} {v!r}")
    if minimum is not None and v < minimum:
        raise ConfigError(f"{where}: must be >= {minimum}, got {v!r}")
    if maximum is not None and v > maximum:
        raise ConfigError(f"{where}: must be <= {maximum}, got {v!r}")
    return int(v)


def _string(v: Any, where: str) -> str:
    if not isinstance(v, str) or not v:
        raise ConfigError(f"{where}: expected a non-empty string, got {_typename(v)} {v!r}")
    return v


def _name(v: Any, where: str) -> str:
    s = _string(v, where)
    if not NAME_RE.match(s):
        raise ConfigError(
            f"{where}: {s!r} is not a valid key chunk (letters, digits, '_', '-', '.' only)"
        )
    return s


def _bool(v: Any, where: str) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(f"{where}: expected true or false, got {_typename(v)} {v!r}")
    return v


def _bool_or_auto(v: Any, where: str) -> bool | str:
    if v == "auto" or isinstance(v, bool):
        return v
    raise ConfigError(f'{where}: expected true, false or "auto", got {_typename(v)} {v!r}')


def _choice(v: Any, where: str, table: Mapping[str, str]) -> str:
    if not isinstance(v, str) or v not in table:
        raise ConfigError(f"{where}: must be one of {', '.join(table)}, got {v!r}")
    return str(v)


def _strings(v: Any, where: str) -> tuple[str, ...]:
    if isinstance(v, str):
        v = [s.strip() for s in v.split(",") if s.strip()]
    if not isinstance(v, list) or not all(isinstance(s, str) and s for s in v):
        raise ConfigError(f"{where}: expected a list of strings, got {_typename(v)} {v!r}")
    return tuple(v)


def _endpoints(v: Any, where: str) -> tuple[str, ...]:
    out = _strings(v, where)
    for e in out:
        if not ENDPOINT_RE.fullmatch(e):
            raise ConfigError(
                f"{where}: {e!r} is not a zenoh endpoint (<protocol>/<address>, e.g. "
                "tcp/127.0.0.1:7447)"
            )
    return out


def _check_keys(doc: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})"
        )


def _table(doc: Mapping[str, Any], name: str, source: str) -> Mapping[str, Any]:
    t = doc.get(name, {})
    if not isinstance(t, Mapping):
        raise ConfigError(f"{source}: [{name}] must be a table, got {_typename(t)}")
    return t


def _keys_of(cls: type) -> set[str]:
    return {f.name for f in fields(cls)}


# -- tables -------------------------------------------------------------------------------


def _parse_cell(t: Mapping[str, Any], w: _Where) -> CellConfig:
    _check_keys(t, _keys_of(CellConfig), f"{w.source}: [cell]")
    d = CellConfig()
    return CellConfig(
        name=_name(t.get("name", d.name), w("[cell]", "name")),
        robot=_name(t.get("robot", d.robot), w("[cell]", "robot")),
    )


def _parse_zenoh(t: Mapping[str, Any], w: _Where) -> ZenohConfig:
    _check_keys(t, _keys_of(ZenohConfig), f"{w.source}: [zenoh]")
    d = ZenohConfig()
    mode = _choice(t.get("mode", d.mode), w("[zenoh]", "mode"), ZENOH_MODES)
    listen_default: tuple[str, ...] = d.listen if mode != "client" else ()
    listen = _endpoints(t.get("listen", list(listen_default)), w("[zenoh]", "listen"))
    connect = _endpoints(t.get("connect", list(d.connect)), w("[zenoh]", "connect"))
    if mode == "client" and not connect:
        raise ConfigError(f"{w('[zenoh]', 'connect')}: mode 'client' needs a router endpoint")
    extra = t.get("extra", {})
    if not isinstance(extra, Mapping):
        raise ConfigError(f"{w('[zenoh]', 'extra')}: expected a table of zenoh config paths")
    return ZenohConfig(
        mode=mode,
        listen=listen,
        connect=connect,
        multicast_scouting=_bool(
            t.get("multicast_scouting", d.multicast_scouting), w("[zenoh]", "multicast_scouting")
        ),
        gossip_scouting=_bool(
            t.get("gossip_scouting", d.gossip_scouting), w("[zenoh]", "gossip_scouting")
        ),
        shared_memory=_bool(t.get("shared_memory", d.shared_memory), w("[zenoh]", "shared_memory")),
        congestion_control=_choice(
            t.get("congestion_control", d.congestion_control),
            w("[zenoh]", "congestion_control"),
            CONGESTION,
        ),
        tx_queue_batches=_integer(
            t.get("tx_queue_batches", d.tx_queue_batches),
            w("[zenoh]", "tx_queue_batches"),
            minimum=1,
            maximum=16,
        ),
        extra=dict(extra),
    )


def _parse_publish(t: Mapping[str, Any], w: _Where) -> PublishConfig:
    _check_keys(t, _keys_of(PublishConfig), f"{w.source}: [publish]")
    d = PublishConfig()
    return PublishConfig(
        max_batch_samples=_integer(
            t.get("max_batch_samples", d.max_batch_samples),
            w("[publish]", "max_batch_samples"),
            minimum=1,
        ),
        max_batch_age_s=_number(
            t.get("max_batch_age_s", d.max_batch_age_s),
            w("[publish]", "max_batch_age_s"),
            minimum=0.0,
        ),
        health_period_s=_number(
            t.get("health_period_s", d.health_period_s),
            w("[publish]", "health_period_s"),
            positive=True,
        ),
        read_timeout_s=_number(
            t.get("read_timeout_s", d.read_timeout_s),
            w("[publish]", "read_timeout_s"),
            positive=True,
        ),
        gil_switch_s=_number(
            t.get("gil_switch_s", d.gil_switch_s), w("[publish]", "gil_switch_s"), minimum=0.0
        ),
        process_per_device=_bool_or_auto(
            t.get("process_per_device", d.process_per_device),
            w("[publish]", "process_per_device"),
        ),
        realtime_priority=_integer(
            t.get("realtime_priority", d.realtime_priority),
            w("[publish]", "realtime_priority"),
            minimum=0,
            maximum=99,
        ),
    )


def path_template(v: Any, where: str) -> str:
    """A recording path that may hold ``{cell}`` and ``{start}`` (and nothing else in
    braces; ``{{`` is a literal brace)."""
    s = _string(v, where)
    try:
        s.format(cell="cell", start="20260101T000000Z")
    except (KeyError, IndexError, ValueError, AttributeError) as exc:
        why = f"unknown placeholder {{{exc.args[0]}}}" if isinstance(exc, KeyError) else str(exc)
        raise ConfigError(
            f"{where}: {s!r}: {why} (allowed: {{cell}}, {{start}}; '{{{{' for a brace)"
        ) from None
    return s


def _parse_recording(t: Mapping[str, Any], w: _Where) -> RecordingConfig:
    _check_keys(t, _keys_of(RecordingConfig), f"{w.source}: [recording]")
    d = RecordingConfig()
    return RecordingConfig(
        enabled=_bool(t.get("enabled", d.enabled), w("[recording]", "enabled")),
        path=path_template(t.get("path", d.path), w("[recording]", "path")),
        compression=_choice(
            t.get("compression", d.compression), w("[recording]", "compression"), COMPRESSIONS
        ),
        chunk_size_bytes=_integer(
            t.get("chunk_size_bytes", d.chunk_size_bytes),
            w("[recording]", "chunk_size_bytes"),
            minimum=1024,
            maximum=MAX_CHUNK_BYTES,
        ),
        chunk_interval_s=_number(
            t.get("chunk_interval_s", d.chunk_interval_s),
            w("[recording]", "chunk_interval_s"),
            positive=True,
        ),
        viewer_rate_hz=_viewer_rate(
            _number(t.get("viewer_rate_hz", d.viewer_rate_hz), w("[recording]", "viewer_rate_hz")),
            w("[recording]", "viewer_rate_hz"),
        ),
        twin=_bool(t.get("twin", d.twin), w("[recording]", "twin")),
    )


def _viewer_rate(value: float, where: str) -> float:
    if not 0.0 <= value <= 1000.0:
        raise ConfigError(f"{where}: must be >= 0 and <= 1000 (Hz), got {value}")
    return value


_DEVICE_KEYS = _keys_of(DeviceConfig)


def _parse_device(t: Any, i: int, cell: CellConfig, source: str) -> DeviceConfig:
    if not isinstance(t, Mapping):
        raise ConfigError(f"{source}: [[device]] #{i}: must be a table, got {_typename(t)}")
    label = f"{source}: [[device]] #{i}"
    if "name" in t and isinstance(t["name"], str):
        label += f" {t['name']!r}"

    def where(key: str) -> str:
        return f"{label}: key {key!r}"

    _check_keys(t, _DEVICE_KEYS, label)
    for key in ("name", "driver", "url"):
        if key not in t:
            raise ConfigError(f"{where(key)}: missing (required)")
    d = DeviceConfig(name="", driver="", url="", robot="")
    rate = t.get("rate_hz")
    joints = t.get("joints")
    if joints is not None:
        if not isinstance(joints, list) or not all(
            isinstance(j, int) and not isinstance(j, bool) and j >= 1 for j in joints
        ):
            raise ConfigError(f"{where('joints')}: expected a list of joint numbers (1-based)")
        joints = tuple(joints)
    groups: list[ChannelGroup] = []
    chan = t.get("channels", {})
    if not isinstance(chan, Mapping):
        raise ConfigError(f"{where('channels')}: expected a table name = [driver channels]")
    for gname, members in chan.items():
        gw = f"{label}: [channels] key {gname!r}"
        _name(gname, gw)
        if gname in RESERVED_CHANNELS:
            raise ConfigError(f"{gw}: {gname!r} is reserved (used by the daemon)")
        groups.append(ChannelGroup(gname, _strings(members, gw)))
    options = t.get("options", {})
    if not isinstance(options, Mapping):
        raise ConfigError(f"{where('options')}: expected a table of driver options")
    return DeviceConfig(
        name=_name(t["name"], where("name")),
        driver=_string(t["driver"], where("driver")),
        url=_string(t["url"], where("url")),
        robot=_name(t.get("robot", cell.robot), where("robot")),
        rate_hz=None if rate is None else _number(rate, where("rate_hz"), positive=True),
        joints=joints,
        channels=tuple(groups),
        options=dict(options),
        enabled=_bool(t.get("enabled", d.enabled), where("enabled")),
        open_timeout_s=_number(
            t.get("open_timeout_s", d.open_timeout_s), where("open_timeout_s"), positive=True
        ),
        clock_latency_us=_number(
            t.get("clock_latency_us", d.clock_latency_us), where("clock_latency_us"), minimum=0.0
        ),
        clock_window_s=_number(
            t.get("clock_window_s", d.clock_window_s), where("clock_window_s"), positive=True
        ),
        foxglove=_choice(t.get("foxglove", d.foxglove), where("foxglove"), FOXGLOVE_KINDS),
        frame_id=_string(t.get("frame_id", d.frame_id), where("frame_id")),
    )


TOP_KEYS = {"cell", "zenoh", "publish", "recording", "device"}
ENV_TABLES: dict[str, type] = {
    "cell": CellConfig,
    "zenoh": ZenohConfig,
    "publish": PublishConfig,
    "recording": RecordingConfig,
}


def parse(
    doc: Mapping[str, Any],
    source: str = "<config>",
    origins: Mapping[tuple[str, str], str] | None = None,
) -> DaqConfig:
    """Validate a configuration document (as from ``tomllib``)."""
    _check_keys(doc, TOP_KEYS, source)
    w = _Where(source, origins or {})
    cell = _parse_cell(_table(doc, "cell", source), w)
    devs = doc.get("device", [])
    if not isinstance(devs, list):
        raise ConfigError(f"{source}: [[device]] must be an array of tables")
    devices = tuple(_parse_device(t, i + 1, cell, source) for i, t in enumerate(devs))
    seen: set[str] = set()
    for dev in devices:
        if dev.name in seen:
            raise ConfigError(f"{source}: [[device]] {dev.name!r}: key 'name': duplicate")
        seen.add(dev.name)
    return DaqConfig(
        cell=cell,
        zenoh=_parse_zenoh(_table(doc, "zenoh", source), w),
        publish=_parse_publish(_table(doc, "publish", source), w),
        recording=_parse_recording(_table(doc, "recording", source), w),
        devices=devices,
        source=source,
    )


# -- layers: file < env < args ----------------------------------------------------------------


def _env_value(raw: str) -> Any:
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):
        return raw


def _toml(text: str, source: str) -> dict[str, Any]:
    """A TOML document, or a :class:`ConfigError` naming ``source`` and the line."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{source}: not valid TOML: arrays or tables nested too deeply") from None


def decode_text(data: bytes, source: str) -> str:
    """UTF-8 text (a byte-order mark dropped, CRLF allowed), or a :class:`ConfigError`
    naming ``source``, the line and column of the first byte that is not UTF-8."""
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise ConfigError(f"{source}: UTF-16 text; save the file as UTF-8")
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ConfigError(
            f"{source}: line {line}, column {column}: not UTF-8 (byte "
            f"{data[exc.start]:#04x}); save the file as UTF-8"
        ) from None


def env_overrides(environ: Mapping[str, str] | None = None) -> dict[str, dict[str, Any]]:
    """``DAQ_<TABLE>_<KEY>`` variables as ``{table: {key: value}}`` (origins noted)."""
    environ = os.environ if environ is None else environ
    out: dict[str, dict[str, Any]] = {}
    for var, raw in environ.items():
        if not var.startswith(ENV_PREFIX) or var == ENV_CONFIG:
            continue
        rest = var[len(ENV_PREFIX) :].lower()
        table, _, key = rest.partition("_")
        if table not in ENV_TABLES or not key:
            continue  # not ours (other DAQ_* tools may exist)
        if key not in _keys_of(ENV_TABLES[table]):
            raise ConfigError(
                f"environment {var}: [{table}] has no key {key!r} "
                f"(allowed: {', '.join(sorted(_keys_of(ENV_TABLES[table])))})"
            )
        out.setdefault(table, {})[key] = _env_value(raw)
    return out


def _env_origin(table: str, key: str) -> str:
    return f"environment {ENV_PREFIX}{table.upper()}_{key.upper()}"


def _arg_origin(table: str, key: str) -> str:
    return f"command-line argument ([{table}] {key})"


def _merge(
    doc: dict[str, Any],
    layer: Mapping[str, Mapping[str, Any]],
    origins: dict[tuple[str, str], str],
    origin: Callable[[str, str], str],
    source: str,
) -> None:
    for table, values in layer.items():
        t = doc.setdefault(table, {})
        if not isinstance(t, dict):
            setters = ", ".join(origin(table, key) for key in values)
            raise ConfigError(
                f"{source}: [{table}] must be a table, got {_typename(t)} "
                f"(and {setters} sets a key in it)"
            )
        for key, value in values.items():
            t[key] = value
            origins[(f"[{table}]", key)] = origin(table, key)


def load(
    path: str | Path | None = None,
    *,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    environ: Mapping[str, str] | None = None,
    base: Mapping[str, Any] | None = None,
) -> DaqConfig:
    """Resolve a configuration: ``overrides`` (args) > ``DAQ_*`` env > file > defaults.

    ``path`` None means ``$DAQ_CONFIG`` if set; ``base`` is a document used when there is
    no file (the emulated default cell).
    """
    environ = os.environ if environ is None else environ
    if path is None and environ.get(ENV_CONFIG):
        path = environ[ENV_CONFIG]
    if path is not None:
        source = str(path)
        if not source.strip():
            raise ConfigError("--config: empty path (or DAQ_CONFIG set to nothing)")
        data = read_input_bytes(path, limit=MAX_TOML_BYTES, error=ConfigError)
        doc: dict[str, Any] = _toml(decode_text(data, source), source)
    else:
        source = "<default cell>"
        doc = _deepcopy(base or {})
    origins: dict[tuple[str, str], str] = {}
    env = env_overrides(environ)
    _merge(doc, env, origins, _env_origin, source)
    if overrides:
        _merge(doc, overrides, origins, _arg_origin, source)
    return parse(doc, source, origins)


def loads(text: str, source: str = "<string>", **kw: Any) -> DaqConfig:
    doc = _toml(text, source)
    origins: dict[tuple[str, str], str] = {}
    env = env_overrides(kw.get("environ", {}))
    _merge(doc, env, origins, _env_origin, source)
    return parse(doc, source, origins)


def _deepcopy(doc: Any) -> Any:
    if isinstance(doc, Mapping):
        return {k: _deepcopy(v) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_deepcopy(v) for v in doc]
    return doc


# -- a command's configuration: file, environment, options ------------------------------
def zenoh_overrides(args: Any) -> dict[str, Any]:
    """The ``--mode/--listen/--connect`` options of a command as a ``[zenoh]`` table
    (``none`` as an endpoint: the empty list)."""
    z: dict[str, Any] = {}
    if getattr(args, "mode", None):
        z["mode"] = args.mode
    if getattr(args, "listen", None):
        z["listen"] = [e for e in args.listen if e != "none"]
    if getattr(args, "connect", None):
        z["connect"] = [e for e in args.connect if e != "none"]
    return z


def resolve(args: Any, extra: dict[str, dict[str, Any]] | None = None) -> DaqConfig:
    """The configuration of a command: ``args.config`` (file), the environment, ``extra``
    tables and the command's zenoh options, in rising precedence."""
    overrides: dict[str, dict[str, Any]] = dict(extra or {})
    z = zenoh_overrides(args)
    if z:
        overrides["zenoh"] = {**overrides.get("zenoh", {}), **z}
    return load(getattr(args, "config", None), overrides=overrides)


def sink_zenoh(args: Any) -> ZenohConfig:
    """zenoh settings of a sink: connect to where the source listens, listen nowhere."""
    user = zenoh_overrides(args)
    zc = resolve(SimpleNamespace(config=getattr(args, "config", None))).zenoh
    connect = list(zc.connect) if zc.mode == "client" else [*zc.listen, *zc.connect]
    zc = replace(zc, listen=(), connect=tuple(dict.fromkeys(connect)))
    if "mode" in user:
        zc = replace(zc, mode=user["mode"])
    if "listen" in user:
        zc = replace(zc, listen=tuple(user["listen"]))
    if "connect" in user:
        zc = replace(zc, connect=tuple(user["connect"]))
    return zc
