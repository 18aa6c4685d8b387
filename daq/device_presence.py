"""Is every configured device there when the daemon starts?

A device path that does not exist (an unplugged adapter, a typo) used to be retried every
second for ever, one log line per attempt, by a daemon that looked as if it ran. Before
the daemon opens anything else, each enabled device is opened once and closed again:

* absent, and ``[[device]] wait_for_device_s = 0`` (the default): one line naming the
  device, its URL and why (:class:`DeviceAbsentError`, exit 2) after at most
  :data:`START_CHECK_S` seconds of trying (or the device's ``open_timeout_s``, if
  shorter);
* absent, and ``wait_for_device_s > 0``: the daemon waits up to that long, saying so once
  per :data:`WAIT_REPORT_S` seconds on stderr (not once per attempt), then refuses the
  same way.

A device lost while the daemon runs is reconnected as before (daq.pipeline): this check
is for the start only.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable

from daq.config import DaqConfig, DeviceConfig
from daq.device_drivers import DriverFactory
from daq.errors import DeviceAbsentError

#: the longest an absent device is tried at start without ``wait_for_device_s`` (s)
START_CHECK_S = 3.0
#: while waiting for a device, one line per this many seconds (s)
WAIT_REPORT_S = 10.0


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _try_open(driver_factory: DriverFactory, dev: DeviceConfig, s: float) -> str:
    """Open ``dev`` for up to ``s`` seconds and close it again; why it failed ("": it
    opened)."""
    from drivers.errors import DriverError

    quiet = logging.getLogger("drivers")  # their per-failure lines: this check says it once
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    driver = driver_factory(dev)
    try:
        driver.open(timeout_s=s)
    except DriverError as exc:
        return str(exc)
    finally:
        driver.close()
        quiet.setLevel(level)
    return ""


def check_devices_present(
    cfg: DaqConfig,
    driver_factory: DriverFactory,
    *,
    say: Callable[[str], None] = _say,
) -> None:
    """Raise :class:`DeviceAbsentError` for the first enabled device of ``cfg`` that does
    not open within its bound (module docstring); wait where the configuration asks."""
    for dev in cfg.devices:
        if not dev.enabled:
            continue
        wait_s = dev.wait_for_device_s
        attempt_s = min(dev.open_timeout_s, START_CHECK_S)
        deadline = time.monotonic() + max(wait_s, attempt_s)
        next_report = time.monotonic()
        while True:
            left = deadline - time.monotonic()
            why = _try_open(driver_factory, dev, max(0.05, min(attempt_s, left)))
            if not why:
                break
            now = time.monotonic()
            if now >= deadline:
                waited = f" (waited {wait_s:g} s: [[device]] wait_for_device_s)" if wait_s else ""
                hint = "" if wait_s else "; set wait_for_device_s to wait for it"
                raise DeviceAbsentError(
                    f"{cfg.source}: [[device]] {dev.name!r}: {dev.url}: not there at start"
                    f"{waited}: {why}{hint}"
                )
            if wait_s and now >= next_report:
                say(
                    f"daq run: waiting for device {dev.name!r} at {dev.url} "
                    f"({deadline - now:.0f} s left of wait_for_device_s = {wait_s:g}): {why}"
                )
                next_report = now + WAIT_REPORT_S
            time.sleep(min(0.5, max(0.0, deadline - time.monotonic())))
