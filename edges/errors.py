"""The four kinds of failure every error of the project belongs to.

As python-can groups its errors by what went wrong (``CanInitializationError``,
``CanOperationError``, ``CanTimeoutError``) rather than by module, each exception of
``calibration``, ``daq``, ``drivers``, ``sim_devices`` and ``view`` inherits exactly one
of these kinds besides its package's root (``CalibrationError``, ``DaqError``,
``DriverError``, ``SimError``), so a caller can handle a kind whatever package raised it:
fix a file on a :class:`ConfigurationError`, reject a data set on an
:class:`InputDataError`, reconnect on a :class:`DeviceError`, gather other data on a
:class:`NumericalError`. ``tests/test_error_kinds.py`` holds every exception class to
exactly one kind.

Defined here because ``edges`` imports nothing from the project, so every package can
import it.
"""

from __future__ import annotations


class ConfigurationError(Exception):
    """What the user set up is wrong: a configuration or description file, an option, a
    name (driver, effect kind, preset), an output path."""


class InputDataError(Exception):
    """Data given to the project cannot be used: a measurement file, a recording, a
    stream, a payload, arrays of the wrong shape or with non-finite values."""


class DeviceError(Exception):
    """A device or the transport failed: the link, its protocol, a closed port, the
    zenoh session, a live source that stays silent."""


class NumericalError(Exception):
    """A computation cannot give a result from the data: a degenerate geometry, nothing
    identifiable, a fit that ran away."""


#: Every kind, for code (and the test) that checks an error's kind.
KINDS: tuple[type[Exception], ...] = (
    ConfigurationError,
    InputDataError,
    DeviceError,
    NumericalError,
)


def kind_of(exc: BaseException | type[BaseException]) -> type[Exception] | None:
    """The kind an error (or error class) belongs to; ``None`` for one of no kind (a
    package's root, or an exception from outside the project)."""
    cls = exc if isinstance(exc, type) else type(exc)
    found = [k for k in KINDS if issubclass(cls, k)]
    return found[0] if len(found) == 1 else None
