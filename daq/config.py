"""The daemon's TOML configuration: devices, zenoh settings, recording.

Resolution order (style rule 9): command-line arguments, then ``DAQ_*`` environment
variables, then the file, then the defaults below. An environment variable
``DAQ_<TABLE>_<KEY>`` sets ``[table] key`` for the tables ``cell``, ``zenoh``,
``publish`` and ``recording`` (``DAQ_ZENOH_CONNECT='["tcp/10.0.0.2:7447"]'``,
``DAQ_RECORDING_PATH=/data/run.mcap``); its value is read as a TOML value when it parses
as one, as a plain string otherwise (a comma-separated string for a list key).
``DAQ_CONFIG`` names the file itself.

Each table is a dataclass below, read by the project's one TOML reader
(:mod:`edges.toml_schema`): types from the hints, ranges, choices and checks in the
fields' metadata. Every error names where the value came from (the file, an environment
variable, a command-line argument), the table and the key, e.g.::

    cell.toml: [[device]] #2 'tracker': key 'rate_hz': expected a number, got str '1000'
    environment DAQ_PUBLISH_HEALTH_PERIOD_S: [publish]: key 'health_period_s': must be > 0, got 0

See docs/daq.md for the full list of keys, types and defaults.
"""

from __future__ import annotations

import os
import re
import tomllib
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, TypeVar

from daq.errors import ConfigError
from daq.tls import check_tls_files
from edges.inputs import MAX_TOML_BYTES, read_input_bytes
from edges.toml_schema import (
    NON_NEGATIVE,
    POSITIVE,
    Range,
    TomlTable,
    build,
    key_spec,
    origins_at,
    parse_toml_text,
    short,
)

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

ENV_PREFIX = "DAQ_"
ENV_CONFIG = "DAQ_CONFIG"
#: the largest ``[recording] chunk_size_bytes`` (the reader loads one chunk at a time and
#: refuses records over ``daq.recording_reader.MAX_RECORD_BYTES``, 256 MiB)
MAX_CHUNK_BYTES = 64 << 20
#: the fastest device rate the daemon takes (Hz), from cell.toml (``rate_hz``) or from
#: ``daq run --rate``: one bound wherever the value comes from
MAX_RATE_HZ = 100_000.0
#: a device's sample rate: > 0 and at most MAX_RATE_HZ
RATE_HZ = Range(0.0, MAX_RATE_HZ, lo_open=True, what="Hz")
#: the longest a daemon waits at start for an absent device (s; an hour)
MAX_WAIT_FOR_DEVICE_S = 3600.0
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


# -- checks of single values, beyond their types and ranges (edges.toml_schema.Check) -------
def _key_chunk(value: str) -> str | None:
    """Why ``value`` cannot be one chunk of a zenoh key (None: it can)."""
    if NAME_RE.match(value):
        return None
    return f"{value!r} is not a valid key chunk (letters, digits, '_', '-', '.' only)"


def _non_empty(value: str) -> str | None:
    return None if value else f"expected a non-empty string, got {value!r}"


def _endpoints(values: tuple[str, ...]) -> str | None:
    for e in values:
        if not ENDPOINT_RE.fullmatch(e):
            return f"{e!r} is not a zenoh endpoint (<protocol>/<address>, e.g. tcp/127.0.0.1:7447)"
    return None


def _at_most(hi: int) -> Callable[[int], str | None]:
    """The upper bound of an integer whose range is its lower one: a refusal names the
    bound crossed (``must be >= 1024`` by the range, ``must be <= 16`` here)."""
    return lambda value: f"must be <= {hi}, got {value!r}" if value > hi else None


def template_refusal(value: str) -> str | None:
    """Why ``value`` is not a recording path template: only ``{cell}`` and ``{start}`` in
    braces (``{{`` is a literal brace), not empty. None: it is one."""
    if not value:
        return f"expected a non-empty string, got {value!r}"
    try:
        value.format(cell="cell", start="20260101T000000Z")
    except (KeyError, IndexError, ValueError, AttributeError) as exc:
        why = f"unknown placeholder {{{exc.args[0]}}}" if isinstance(exc, KeyError) else str(exc)
        return f"{value!r}: {why} (allowed: {{cell}}, {{start}}; '{{{{' for a brace)"
    return None


