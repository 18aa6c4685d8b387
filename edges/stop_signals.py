"""Stopping a process on SIGINT/SIGTERM without taking a lock in the signal handler.

A Python signal handler runs in the main thread between two bytecodes, possibly while
that thread holds the very lock the handler wants: ``threading.Event.set()`` from a
handler deadlocks when the signal lands inside ``Event.wait``'s own locked section. A
``daq run`` hung on SIGTERM that way in CI (its main thread waits on the stop event
between health rounds; gdb showed the handler blocked on the event's lock for 17 min).
Here the Python handler does nothing: the interpreter writes the signal's number to a
socket (``signal.set_wakeup_fd``) and a thread of its own runs the actions, taking
locks as any thread may.

A forked child (``sim-cell``'s device processes) starts clean: no actions, a lock of its
own, no wakeup socket (the parent's would carry the child's signals to the parent's
watcher), its signals ignored until it calls :func:`on_stop_signals` itself.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import threading
from collections.abc import Callable, Iterable
from types import FrameType

_lock = threading.Lock()
_actions: list[tuple[frozenset[int], Callable[[], object]]] = []
_watching_pid: int | None = None  # the process whose watcher runs (a fork must start its own)


def _after_fork_in_child() -> None:
    """The child forgets the parent's watcher: it has no thread, and its socket is the
    parent's."""
    global _lock, _watching_pid
    _lock = threading.Lock()  # the parent's watcher may have held it at the fork
    _actions.clear()
    if _watching_pid is not None:
        _watching_pid = None
        with contextlib.suppress(ValueError):  # only the main thread may (fork from another)
            signal.set_wakeup_fd(-1)


os.register_at_fork(after_in_child=_after_fork_in_child)


def on_stop_signals(
    action: Callable[[], object],
    signals: Iterable[signal.Signals] = (signal.SIGINT, signal.SIGTERM),
) -> None:
    """Run ``action()`` in a watcher thread each time one of ``signals`` arrives (the
    signal's default, such as KeyboardInterrupt, no longer happens). Call from the main
    thread: only it may set signal handlers."""
    global _watching_pid
    nums = frozenset(int(s) for s in signals)
    with _lock:
        if _watching_pid != os.getpid():
            _actions.clear()
            receive, send = socket.socketpair()
            send.setblocking(False)
            signal.set_wakeup_fd(send.fileno(), warn_on_full_buffer=False)
            watcher = threading.Thread(
                target=_watch, args=(receive, send), name="stop-signals", daemon=True
            )
            watcher.start()
            _watching_pid = os.getpid()
        _actions.append((nums, action))
    for s in nums:
        signal.signal(s, _written_to_the_socket)


def _written_to_the_socket(signum: int, frame: FrameType | None) -> None:
    """The Python handler: nothing (the interpreter wrote ``signum`` to the wakeup fd)."""


def _watch(receive: socket.socket, send: socket.socket) -> None:
    """Run the actions of each signal number read (``send`` is held so it stays open)."""
    while True:
        data = receive.recv(64)
        if not data:
            return
        with _lock:
            actions = list(_actions)
        for signum in data:
            for nums, action in actions:
                if signum in nums:
                    action()
