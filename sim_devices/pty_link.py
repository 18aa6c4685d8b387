"""Serial emulation over a pty pair: the driver opens a real device path, like a USB adapter.

The emulator keeps the master side; the slave's path (``/dev/pts/N``) is what a driver
opens with pyserial. A stable symlink (like ``/dev/serial/by-id/...``) can point at it so
that a driver finds the device again after the emulator restarts. The emulator also holds
the slave open, so the pty survives the driver closing and reopening it.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import tty
from pathlib import Path


class PtyLink:
    """One pty pair; ``path`` is the device path a driver opens."""

    def __init__(self, symlink: str | Path | None = None) -> None:
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd, termios.TCSANOW)
        tty.setraw(self.master_fd, termios.TCSANOW)
        os.set_blocking(self.master_fd, False)
        self.tty_path = os.ttyname(self.slave_fd)
        self.symlink = Path(symlink) if symlink else None
        if self.symlink is not None:
            with contextlib.suppress(FileNotFoundError):
                self.symlink.unlink()
            self.symlink.symlink_to(self.tty_path)
        self._closed = False

    @property
    def path(self) -> str:
        return str(self.symlink) if self.symlink is not None else self.tty_path

    def read(self, timeout_s: float, max_bytes: int = 65536) -> bytes:
        """Bytes the driver wrote, waiting up to ``timeout_s`` (b"" on timeout)."""
        if self._closed:
            return b""
        r, _, _ = select.select([self.master_fd], [], [], timeout_s)
        if not r:
            return b""
        try:
            return os.read(self.master_fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:  # EIO: no slave open at the moment
            return b""

    def write(self, data: bytes, timeout_s: float = 0.5) -> int:
        """Write all of ``data`` to the driver side (drops the rest after ``timeout_s``)."""
        view = memoryview(data)
        sent = 0
        while sent < len(view) and not self._closed:
            try:
                sent += os.write(self.master_fd, view[sent:])
            except BlockingIOError:
                _, w, _ = select.select([], [self.master_fd], [], timeout_s)
                if not w:
                    # nobody reads: flush what is queued so the line does not stall
                    with contextlib.suppress(termios.error):
                        termios.tcflush(self.master_fd, termios.TCIOFLUSH)
                    break
            except OSError:
                break
        return sent

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.symlink is not None:
            with contextlib.suppress(OSError):
                if self.symlink.is_symlink() and os.readlink(self.symlink) == self.tty_path:
                    self.symlink.unlink()
        for fd in (self.master_fd, self.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> PtyLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
