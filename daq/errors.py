"""The daq package's one root exception and its children."""

from __future__ import annotations


class DaqError(Exception):
    """Root of every error raised by the ``daq`` package."""


class ConfigError(DaqError, ValueError):
    """The daemon configuration is malformed: the message names the file, table and key."""


class SchemaError(DaqError, ValueError):
    """A payload does not match its columnar schema (magic, id, sizes, dtypes)."""


class RecordingError(DaqError, OSError):
    """An MCAP recording cannot be written, read or recovered."""


class TransportError(DaqError, RuntimeError):
    """The zenoh session could not be opened or used."""
