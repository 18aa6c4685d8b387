"""The drivers package's one root exception and its children."""

from __future__ import annotations

from edges.errors import ConfigurationError, DeviceError


class DriverError(Exception):
    """Root of every error raised by the ``drivers`` package."""


class DriverConfigError(DriverError, ConfigurationError, ValueError):
    """Bad driver name, URL or option (the message lists what is allowed)."""


class DriverClosedError(DriverError, DeviceError, RuntimeError):
    """The driver was used after :meth:`~drivers.base.Driver.close`."""


class DeviceIOError(DriverError, DeviceError, OSError):
    """The link to the device failed (raised by adapters, handled by the base class).

    The base class catches it, counts it, closes the link and reconnects with backoff:
    callers of :meth:`~drivers.base.Driver.read` never see it.
    """


class ProtocolError(DriverError, DeviceError):
    """A frame from the device could not be parsed (counted, never fatal)."""

    def __init__(self, kind: str, message: str = "") -> None:
        super().__init__(f"{kind}: {message}" if message else kind)
        self.kind = kind
