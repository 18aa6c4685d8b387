"""The one URL opener for byte streams: every driver opens its port through here.

A thin layer over :func:`serial.serial_for_url` (pyserial's URL handlers), so one driver
works unchanged on a real serial port (``/dev/ttyUSB0``), a pty path given by an emulator,
a TCP device (``socket://127.0.0.1:5025``) and pyserial's in-memory ``loop://``.

Drivers never build sockets themselves: a TCP instrument is a ``socket://`` URL.
"""

from __future__ import annotations

import os
import select
import time
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


# -- event-driven I/O on the port's file descriptor -------------------------------------------
# pyserial opens device paths and socket:// non-blocking; its read(n) waits for n bytes or
# the whole timeout and writes wait for writability after every write. The helpers below
# return as soon as something has arrived (one select and one read), for ports that have a
# file descriptor; callers fall back to pyserial's read/write for the others (loop://).


def stream_fileno(port: serial.SerialBase) -> int | None:
    """The port's file descriptor, if it has a usable one (serial device, pty, socket://)."""
    try:
        fd = port.fileno()
    except Exception:  # loop:// and friends have none
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


def read_available(fd: int, timeout_s: float, max_bytes: int = 65536) -> bytes:
    """What has arrived on ``fd``, waiting up to ``timeout_s`` for the first bytes.

    Returns b"" on timeout; raises OSError when the other side is gone (readable but
    nothing to read: a closed socket, a tty whose device went away).
    """
    readable = False
    deadline = None
    while True:
        try:
            chunk = os.read(fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            chunk = None
        if chunk:
            return chunk
        if chunk is not None and readable:
            raise OSError("device reports readiness to read but returned no data")
        if deadline is None:
            deadline = time.monotonic() + timeout_s
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            return b""
        readable = True


def drain(fd: int) -> int:
    """Discard what is waiting on ``fd``; the number of bytes dropped."""
    n = 0
    while True:
        try:
            chunk = os.read(fd, 65536)
        except (BlockingIOError, InterruptedError):
            return n
        if not chunk:  # a tty with VMIN=0: nothing there (a closed socket: next read)
            return n
        n += len(chunk)


def write_all(fd: int, data: bytes, timeout_s: float) -> None:
    """Write all of ``data`` to the non-blocking ``fd``; OSError after ``timeout_s``."""
    view = memoryview(data)
    deadline = time.monotonic() + timeout_s
    while view:
        try:
            view = view[os.write(fd, view) :]
            continue
        except (BlockingIOError, InterruptedError):
            pass
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([], [fd], [], left)[1]:
            raise OSError("write timeout")
