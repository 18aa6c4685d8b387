"""The emulated laser tracker: ASCII command/response and streaming over TCP and serial.

One protocol (docs/protocols.md, "Laser tracker") served on a TCP port of 127.0.0.1 and on
a pty. Commands end in LF (CR LF accepted); every reply line ends in CR LF. It answers
``*IDN?`` as SCPI instruments do. Measurements are in the tracker's own frame, mm.

Each connection is a session with its own streaming state; the beam (breaks, restores)
and the device clock belong to the instrument and are shared by all sessions.

Streaming evaluates the plant ahead: the lines of the next ~0.1 s of samples are measured
and formatted in one vectorized call and written when their instant has passed (a plant
call costs ~1 ms whatever its size up to ~100 samples).
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import struct
import threading
from collections import Counter
from typing import Protocol

import numpy as np

from edges.errors import DeviceError
from sim_devices.config import EffectsSection, TrackerSection
from sim_devices.plant import DeviceClock, Plant
from sim_devices.pty_link import PtyLink
from sim_devices.tracker_view import cell_geometry, true_view_codes

log = logging.getLogger(__name__)

IDN = "EMULATED,LT500-SIM,{serial},1.0"
MAX_RATE_HZ = 1000.0
ERRORS = {
    -100: "Command error",
    -113: "Undefined header",
    -222: "Data out of range",
    -350: "Queue overflow",
}


class Port(Protocol):
    def read(self, timeout_s: float, max_bytes: int = 65536) -> bytes: ...
    def write(self, data: bytes, timeout_s: float = 0.5) -> int: ...


class PortClosed(DeviceError):
    """The peer went away."""


class SocketPort:
    """A connected TCP socket with the pty link's read/write interface."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(None)

    def read(self, timeout_s: float, max_bytes: int = 65536) -> bytes:
        import select

        r, _, _ = select.select([self.sock], [], [], timeout_s)
        if not r:
            return b""
        try:
            data = self.sock.recv(max_bytes)
        except OSError as exc:
            raise PortClosed(str(exc)) from exc
        if not data:
            raise PortClosed("peer closed")
        return data

    def write(self, data: bytes, timeout_s: float = 0.5) -> int:
        try:
            self.sock.settimeout(timeout_s)
            self.sock.sendall(data)
        except TimeoutError:
            return 0
        except OSError as exc:
            raise PortClosed(str(exc)) from exc
        return len(data)

    def reset(self) -> None:
        """Abort the connection with a TCP RST (fault injection)."""
        with contextlib.suppress(OSError):
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        with contextlib.suppress(OSError):
            self.sock.close()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


