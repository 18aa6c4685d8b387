"""The daq package's one root exception and its children (:class:`PublishError` too,
once in ``daq.bus``: ``from daq.bus import PublishError`` still works)."""

from __future__ import annotations

from edges.errors import ConfigurationError, DeviceError, InputDataError


class DaqError(Exception):
    """Root of every error raised by the ``daq`` package."""


class ConfigError(DaqError, ConfigurationError, ValueError):
    """The daemon configuration is malformed: the message names the file, table and key."""


class SchemaError(DaqError, InputDataError, ValueError):
    """A payload does not match its columnar schema (magic, id, sizes, dtypes)."""


class RecordingError(DaqError, InputDataError, OSError):
    """An MCAP recording cannot be written, read or recovered."""


class TransportError(DaqError, DeviceError, RuntimeError):
    """The zenoh session could not be opened or used."""


class PublishError(TransportError):
    """Some puts of :meth:`daq.bus.ChannelPublisher.publish_slices` failed; ``payloads`` holds all
    of its payloads (for the recorder), ``cause`` the first error."""

    def __init__(self, payloads: list[bytes], cause: Exception) -> None:
        super().__init__(f"put failed: {cause!r}")
        self.payloads = payloads
        self.cause = cause


class DeviceAbsentError(DaqError, DeviceError):
    """A configured device could not be opened at start (the message names it)."""