KEY_CHUNK = key_spec(check=_key_chunk)
NON_EMPTY = key_spec(check=_non_empty)
ENDPOINTS = key_spec(check=_endpoints)


# -- the tables -------------------------------------------------------------------------------
@dataclass(frozen=True)
class CellConfig:
    name: str = field(default="cell1", metadata=KEY_CHUNK)
    # the robot a device belongs to unless it names another
    robot: str = field(default="robot1", metadata=KEY_CHUNK)


@dataclass(frozen=True)
class ZenohConfig:
    mode: str = field(default="peer", metadata=key_spec(choices=tuple(ZENOH_MODES)))
    #: default for peer and router; a client listens nowhere unless told (:func:`parse`)
    listen: tuple[str, ...] = field(default=("tcp/127.0.0.1:7447",), metadata=ENDPOINTS)
    connect: tuple[str, ...] = field(default=(), metadata=ENDPOINTS)
    multicast_scouting: bool = False
    gossip_scouting: bool = False
    shared_memory: bool = False
    congestion_control: str = field(default="block", metadata=key_spec(choices=tuple(CONGESTION)))
    #: zenoh's transmit queue for data, in batches of up to 64 KiB (zenoh allows 1-16,
    #: default 2). The daemon puts in bursts, one read's messages back to back; a queue
    #: that outlasts encoding the next read keeps the link busy meanwhile (docs/daq.md)
    tx_queue_batches: int = field(default=16, metadata=key_spec(range=Range(1), check=_at_most(16)))
    #: TLS on ``tls/`` endpoints (docs/deployment.md): the CA that signed the router's
    #: certificate (and ours), and this host's client certificate and key (PEM files;
    #: empty: unset). A certificate makes the link mutually authenticated
    tls_ca: str = ""
    tls_certificate: str = ""
    tls_private_key: str = ""
    #: extra zenoh config entries, path -> JSON value (``insert_json5``), applied last
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PublishConfig:
    max_batch_samples: int = field(default=500, metadata=key_spec(range=Range(1)))
    # publish each read: a fast device's read holds many samples
    max_batch_age_s: float = field(default=0.0, metadata=key_spec(range=NON_NEGATIVE))
    health_period_s: float = field(default=1.0, metadata=key_spec(range=POSITIVE))
    read_timeout_s: float = field(default=0.002, metadata=key_spec(range=POSITIVE))
    # sys.setswitchinterval for the daemon (0: Python's 5 ms)
    gil_switch_s: float = field(default=0.0005, metadata=key_spec(range=NON_NEGATIVE))
    # each device's acquisition in a process of its own (daq.worker): true, false, or
    # "auto": when the daemon runs more than one device (one device has no GIL to share)
    process_per_device: bool | str = field(
        default="auto", metadata=key_spec(choices=(True, False, "auto"))
    )
    #: SCHED_FIFO priority (1-99) of the daemon and its device workers; 0: normal
    #: scheduling (daq.scheduling; docs/daq.md "Real-time scheduling")
    realtime_priority: int = field(default=0, metadata=key_spec(range=Range(0), check=_at_most(99)))
    #: a client of routers warns when its clock is further than this from the router's
    #: (daq.host_clock; docs/deployment.md "Faults")
    clock_tolerance_s: float = field(default=0.01, metadata=key_spec(range=POSITIVE))


