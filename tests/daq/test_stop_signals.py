"""SIGINT/SIGTERM stop a process whose main thread waits on its stop event, every time
(daq/stop_signals.py: the event is set in a thread, never in the handler, which could
deadlock on the event's own lock: a `daq run` hung on SIGTERM that way in CI)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

SCRIPT = """
import threading
from daq.stop_signals import on_stop_signals
stop = threading.Event()
on_stop_signals(stop.set)
print("ready", flush=True)
while not stop.wait(1e-4):  # the main thread in Event.wait's locked section most of the time
    pass
print("stopped", flush=True)
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_a_main_thread_waiting_on_its_event(sig: signal.Signals) -> None:
    for _ in range(5):
        p = subprocess.Popen(
            [sys.executable, "-c", SCRIPT],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert p.stdout is not None
        assert p.stdout.readline().strip() == "ready"
        time.sleep(0.05)
        p.send_signal(sig)
        try:
            out, err = p.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            raise
        assert p.returncode == 0, err
        assert out.strip() == "stopped"
