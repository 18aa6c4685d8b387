"""Every exception class of the project belongs to exactly one kind of failure
(edges/errors.py: configuration, input data, device, numerical); the packages' roots to
none, so a kind is never caught by accident through a root."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

from calibration.errors import CalibrationError
from daq.errors import DaqError
from drivers.errors import DriverError
from edges.errors import (
    KINDS,
    ConfigurationError,
    DeviceError,
    InputDataError,
    NumericalError,
    kind_of,
)
from sim_devices.errors import SimError

PACKAGES = ("calibration", "daq", "drivers", "edges", "sim_devices", "view")
ROOTS = (CalibrationError, DaqError, DriverError, SimError)


def project_exceptions() -> dict[str, type[BaseException]]:
    """Every public exception class defined in a module of the project, by dotted name
    (private ones, ``_Name``, are one module's control flow and never leave it)."""
    found: dict[str, type[BaseException]] = {}
    for package in PACKAGES:
        pkg = importlib.import_module(package)
        names = [package, *(m.name for m in pkgutil.walk_packages(pkg.__path__, f"{package}."))]
        for name in names:
            module = importlib.import_module(name)
            for attr, obj in vars(module).items():
                if (
                    inspect.isclass(obj)
                    and issubclass(obj, BaseException)
                    and obj.__module__ == name
                    and not attr.startswith("_")
                ):
                    found[f"{name}.{attr}"] = obj
    return found


def test_every_exception_of_the_project_belongs_to_exactly_one_kind():
    classes = project_exceptions()
    assert len(classes) > 30  # the walk found the packages' errors
    roots_and_kinds = {*ROOTS, *KINDS}
    wrong = {
        name: [k.__name__ for k in KINDS if issubclass(cls, k)]
        for name, cls in classes.items()
        if cls not in roots_and_kinds and sum(issubclass(cls, k) for k in KINDS) != 1
    }
    assert wrong == {}


def test_the_roots_belong_to_no_kind():
    for root in ROOTS:
        assert kind_of(root) is None, root


@pytest.mark.parametrize(
    ("module", "name", "kind", "builtin"),
    [
        ("calibration.errors", "DescriptionError", ConfigurationError, ValueError),
        ("calibration.errors", "DataFileError", InputDataError, ValueError),
        ("calibration.errors", "CircleFitError", NumericalError, ValueError),
        ("daq.errors", "ConfigError", ConfigurationError, ValueError),
        ("daq.errors", "RecordingError", InputDataError, OSError),
        ("daq.errors", "PublishError", DeviceError, RuntimeError),
        ("drivers.errors", "DeviceIOError", DeviceError, OSError),
        ("drivers.errors", "DriverConfigError", ConfigurationError, ValueError),
        ("sim_devices.errors", "SimConfigError", ConfigurationError, ValueError),
    ],
)
def test_errors_keep_their_names_and_bases_and_gain_a_kind(module, name, kind, builtin):
    cls = getattr(importlib.import_module(module), name)
    assert kind_of(cls) is kind
    # what callers caught before still catches them
    assert issubclass(cls, ROOTS) and issubclass(cls, builtin)


def test_publish_error_lives_in_daq_errors_and_its_old_path_still_works():
    from daq import bus, errors

    assert bus.PublishError is errors.PublishError
    assert errors.PublishError.__module__ == "daq.errors"
    err = errors.PublishError([b"x"], OSError("put failed"))
    assert err.payloads == [b"x"] and isinstance(err, errors.TransportError)


def test_a_kind_is_caught_whatever_package_raised_it():
    from calibration.errors import OptionError
    from drivers.errors import DriverConfigError

    for cls in (OptionError, DriverConfigError):
        with pytest.raises(ConfigurationError):
            raise cls("bad")
