"""Driver registry: BACKENDS table + `daq.drivers` entry points, lazy import, validation."""

from __future__ import annotations

from importlib.metadata import EntryPoint

import pytest

from drivers import registry
from drivers.base import DeviceClock, SampleBatch
from drivers.errors import DriverConfigError


def test_builtin_and_entry_points_listed():
    names = registry.available_drivers()
    assert {"grating_modbus", "tracker_ascii", "encoder_canopen"} <= set(names)


def test_plugin_entry_point_is_found(monkeypatch):
    ep = EntryPoint("fake", "drivers.tracker_ascii:TrackerAsciiDriver", "daq.drivers")
    monkeypatch.setattr(registry, "entry_points", lambda group: [ep])
    assert registry.driver_class("fake").kind == "tracker_ascii"


def test_unknown_driver_lists_choices():
    with pytest.raises(DriverConfigError, match="available"):
        registry.driver_class("nope")


def test_empty_batch_and_concat():
    from drivers.grating_modbus import SCHEMA

    e = SampleBatch.empty(SCHEMA)
    assert len(e) == 0 and e.values.shape == (0, 6)
    assert len(SampleBatch.concat(SCHEMA, [e, e])) == 0
    assert SCHEMA.describe()["channels"][0]["name"] == "grating1_counts"


def test_device_clock_restart_and_wrap():
    c = DeviceClock(bits=32)
    t, ep = c.unwrap([2**32 - 2000, 2**32 - 1000, 0, 1000])
    assert list(t) == [2**32 - 2000, 2**32 - 1000, 2**32, 2**32 + 1000] and c.wraps == 1
    t, ep = c.unwrap([500, 1500])  # went back: a restart
    assert c.restarts == 1 and list(ep) == [1, 1] and list(t) == [500, 1500]
