"""The public APIs of ``calibration`` and ``drivers``: their documented examples run as
written, every name in ``__all__`` resolves, and heavy parts load only when used."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap

import calibration
from calibration.identify.campaign_files import write_campaign
from sim_devices.pose_campaign import CampaignSettings, emulated_campaign


def docstring_example(module: object) -> str:
    """The code block (``::`` then indented lines) of a package's docstring."""
    doc = getattr(module, "__doc__", None) or ""
    return textwrap.dedent(re.search(r"::\n\n((?:    .*\n|\n)+)", doc).group(1))


def test_every_public_name_resolves():
    for name in calibration.__all__:
        assert getattr(calibration, name) is not None, name


def test_the_package_example_calibrates_a_campaign(tmp_path):
    data = emulated_campaign("kr500", 4, CampaignSettings(n_identify=60, n_validate=30))
    write_campaign(tmp_path / "campaign.csv", data.campaign)
    code = docstring_example(calibration)
    assert code.count("\n") <= 6  # five lines of Python, as promised
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(code, "calibration.__doc__", "exec"), {})  # our own docstring
    finally:
        os.chdir(cwd)
    desc = calibration.load_robot(str(tmp_path / "calibrated.toml"))
    assert desc.base is not None and desc.n_joints == 6


def test_importing_the_package_does_not_load_the_solvers():
    code = "import sys, calibration; print('calibration.effects.closed_loop' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "False", out.stderr


def test_drivers_exports_its_interface_and_registry():
    import drivers

    for name in drivers.__all__:
        assert getattr(drivers, name) is not None, name
    assert set(drivers.available_drivers()) >= {
        "grating_modbus",
        "encoder_canopen",
        "tracker_ascii",
    }
    assert issubclass(drivers.ProtocolError, drivers.DriverError)
    heavy = "('calibration', 'daq', 'canopen')"
    code = f"import sys, drivers; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "[]", out.stderr  # light: the protocols load per driver


def test_the_drivers_example_reads_a_tracker():
    import drivers
    from tests.drivers.test_driver_tracker import Tracker

    tracker = Tracker()
    try:
        code = docstring_example(drivers)
        code = code.replace("socket://127.0.0.1:5000", f"socket://127.0.0.1:{tracker.server.port}")
        scope: dict = {}
        exec(compile(code, "drivers.__doc__", "exec"), scope)  # our own docstring
        assert scope["batch"].schema is not None
    finally:
        tracker.close()


def test_daq_exports_its_formats_and_loads_zenoh_on_first_use():
    import daq

    for name in daq.__all__:
        assert getattr(daq, name) is not None, name
    heavy = "('zenoh', 'mcap', 'calibration')"
    code = f"import sys, daq; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "[]", out.stderr


def test_the_daq_example_receives_a_batch():
    """The docstring's subscriber, against a publisher listening where a daemon would."""
    import threading

    import numpy as np

    import daq
    from daq.bus import ChannelPublisher, SchemaServer, open_session
    from daq.testing import free_port, loopback_source

    port = free_port()
    session = open_session(loopback_source(port))
    schema = daq.StreamSchema(
        "cell/kr500/grating", (daq.Column("t_ns", "int64"), daq.Column("counts", "uint32", (6,)))
    )
    schemas = SchemaServer(session, "cell")
    pub = ChannelPublisher(session, schema, schemas=schemas)
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.01):
            pub.publish(
                {"t_ns": np.arange(3, dtype=np.int64), "counts": np.ones((3, 6), np.uint32)}
            )

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        code = docstring_example(daq)
        code = code.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
        scope: dict = {}
        exec(compile(code, "daq.__doc__", "exec"), scope)  # our own docstring
        batch = scope["batch"]
        assert batch is not None and batch.key == "cell/kr500/grating"
        assert batch.columns["counts"].shape == (3, 6)
    finally:
        stop.set()
        thread.join(5)
        pub.close()
        schemas.close()
        session.close()
