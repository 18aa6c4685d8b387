"""Bounded reading of the text inputs (CSV, TOML).

A campaign or sweep file is megabytes; a reader that takes whatever it is given hangs on
``/dev/zero`` and exhausts memory on a wrong file. Inputs are therefore read whole but
bounded: a device is refused at once, a regular file larger than the limit is refused
from its size, and a pipe is read up to the limit and refused beyond it.

The limit is :data:`MAX_TEXT_BYTES` (256 MiB; TOML files: :data:`MAX_TOML_BYTES`, 16
MiB); the environment variable ``GRATING_TWIN_MAX_INPUT_MB`` raises or lowers both.
"""

from __future__ import annotations

import os
import select
import stat
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

MAX_TEXT_BYTES = 256 * 1024 * 1024
MAX_TOML_BYTES = 16 * 1024 * 1024
LIMIT_VARIABLE = "GRATING_TWIN_MAX_INPUT_MB"


def input_limit(default: int) -> int:
    """The limit in bytes: ``default``, or ``GRATING_TWIN_MAX_INPUT_MB`` when set."""
    text = os.environ.get(LIMIT_VARIABLE, "").strip()
    if not text:
        return default
    try:
        mb = float(text)
    except ValueError:
        return default
    return int(mb * 1024 * 1024) if mb > 0 else default


def _mb(n: int) -> str:
    return f"{n / (1024 * 1024):g} MiB"


#: How long a named pipe may wait for its writer (s) before it is refused.
FIFO_WAIT_S = 10.0


def _open(path: str | Path, error: Callable[[str], Exception]) -> BinaryIO:
    """``open(path, "rb")``; a named pipe is opened without blocking and given
    :data:`FIFO_WAIT_S` for a writer to appear (or refused), so it never hangs."""
    try:
        is_fifo = stat.S_ISFIFO(os.stat(path).st_mode)
    except OSError:
        is_fifo = False
    if not is_fifo:
        return open(path, "rb")
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    # Linux reports POLLHUP on a pipe's read end only once a writer has come and gone:
    # before any writer, the poll waits, and its time-out is the bound
    poller = select.poll()
    poller.register(fd, select.POLLIN | select.POLLHUP)
    if not poller.poll(FIFO_WAIT_S * 1000):
        os.close(fd)
        raise error(f"{path}: a named pipe nobody wrote to within {FIFO_WAIT_S:g} s")
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def read_input_bytes(
    path: str | Path,
    *,
    limit: int = MAX_TEXT_BYTES,
    error: Callable[[str], Exception] = ValueError,
) -> bytes:
    """The bytes of ``path``, at most ``limit`` (else ``error`` naming the file and the
    limit). Missing, unreadable, a directory or a device: ``error`` naming the file."""
    source = str(path)
    limit = input_limit(limit)
    try:
        fh = _open(path, error)
    except IsADirectoryError:
        raise error(f"{source}: is a directory, expected a file") from None
    except OSError as exc:
        raise error(f"{source}: cannot read: {exc.strerror or exc}") from None
    with fh:
        mode = os.fstat(fh.fileno()).st_mode
        if stat.S_ISDIR(mode):
            raise error(f"{source}: is a directory, expected a file")
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
            raise error(f"{source}: is a device, not a file (an endless input is refused)")
        if stat.S_ISREG(mode):
            size = os.fstat(fh.fileno()).st_size
            if size > limit:
                raise error(
                    f"{source}: {_mb(size)} is larger than the input limit of {_mb(limit)} "
                    f"(set {LIMIT_VARIABLE} to raise it)"
                )
        try:
            data = fh.read(limit + 1)
        except OSError as exc:
            raise error(f"{source}: cannot read: {exc.strerror or exc}") from None
    if len(data) > limit:
        raise error(
            f"{source}: more than the input limit of {_mb(limit)} (set {LIMIT_VARIABLE} "
            "to raise it)"
        )
    return data
