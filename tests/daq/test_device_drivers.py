"""The driver of a configured device: a registry name or ``module:Class``, which must be a
``drivers.base.Driver`` (the daemon's pipeline is typed against it)."""

from __future__ import annotations

import pytest

from daq.config import DeviceConfig
from daq.device_drivers import make_driver
from daq.errors import ConfigError
from daq.testing import FakeDriver


def device(driver: str) -> DeviceConfig:
    return DeviceConfig(name="d", driver=driver, url="fake://", robot="r")


def test_a_module_class_driver_is_made():
    assert isinstance(make_driver(device("daq.testing:FakeDriver")), FakeDriver)


def test_a_class_that_is_not_a_driver_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match=r"\[\[device\]\] 'd': key 'driver': .*not a Driver"):
        make_driver(device("daq.config:DeviceConfig"))
    with pytest.raises(ConfigError, match=r"key 'driver': .*not a Driver"):
        make_driver(device("daq.device_drivers:make_driver"))  # a function, not a class
