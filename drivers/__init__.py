"""Device adapters on real wire protocols, behind one small interface (python-can's shape).

A driver is found by name (:func:`open_driver`, :func:`available_drivers`): the built-in
``grating_modbus`` (Modbus RTU), ``encoder_canopen`` (CANopen CiA 406 over socketcand) and
``tracker_ascii`` (the tracker's ASCII protocol over TCP or serial), plus any a package
declares in the ``daq.drivers`` entry-point group. Every driver reads
:class:`SampleBatch` es stamped with its :class:`DeviceClock`; every error is a
:class:`DriverError`::

    from drivers import open_driver

    with open_driver("tracker_ascii", "socket://127.0.0.1:5000") as tracker:
        batch = tracker.read(timeout_s=1.0)

See docs/drivers.md. The package imports nothing of the project but :mod:`edges`.
"""

from drivers.base import BatchSchema, ChannelSchema, DeviceClock, Driver, Health, SampleBatch
from drivers.errors import (
    DeviceIOError,
    DriverClosedError,
    DriverConfigError,
    DriverError,
    ProtocolError,
)
from drivers.registry import available_drivers, driver_class, open_driver

__all__ = [
    "BatchSchema",
    "ChannelSchema",
    "DeviceClock",
    "DeviceIOError",
    "Driver",
    "DriverClosedError",
    "DriverConfigError",
    "DriverError",
    "Health",
    "ProtocolError",
    "SampleBatch",
    "available_drivers",
    "driver_class",
    "open_driver",
]
