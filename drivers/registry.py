"""Driver lookup: a ``BACKENDS`` table merged with the ``daq.drivers`` entry-point group.

As python-can finds its interfaces: a name maps to ``(module, class)`` strings and the
module is imported only when that driver is chosen, so a missing optional library (say
``canopen``) fails only the driver that needs it. A package adds a device type without
touching this code by declaring, in its ``pyproject.toml``::

    [project.entry-points."daq.drivers"]
    my_device = "my_package.my_module:MyDriver"
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from drivers.base import Driver
from drivers.errors import DriverConfigError

ENTRY_POINT_GROUP = "daq.drivers"

#: Built-in drivers: name -> (module, class).
BACKENDS: dict[str, tuple[str, str]] = {
    "grating_modbus": ("drivers.grating_modbus", "GratingModbusDriver"),
    "tracker_ascii": ("drivers.tracker_ascii", "TrackerAsciiDriver"),
    "encoder_canopen": ("drivers.encoder_canopen", "EncoderCanopenDriver"),
}


def available_drivers() -> dict[str, tuple[str, str]]:
    """All known drivers: built-ins, then entry points (an entry point may not shadow one)."""
    found = dict(BACKENDS)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in found:
            continue
        module, _, attr = ep.value.partition(":")
        found[ep.name] = (module.strip(), attr.strip())
    return found


def driver_class(name: str) -> type[Driver]:
    """Import and return the driver class registered as ``name``."""
    if name in BACKENDS:  # built-ins win anyway: no need to scan the installed packages
        module_name, class_name = BACKENDS[name]
    else:
        table = available_drivers()
        if name not in table:
            raise DriverConfigError(
                f"unknown driver {name!r} (available: {', '.join(sorted(table))})"
            )
        module_name, class_name = table[name]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverConfigError(f"driver {name!r}: cannot import {module_name}: {exc}") from exc
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise DriverConfigError(f"driver {name!r}: {module_name}.{class_name} is not a Driver")
    return cls


def open_driver(name: str, url: str, *, open_timeout_s: float = 5.0, **options: Any) -> Driver:
    """Create the driver ``name`` on ``url`` with ``options`` and open it."""
    return driver_class(name)(url, **options).open(open_timeout_s)