class TrackerInstrument:
    """State shared by all sessions: plant, clock, beam, weather, noise model."""

    def __init__(self, plant: Plant, config: TrackerSection, effects: EffectsSection) -> None:
        self.plant = plant
        self.config = config
        self.effects = effects
        self.clock = DeviceClock(ppm=config.clock_ppm)
        self.model = plant.cell.tracker
        self.serial = f"SN{plant.cell.seed:05d}"
        self.rng = np.random.default_rng(plant.cell.seed + 21)
        self.lock = threading.Lock()
        self.stats: Counter[str] = Counter()
        self._breaks = self._beam_breaks(3600.0 * 24)
        self.geometry = cell_geometry(plant.cell, plant.config.geometry)

    def _beam_breaks(self, horizon_s: float) -> np.ndarray:
        """(K, 2) wall-time intervals of obstructed beam (Poisson arrivals)."""
        rate = self.config.beam_breaks_per_min / 60.0
        if rate <= 0:
            return np.empty((0, 2))
        rng = np.random.default_rng(self.plant.cell.seed + 22)
        n = int(rate * horizon_s * 1.2) + 10
        starts = np.cumsum(rng.exponential(1.0 / rate, n))
        starts = starts[starts < horizon_s]
        return np.stack([starts, starts + self.config.beam_break_duration_s], axis=1)

    def beam_broken(self, wall_s: np.ndarray) -> np.ndarray:
        if self._breaks.shape[0] == 0:
            return np.zeros(np.shape(wall_s), bool)
        i = np.searchsorted(self._breaks[:, 0], wall_s, side="right") - 1
        ok = i >= 0
        out = np.zeros(np.shape(wall_s), bool)
        out[ok] = wall_s[ok] < self._breaks[i[ok], 1]
        return out

    def temperature_c(self, wall_s: np.ndarray | float) -> np.ndarray:
        drift = self.effects.tracker_temperature_drift_k_per_h
        return self.config.temperature_c + drift * np.asarray(wall_s) / 3600.0

    def measure(self, wall_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measured points ``(N, 3)`` mm and status codes ``(N,)`` at wall times ``(N,)``."""
        state = self.plant.joint_state(self.plant.clock.sim_s(wall_s))
        truth = self.plant.target_mm(state.q_out_rad, wall_s)  # target and drift at each sample
        ppm = self.effects.tracker_scale_ppm_per_k * (
            self.temperature_c(wall_s) - self.config.temperature_c
        )
        truth = truth * (1.0 + 1e-6 * np.asarray(ppm))[..., None]
        with self.lock:
            pts, ok = self.model.measure(truth, self.rng)
        status = np.where(ok, 0, 2).astype(np.int8)  # 2: dropout (per measurement)
        if self.config.line_of_sight:  # the reflector out of view: obstructed
            tcp = self.plant.tcp_target(np.asarray(wall_s), len(pts))
            hidden = np.zeros(len(pts), dtype=bool)
            hidden[tcp] = true_view_codes(self.plant.cell, self.geometry, state.q_out_rad[tcp]) != 0
            status[hidden] = 1
            pts[hidden] = np.nan
        # the reflector out of view (a program move without a target) or the beam broken
        broken = self.beam_broken(np.asarray(wall_s)) | self.plant.hidden_target(
            np.asarray(wall_s), len(pts)
        )
        status[broken] = 1  # 1: obstructed
        pts[broken] = np.nan
        return pts, status


STATUS_TEXT = {0: "OK", 1: "BROKEN_OBSTRUCTED", 2: "BROKEN_DROPOUT"}


class TrackerSession:
    """One connection: parse commands, answer them, stream measurements."""

    def __init__(self, inst: TrackerInstrument, port: Port, name: str) -> None:
        self.inst = inst
        self.port = port
        self.name = name
        self.rate_hz = 100.0
        self.streaming = False
        self.seq = 0
        self.next_k = 0
        self.period_us = 1e6 / self.rate_hz
        self.last_error = (0, "No error")
        self.rx = b""
        self.was_broken = False  # beam state of the last line written
        self.stop = threading.Event()
        # lines computed ahead: sample k0 + i is self._ahead[i] (with its EV line, if any)
        self._ahead_k0 = 0
        self._ahead: list[str] = []
        self._ahead_broken: list[bool] = []

    def run(self) -> None:
        clock = self.inst.plant.clock
        try:
            while not self.stop.is_set():
                data = self.port.read(0.004)
                if data:
                    self.rx += data
                    if len(self.rx) > 4096 and b"\n" not in self.rx:
                        self.rx = b""
                        self._error(-350)
                    while b"\n" in self.rx:
                        line, self.rx = self.rx.split(b"\n", 1)
                        reply = self.command(line.decode("ascii", "replace").strip())
                        if reply:
                            self.port.write(reply.encode() + b"\r\n")
                self._stream(clock.wall_s())
        except (PortClosed, OSError, ValueError):
            pass  # peer gone or connection reset by the fault injector
        finally:
            self.inst.stats["sessions_closed"] += 1

    def _error(self, code: int, detail: str = "") -> str:
        detail = "".join(c if c.isprintable() and c != "," else "?" for c in detail)[:40]
        text = ERRORS.get(code, "Error") + (f"; {detail}" if detail else "")
        self.last_error = (code, text)
        self.inst.stats["command_errors"] += 1
        return f"ERR,{code},{text}"

    def _now_us(self) -> int:
        return int(self.inst.clock.device_us(self.inst.plant.clock.wall_s()))

    def command(self, line: str) -> str:
        """The reply to one command ``line`` ("" to an empty line). Long because it is
        the protocol's dispatcher: one flat branch per command, like the manual's table;
        a split would add a call to every request (``MEAS:POINT?`` polls)."""
        if not line:
            return ""
        self.inst.stats["commands"] += 1
        head, _, arg = line.partition(" ")
        head = head.upper()
        arg = arg.strip()
        if head == "*IDN?":
            return IDN.format(serial=self.inst.serial)
        if head in ("*RST", "*CLS"):
            self.streaming = False
            if head == "*RST":
                self.rate_hz = 100.0
            self.last_error = (0, "No error")
            return "OK"
        if head == "SYST:ERR?":
            code, text = self.last_error
            self.last_error = (0, "No error")
            return f"ERR,{code},{text}"
        if head == "STREAM:RATE":
            try:
                rate = float(arg)
            except ValueError:
                return self._error(-100, f"bad number {arg!r}")
            if not (0.1 <= rate <= MAX_RATE_HZ) or not math.isfinite(rate):
                return self._error(-222, f"rate must be 0.1..{MAX_RATE_HZ:g} Hz")
            self.rate_hz = rate
            self.period_us = 1e6 / rate
            self._ahead = []
            return "OK"
        if head == "STREAM:RATE?":
            return f"RATE,{self.rate_hz:g}"
        if head == "STREAM:START":
            if not self.streaming:
                self.streaming = True
                now_us = self._now_us() - self.inst.clock.start_us
                self.next_k = int(now_us // self.period_us) + 1
                self._ahead = []
            return "OK"
        if head == "STREAM:STOP":
            self.streaming = False
            return "OK"
        if head == "MEAS:POINT?":
            n = 10
            if arg:
                try:
                    n = int(arg)
                except ValueError:
                    return self._error(-100, f"bad count {arg!r}")
                if not 1 <= n <= 1000:
                    return self._error(-222, "averaging count must be 1..1000")
            return self._point(n)
        if head == "WEATHER?":
            wall = self.inst.plant.clock.wall_s()
            t = float(self.inst.temperature_c(wall))
            return (
                f"WX,{self._now_us()},{t:.3f},{self.inst.config.pressure_hpa:.2f},"
                f"{self.inst.config.humidity_pct:.1f}"
            )
        if head == "STATUS?":
            wall = self.inst.plant.clock.wall_s()
            broken = bool(self.inst.beam_broken(np.array([wall]))[0])
            beam = "BROKEN_OBSTRUCTED" if broken else "LOCKED"
            return (
                f"ST,READY,{beam},{int(self.streaming)},{self.rate_hz:g},"
                f"{self.inst.clock.boot_count}"
            )
        return self._error(-113, head)

    def _point(self, n: int) -> str:
        step = 1.0 / self.inst.config.internal_rate_hz
        wall_now = self.inst.plant.clock.wall_s()
        walls = wall_now - step * np.arange(n)[::-1]
        pts, status = self.inst.measure(walls)
        good = status == 0
        t_us = self._now_us()
        if not np.any(good):
            code = int(status[-1])
            return f"PT,{t_us},NaN,NaN,NaN,{STATUS_TEXT[code]},0"
        mean = pts[good].mean(axis=0)
        return f"PT,{t_us},{mean[0]:.4f},{mean[1]:.4f},{mean[2]:.4f},OK,{int(good.sum())}"

    LOOKAHEAD_S = 0.1

    def _compute_ahead(self, n: int) -> None:
        """Measure and format the ``n`` samples from ``next_k`` (not due yet)."""
        clock = self.inst.clock
        k = np.arange(self.next_k, self.next_k + n)
        t_dev = clock.start_us + k * self.period_us
        pts, status = self.inst.measure(clock.wall_of(t_dev))
        t_int = np.rint(t_dev).astype(np.int64).tolist()
        xyz = pts.tolist()
        codes = status.tolist()
        lines: list[str] = []
        broken_list: list[bool] = []
        was = self.was_broken
        seq = self.seq
        for i in range(n):
            code = codes[i]
            broken = code == 1
            ev = ""
            if broken != was:
                was = broken
                if broken:
                    ev = f"EV,BEAM_BROKEN,{t_int[i]},OBSTRUCTED\r\n"
                else:
                    ev = f"EV,BEAM_RESTORED,{t_int[i]}\r\n"
            x, y, z = xyz[i]
            lines.append(
                f"{ev}D,{seq + i},{t_int[i]},{x:.4f},{y:.4f},{z:.4f},{STATUS_TEXT[code]}\r\n"
            )
            broken_list.append(broken)
        self._ahead_k0 = self.next_k
        self._ahead = lines
        self._ahead_broken = broken_list

    def _stream(self, wall: float) -> None:
        if not self.streaming:
            return
        clock = self.inst.clock
        dev_now = float(clock.device_us(wall))
        k_end = int((dev_now - clock.start_us) // self.period_us) + 1
        n = min(k_end - self.next_k, 2000)
        if n <= 0:
            return
        block = max(8, int(self.rate_hz * self.LOOKAHEAD_S))
        out: list[str] = []
        left = n
        while left > 0:
            off = self.next_k - self._ahead_k0
            if not 0 <= off < len(self._ahead):
                self._compute_ahead(max(block, left))
                off = 0
            m = min(left, len(self._ahead) - off)
            out += self._ahead[off : off + m]
            self.was_broken = self._ahead_broken[off + m - 1]
            self.next_k += m
            self.seq += m
            left -= m
        self.port.write("".join(out).encode())
        self.inst.stats["samples"] += n


class TrackerServer:
    """Serves the instrument on TCP 127.0.0.1 and, optionally, on a pty."""

    def __init__(
        self, inst: TrackerInstrument, *, tcp_port: int = 0, pty: PtyLink | None = None
    ) -> None:
        self.inst = inst
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", tcp_port))
        self.sock.listen(4)
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.pty = pty
        self.sessions: list[tuple[TrackerSession, SocketPort | None]] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._reset_done = False

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def start(self) -> TrackerServer:
        t = threading.Thread(target=self._accept_loop, name="tracker-accept", daemon=True)
        t.start()
        self._threads.append(t)
        if self.pty is not None:
            s = TrackerSession(self.inst, self.pty, "serial")
            self.sessions.append((s, None))
            t2 = threading.Thread(target=s.run, name="tracker-serial", daemon=True)
            t2.start()
            self._threads.append(t2)
        return self

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            self._maybe_reset()
            try:
                conn, _addr = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            port = SocketPort(conn)
            s = TrackerSession(self.inst, port, "tcp")
            self.sessions.append((s, port))
            self.inst.stats["connections"] += 1
            t = threading.Thread(target=s.run, name="tracker-tcp", daemon=True)
            t.start()
            self._threads.append(t)

    def _maybe_reset(self) -> None:
        at = self.inst.config.reset_after_s
        if self._reset_done or at < 0 or self.inst.plant.clock.wall_s() < at:
            return
        self._reset_done = True
        self.reset_connections()

    def reset_connections(self) -> None:
        """Fault: abort every TCP session with a reset (RST), mid-stream."""
        for s, port in list(self.sessions):
            if port is not None:
                s.stop.set()
                port.reset()
                self.inst.stats["fault_resets"] += 1

    def stop(self) -> None:
        self._stop.set()
        for s, port in self.sessions:
            s.stop.set()
            if port is not None:
                port.close()
        with contextlib.suppress(OSError):
            self.sock.close()
        for t in self._threads:
            t.join(timeout=1.0)