@dataclass(frozen=True)
class RecordingConfig:
    enabled: bool = False
    path: str = field(default="daq-{cell}-{start}.mcap", metadata=key_spec(check=template_refusal))
    compression: str = field(default="zstd", metadata=key_spec(choices=tuple(COMPRESSIONS)))
    chunk_size_bytes: int = field(
        default=1 << 20, metadata=key_spec(range=Range(1024), check=_at_most(MAX_CHUNK_BYTES))
    )
    chunk_interval_s: float = field(default=1.0, metadata=key_spec(range=POSITIVE))
    #: Foxglove viewer channels (joints, points, TCP, frame transforms) at most this
    #: often per stream; 0: none (docs/daq.md "Recording")
    viewer_rate_hz: float = field(
        default=30.0, metadata=key_spec(range=Range(0.0, 1000.0, what="Hz"))
    )
    #: also record the live twin's keys (``twin/<cell>/**``) when a twin publishes
    twin: bool = True


@dataclass(frozen=True)
class ChannelGroup:
    """One published key under a device: a name and the driver channels it carries."""

    name: str
    channels: tuple[str, ...] = ()  # driver channel names; empty: all of them


@dataclass(frozen=True)
class DeviceConfig:
    """One ``[[device]]``; ``robot`` defaults to ``[cell] robot`` and ``channels`` is
    read from the ``[device.channels]`` table (:func:`parse`)."""

    name: str = field(metadata=KEY_CHUNK)
    driver: str = field(metadata=NON_EMPTY)
    url: str = field(metadata=NON_EMPTY)
    robot: str = field(metadata=KEY_CHUNK)
    rate_hz: float | None = field(default=None, metadata=key_spec(range=RATE_HZ))
    joints: tuple[int, ...] | None = field(
        default=None, metadata=key_spec(range=Range(1, what="joint numbers, 1-based"))
    )
    channels: tuple[ChannelGroup, ...] = ()
    options: Mapping[str, Any] = field(default_factory=dict)
    enabled: bool = True
    open_timeout_s: float = field(default=5.0, metadata=key_spec(range=POSITIVE))
    #: absent at start: wait this long for the device (0: refuse at once; daq.device_presence)
    wait_for_device_s: float = field(
        default=0.0, metadata=key_spec(range=Range(0.0, MAX_WAIT_FOR_DEVICE_S, what="s"))
    )
    clock_latency_us: float = field(default=0.0, metadata=key_spec(range=NON_NEGATIVE))
    clock_window_s: float = field(default=60.0, metadata=key_spec(range=POSITIVE))
    foxglove: str = field(default="auto", metadata=key_spec(choices=tuple(FOXGLOVE_KINDS)))
    frame_id: str = field(default="tracker", metadata=NON_EMPTY)


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


ENV_TABLES: dict[str, type] = {
    "cell": CellConfig,
    "zenoh": ZenohConfig,
    "publish": PublishConfig,
    "recording": RecordingConfig,
}
TOP_KEYS = {*ENV_TABLES, "device"}
T = TypeVar("T", bound="DataclassInstance")


def parse(
    doc: Mapping[str, Any],
    source: str = "<config>",
    origins: Mapping[str, str] | None = None,
) -> DaqConfig:
    """Validate a configuration document (as from ``tomllib``); ``origins``: where a
    value came from when not from ``source``, by dotted key (``zenoh.mode``)."""
    top = TomlTable(dict(doc), source, "top level", ConfigError)
    unknown = sorted(set(doc) - TOP_KEYS)
    if unknown:
        allowed = ", ".join(sorted(TOP_KEYS))
        raise top.fail(None, f"unknown key {unknown[0]!r} (allowed: {allowed})")

    def table(cls: type[T], name: str) -> T:
        given = _comma_lists(doc.get(name, {}), cls)
        return build(cls, given, source=source, error=ConfigError, path=(name,), origins=origins)

    cell = table(CellConfig, "cell")
    devs = doc.get("device", [])
    if not isinstance(devs, list):
        raise top.fail("device", f"expected an array of tables ([[device]]), got {short(devs)}")
    devices: list[DeviceConfig] = []
    for i, t in enumerate(devs, start=1):
        dev = _device(t, f"[[device]] #{i}", cell, source)
        if dev.name in {d.name for d in devices}:
            raise ConfigError(f"{source}: [[device]] {dev.name!r}: key 'name': duplicate")
        devices.append(dev)
    zenoh = table(ZenohConfig, "zenoh")
    if zenoh.mode == "client":
        given = doc.get("zenoh", {})
        if "listen" not in given:
            zenoh = replace(zenoh, listen=())
        if not zenoh.connect:
            z = TomlTable(given, source, "[zenoh]", ConfigError, origins_at(origins, ("zenoh",)))
            raise z.fail("connect", "mode 'client' needs a router endpoint")
    check_tls_files(zenoh, source, origins)
    return DaqConfig(
        cell=cell,
        zenoh=zenoh,
        publish=table(PublishConfig, "publish"),
        recording=table(RecordingConfig, "recording"),
        devices=tuple(devices),
        source=source,
    )


