"""The acquisition daemon: device drivers → timestamped columnar batches on zenoh and MCAP.

Programs meet the daemon through its data: one columnar batch per message on a zenoh key
per device (docs/topics.md), its schema on a queryable beside it, and MCAP recordings of
the same bytes. The names below are the public API; the zenoh and MCAP parts load on
first use (PEP 562). A subscriber in three lines (the daemon's default endpoint)::

    from daq import Receiver, ZenohConfig, open_session

    config = ZenohConfig(mode="client", listen=(), connect=("tcp/127.0.0.1:7447",))
    batch = Receiver(open_session(config), "cell/**").receive(timeout_s=5.0)
    print(batch.key, {name: column.shape for name, column in batch.columns.items()})

A standard zenoh subscriber reads the same batches with :func:`decode` and the schema
(``<key>/@schema``); ``daq run`` / ``daq record`` / ``daq replay`` are the commands
(docs/daq.md). The package imports ``drivers`` and ``edges`` only.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from daq.columnar import Column, Header, StreamSchema, decode, encode, read_header
from daq.config import DaqConfig, DeviceConfig, ZenohConfig, load, loads
from daq.errors import ConfigError, DaqError, RecordingError, SchemaError, TransportError

if TYPE_CHECKING:
    from daq.bus import ChannelPublisher, Received, Receiver, open_session
    from daq.daemon import Daemon
    from daq.recording_reader import Recording, read_recording
    from daq.recording_recover import recover

#: The daemon's configuration from a TOML file / text (the names say what they load);
#: ``load`` and ``loads`` are the old names, kept for programs that use them.
load_config = load
loads_config = loads

#: name -> module, imported on first use (zenoh, mcap)
_LAZY = {
    "ChannelPublisher": "daq.bus",
    "Received": "daq.bus",
    "Receiver": "daq.bus",
    "open_session": "daq.bus",
    "Daemon": "daq.daemon",
    "Recording": "daq.recording_reader",
    "read_recording": "daq.recording_reader",
    "recover": "daq.recording_recover",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'daq' has no attribute {name!r}")


__all__ = [
    "ChannelPublisher",
    "Column",
    "ConfigError",
    "Daemon",
    "DaqConfig",
    "DaqError",
    "DeviceConfig",
    "Header",
    "Received",
    "Receiver",
    "Recording",
    "RecordingError",
    "SchemaError",
    "StreamSchema",
    "TransportError",
    "ZenohConfig",
    "decode",
    "encode",
    "load",
    "load_config",
    "loads",
    "loads_config",
    "open_session",
    "read_header",
    "read_recording",
    "recover",
]
