"""The emulated default cell for ``daq run`` without ``--config``.

Spawns ``sim-cell serve`` (the emulator's public command line, one process per device
kind) as a child process, reads the JSON line it prints per device (kind, protocol, path
or URL, ids) and turns them into a daemon configuration document: the grating box on its
pty (Modbus RTU), the laser tracker on its TCP port (the serial twin of the same
instrument is not used), the motor encoders over socketcand (CANopen). The child is
stopped with SIGTERM on :meth:`EmulatedCell.close`.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any

from daq.errors import DaqError

START_TIMEOUT_S = 60.0
BURST_GAP_S = 0.5  # sim-cell prints all device lines in one burst


class EmulatedCell:
    """``sim-cell serve`` as a child process; :meth:`start` returns a config document."""

    def __init__(
        self,
        sim_config: str | None = None,
        *,
        cell: str = "emulated",
        robot: str = "robot1",
        listen: str = "tcp/127.0.0.1:7447",
        rate_hz: float = 1000.0,
    ) -> None:
        self.sim_config = sim_config
        self.cell = cell
        self.robot = robot
        self.listen = listen
        self.rate_hz = rate_hz
        self.proc: subprocess.Popen[str] | None = None
        self._stderr: Any = None  # the cell's stderr (a temporary file)
        self.records: list[dict[str, Any]] = []
        self.devices: list[dict[str, Any]] = []
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._closed = False

    def _command(self) -> list[str]:
        exe = shutil.which("sim-cell", path=os.path.dirname(sys.executable)) or shutil.which(
            "sim-cell"
        )
        cmd = [exe] if exe else [sys.executable, "-c", "from sim_devices.cli import main; main()"]
        cmd.append("serve")
        if self.sim_config:
            cmd += ["--config", self.sim_config]
        return cmd

    def _pump(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def start(self) -> dict[str, Any]:
        # stderr to a file, not a pipe: nobody drains it while the cell runs, and its last
        # line is the reason when the cell could not start
        self._stderr = tempfile.TemporaryFile(mode="w+", prefix="sim-cell-")  # noqa: SIM115 - closed in close()
        self.proc = subprocess.Popen(
            self._command(), stdout=subprocess.PIPE, stderr=self._stderr, text=True
        )
        threading.Thread(target=self._pump, name="sim-cell-stdout", daemon=True).start()
        deadline = time.monotonic() + START_TIMEOUT_S
        try:
            while True:
                timeout = deadline - time.monotonic() if not self.records else BURST_GAP_S
                try:
                    line = self._lines.get(timeout=max(0.01, timeout))
                except queue.Empty:
                    if self.records:
                        break
                    raise DaqError("sim-cell serve printed no device in time") from None
                if line is None:
                    if self.records:
                        break
                    raise DaqError(
                        f"sim-cell serve exited ({self._exit_status()}) before starting"
                        + self._last_error()
                    )
                line = line.strip()
                if line.startswith("{"):
                    self.records.append(json.loads(line))
        except BaseException:
            self.close()
            raise
        return self.document()

    def _exit_status(self) -> int | None:
        """The cell's exit status: its stdout closed, so it is ending (a second at most)."""
        assert self.proc is not None
        try:
            return self.proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return None

    def _last_error(self) -> str:
        """``: <the cell's last stderr line>`` (empty when it said nothing)."""
        try:
            self._stderr.seek(0)
            lines = [ln.strip() for ln in self._stderr.read().splitlines() if ln.strip()]
        except (OSError, ValueError):
            return ""
        return f": {lines[-1]}" if lines else ""

    @property
    def t0_monotonic_ns(self) -> int | None:
        """The emulator's truth-clock origin (host CLOCK_MONOTONIC ns), as it printed."""
        return next(
            (int(r["t0_monotonic_ns"]) for r in self.records if "t0_monotonic_ns" in r), None
        )

    def document(self) -> dict[str, Any]:
        """A daemon configuration document (as from TOML) for the printed devices."""
        devices: list[dict[str, Any]] = []
        for r in self.records:
            kind, proto = r.get("kind"), r.get("protocol")
            if kind == "grating_reader":
                devices.append(
                    {
                        "name": "grating",
                        "driver": r.get("driver", "grating_modbus"),
                        "url": r["path"],
                        "rate_hz": float(r.get("rate_hz", self.rate_hz)),
                        "joints": [1, 2, 3, 4, 5, 6],
                        "options": {"unit_id": int(r.get("unit_id", 1))},
                    }
                )
            elif kind == "laser_tracker" and proto == "ascii-tcp":
                devices.append(
                    {
                        "name": "tracker",
                        "driver": r.get("driver", "tracker_ascii"),
                        "url": r["url"],
                        "rate_hz": self.rate_hz,
                        "options": {"rate_hz": self.rate_hz, "poll_s": 0.001},
                        "foxglove": "points",
                    }
                )
            elif kind == "motor_encoders":
                devices.append(
                    {
                        "name": "encoders",
                        "driver": r.get("driver", "encoder_canopen"),
                        "url": r["url"],
                        "rate_hz": self.rate_hz,
                        "joints": list(range(1, len(r.get("node_ids", [])) + 1)),
                        "options": {
                            "node_ids": list(r.get("node_ids", [])),
                            "sync_hz": self.rate_hz,
                        },
                    }
                )
        self.devices = devices
        return {
            "cell": {"name": self.cell, "robot": self.robot},
            "zenoh": {"listen": [self.listen]},
            "device": devices,
        }

    def close(self) -> None:
        """Stop the emulator (SIGTERM, then SIGKILL); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self._stderr is not None:
            self._stderr.close()
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)

    def __enter__(self) -> EmulatedCell:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
