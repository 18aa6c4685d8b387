"""Which tests measure real time.

``make test`` runs the suite in two parts: the tests below, whose assertions depend on
real-time behaviour (no sample lost at 1 kHz, a clock map that settles within seconds,
frames reaching a browser, a live twin keeping up), alone, one at a time; every other
test on two pytest-xdist workers (their results do not depend on the host's speed). A
real-time test shares the machine with nothing of the suite's own, as before the split.
"""

from __future__ import annotations

from pathlib import Path

import pytest

#: test modules that acquire, publish or serve live (devices, the daemon, zenoh, a browser)
REALTIME_MODULES = frozenset(
    {
        "test_benchmarks_smoke",
        "test_bad_input_daq_live",
        "test_cell_hosts",
        "test_cell_hosts_multi",
        "test_cell_pick",
        "test_clock_sync",
        "test_daq_bus",
        "test_daq_daemon",
        "test_daq_demo",
        "test_demo_planned",
        "test_daq_emulated",
        "test_daq_loss",
        "test_daq_scheduling",
        "test_daq_subscriber",
        "test_daq_worker",
        "test_driver_encoders",
        "test_driver_grating",
        "test_driver_tracker",
        "test_router_faults",
        "test_router_cells",
        "test_sim_cell",
        "test_twin_endpoint",
        "test_twin_hosts",
        "test_twin_live",
        "test_twin_live_drift",
        "test_twin_live_tracking",
        "test_twin_live_clocks",
        "test_view",
    }
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if Path(str(item.fspath)).stem in REALTIME_MODULES:
            item.add_marker(pytest.mark.realtime)
