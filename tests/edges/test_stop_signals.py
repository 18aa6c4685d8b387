"""SIGINT/SIGTERM stop a process whose main thread waits on its stop event, every time
(edges/stop_signals.py: the event is set in a thread, never in the handler, which could
deadlock on the event's own lock: a `daq run` hung on SIGTERM that way in CI)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

SCRIPT = """
import threading
from edges.stop_signals import on_stop_signals
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


FORK_SCRIPT = """
import multiprocessing, os, signal, threading, time
from edges.stop_signals import on_stop_signals

parent_stop = threading.Event()
on_stop_signals(parent_stop.set)

def child(go, done):
    go.recv()  # SIGTERM'd once before it registers: the signal must not reach the parent
    stop = threading.Event()
    on_stop_signals(stop.set, (signal.SIGTERM,))
    done.send("registered")
    done.send("stopped" if stop.wait(10) else "timeout")

ctx = multiprocessing.get_context("fork")
go_r, go_w = ctx.Pipe(duplex=False)
done_r, done_w = ctx.Pipe(duplex=False)
proc = ctx.Process(target=child, args=(go_r, done_w))
proc.start()
time.sleep(0.2)
os.kill(proc.pid, signal.SIGTERM)
time.sleep(0.3)
print("parent stopped by the child's signal" if parent_stop.is_set() else "parent running")
go_w.send("go")
assert done_r.recv() == "registered"
os.kill(proc.pid, signal.SIGTERM)
print("child " + done_r.recv(), flush=True)
proc.join(10)
print(f"child exit {proc.exitcode}", flush=True)
"""


def test_a_forked_child_takes_its_own_signals_not_the_parents() -> None:
    """sim-cell forks its device processes after registering: a child's SIGTERM before it
    registers is ignored, not carried over the parent's wakeup socket to the parent's
    watcher; once registered, the child's own action runs."""
    out = subprocess.run(
        [sys.executable, "-c", FORK_SCRIPT], capture_output=True, text=True, timeout=30
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:3] == ["parent running", "child stopped", "child exit 0"]
