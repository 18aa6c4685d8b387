"""The one URL opener for byte streams: every driver opens its port through here.

A thin layer over :func:`serial.serial_for_url` (pyserial's URL handlers), so one driver
works unchanged on a real serial port (``/dev/ttyUSB0``), a pty path given by an emulator,
a TCP device (``socket://127.0.0.1:5025``) and pyserial's in-memory ``loop://``.

Drivers never build sockets themselves: a TCP instrument is a ``socket://`` URL.
"""

from __future__ import annotations

import os
import urllib.parse
from typing import Any

import serial

from drivers.errors import DeviceIOError, DriverConfigError

#: URL schemes accepted by :func:`open_stream` (besides plain device paths).
SCHEMES: dict[str, str] = {
    "socket": "TCP stream, socket://HOST:PORT (pyserial protocol_socket)",
    "loop": "in-memory loopback, loop:// (tests only; ~7k frames/s, set write_timeout)",
    "spy": "hexdump wrapper around another URL, spy://PORT?file=...",
    "rfc2217": "serial port server, rfc2217://HOST:PORT",
}


def url_scheme(url: str) -> str:
    """The scheme of ``url``, or ``""`` for a plain device path."""
    if "://" not in url:
        return ""
    return urllib.parse.urlsplit(url).scheme


def check_url(url: str) -> str:
    """Validate ``url`` against :data:`SCHEMES`; plain paths must be absolute."""
    if not isinstance(url, str) or not url:
        raise DriverConfigError(f"port URL must be a non-empty string, got {url!r}")
    scheme = url_scheme(url)
    if scheme and scheme not in SCHEMES:
        raise DriverConfigError(
            f"unknown URL scheme {scheme!r} in {url!r} "
            f"(allowed: {', '.join(sorted(SCHEMES))}, or a device path like /dev/ttyUSB0)"
        )
    if not scheme and not os.path.isabs(url):
        raise DriverConfigError(f"device path must be absolute, got {url!r}")
    return scheme


def open_stream(
    url: str,
    *,
    timeout_s: float = 0.01,
    write_timeout_s: float = 1.0,
    baudrate: int = 115200,
    **serial_kwargs: Any,
) -> serial.SerialBase:
    """Open ``url`` and return a pyserial port object (``read``/``write``/``close``).

    ``timeout_s`` is the read timeout (``read(n)`` returns what arrived by then);
    ``write_timeout_s`` bounds writes (``loop://`` would otherwise block forever on
    writes over 4 KiB with no reader). Failure raises :class:`DeviceIOError`.
    """
    check_url(url)
    try:
        return serial.serial_for_url(
            url,
            timeout=timeout_s,
            write_timeout=write_timeout_s,
            baudrate=baudrate,
            **serial_kwargs,
        )
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceIOError(f"cannot open {url}: {exc}") from exc