def _comma_list(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def _comma_lists(values: Any, cls: type) -> Any:
    """``values`` with a list key given as one string read as a comma-separated list
    (how an environment variable says a list; the file may say it so too)."""
    if not isinstance(values, dict):
        return values  # build() names what it is
    hints = typing.get_type_hints(cls)
    return {
        k: _comma_list(v) if isinstance(v, str) and typing.get_origin(hints.get(k)) is tuple else v
        for k, v in values.items()
    }


def _device(t: Any, label: str, cell: CellConfig, source: str) -> DeviceConfig:
    """One ``[[device]]`` table: its keys, then its ``[device.channels]``."""
    if isinstance(t, dict) and isinstance(t.get("name"), str):
        label += f" {t['name']!r}"
    table = TomlTable(t, source, label, ConfigError)
    keys = {k: v for k, v in table.data.items() if k != "channels"}
    dev = build(
        DeviceConfig, {"robot": cell.robot, **keys}, source=source, error=ConfigError, name=label
    )
    chan = TomlTable(table.data.get("channels", {}), source, f"{label}: [channels]", ConfigError)
    groups = []
    for name in chan.data:
        refusal = _key_chunk(name)
        if refusal is None and name in RESERVED_CHANNELS:
            refusal = f"{name!r} is reserved (used by the daemon)"
        if refusal is not None:
            raise chan.fail(name, refusal)
        members = chan.data[name]
        groups.append(
            ChannelGroup(
                name,
                chan.strings(name, _comma_list(members) if isinstance(members, str) else members),
            )
        )
    return replace(dev, channels=tuple(groups))


# -- layers: file < env < args ----------------------------------------------------------------


def _env_value(raw: str) -> Any:
    """A variable's value: TOML when it parses as TOML, else the text."""
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):
        return raw


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
        allowed = {f.name for f in fields(ENV_TABLES[table])}
        if key not in allowed:
            raise ConfigError(
                f"environment {var}: [{table}] has no key {key!r} "
                f"(allowed: {', '.join(sorted(allowed))})"
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
    origins: dict[str, str],
    origin: Callable[[str, str], str],
    source: str,
) -> None:
    """``layer``'s values over ``doc``'s, each noted in ``origins`` (by dotted key)."""
    for table, values in layer.items():
        t = doc.setdefault(table, {})
        if not isinstance(t, dict):
            setters = ", ".join(origin(table, key) for key in values)
            raise ConfigError(
                f"{source}: [{table}] must be a table, got {type(t).__name__} "
                f"(and {setters} sets a key in it)"
            )
        for key, value in values.items():
            t[key] = value
            origins[f"{table}.{key}"] = origin(table, key)


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
        doc: dict[str, Any] = parse_toml_text(decode_text(data, source), source, ConfigError)
    else:
        source = "<default cell>"
        doc = _deepcopy(base or {})
    origins: dict[str, str] = {}
    env = env_overrides(environ)
    _merge(doc, env, origins, _env_origin, source)
    if overrides:
        _merge(doc, overrides, origins, _arg_origin, source)
    return parse(doc, source, origins)


def loads(text: str, source: str = "<string>", **kw: Any) -> DaqConfig:
    doc = parse_toml_text(text, source, ConfigError)
    origins: dict[str, str] = {}
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
