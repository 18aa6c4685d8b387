"""The web page: viser's scene and panel, fed from a sample source at a fixed frame rate.

:class:`TwinView` owns a :class:`viser.ViserServer` (it serves its own bundled client:
nothing is fetched from the internet) bound to 127.0.0.1 by default. Its update loop asks
the source for the latest :class:`~view.sources.Snapshot` every ``1 / fps`` seconds and
sets the scene's nodes in one atomic message group: however fast the stream, the page
gets at most ``fps`` updates a second and always the newest sample (the samples between
two frames are never queued). The panel's text (status, phase, rate) changes at
``panel_hz``, since re-rendering markdown in the browser costs more than moving nodes.

Scene units are metres (the twin's mm / 1000), z up, in the tracker frame.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from view.model import TwinModel
from view.scene import (
    MAGNIFICATIONS,
    ArmGeometry,
    arm_geometry,
    camera_pose,
    error_segments,
    magnified,
)
from view.sources import LiveSource, ReplaySource, Snapshot

if TYPE_CHECKING:
    from viser import GuiEvent, ViserServer

M_PER_MM = 1e-3
ARM_RGB = (235, 125, 35)
GHOST_RGB = (150, 150, 160)
TCP_RGB = (220, 30, 30)
TRACKER_RGB = (20, 160, 70)
ERROR_RGB = (190, 20, 170)
SPEEDS = ("0.1", "0.25", "1", "4", "16", "64")
#: the ghost's deviation from the drawn model, drawn this many times larger (nominal and
#: calibrated geometry differ by about a millimetre at the TCP: ×100 is a hand's width)
GHOST_MAGNIFY = 100.0


@dataclass
class FrameStats:
    """Scene updates sent: total, and the rate over the last second (frames/s)."""

    frames: int = 0
    rate_hz: float = 0.0
    update_ms_p50: float = 0.0  # time to compute and send one scene update
    update_ms_p99: float = 0.0
    #: live: host UTC when the frame was sent minus when the twin published the drawn
    #: sample (ms): how far the page is behind the twin
    age_ms_p50: float | None = None
    age_ms_p99: float | None = None


def _quiet_stdout() -> contextlib.AbstractContextManager[object]:
    # viser prints a banner and "Server stopped" on stdout; the command prints its own line
    return contextlib.redirect_stdout(io.StringIO())


def _wxyz(rotations: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternions ``(k, 4)`` (w, x, y, z) of rotation matrices ``(k, 3, 3)``."""
    import viser.transforms as vtf

    return np.asarray(vtf.SO3.from_matrix(rotations).wxyz).reshape(-1, 4)


def _markdown_table(table: str) -> str:
    """The twin's fixed-width stage table (``stage_table``) as a markdown table."""
    lines = [ln for ln in table.splitlines() if ln.strip()]
    if not lines:
        return ""
    head = lines[0].split()
    set_name = head[1] if len(head) > 1 else "validate"
    out = [f"| stage | {set_name} mean AP mm | max mm |", "|---|---:|---:|"]
    for ln in lines[1:]:
        parts = ln.rsplit(None, 3)
        if len(parts) == 4:
            out.append(f"| {parts[0].strip()} | {parts[1]} | {parts[2]} |")
    return "\n".join(out)


class TwinView:
    """The twin's page. ``start()`` serves it and returns the URL; ``run()`` updates it."""

    def __init__(
        self,
        source: ReplaySource | LiveSource,
        twin: TwinModel,
        *,
        title: str,
        host: str = "127.0.0.1",
        port: int = 8080,
        fps: float = 40.0,
        panel_hz: float = 5.0,
        magnify: float = 100.0,
    ) -> None:
        self.source = source
        self.twin = twin
        self.title = title
        self.host = host
        self.port = port
        self.fps = fps
        self.panel_period_s = 1.0 / panel_hz
        self.factor = float(magnify)
        self.stats = FrameStats()
        self._stopped = threading.Event()
        self._server: Any = None  # viser.ViserServer once started (viser loads on start)
        # a replay's controls (viser's handles; their value setters are untyped)
        self._slider: Any = None
        self._play_button: Any = None
        self._kin = twin.kinematics
        self._frame_times: deque[float] = deque(maxlen=4096)
        self._update_ms: deque[float] = deque(maxlen=4096)
        self._age_ms: deque[float] = deque(maxlen=4096)

    # -- set-up ------------------------------------------------------------------------------
    def start(self) -> str:
        """Serve the page; the URL it is served at (the port viser bound)."""
        import viser

        # a browser that goes away mid-handshake makes the websockets library log a
        # traceback; for a page server that is an ordinary disconnect
        logging.getLogger("websockets.server").setLevel(logging.CRITICAL)
        with _quiet_stdout():
            server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
        self._server = server
        server.gui.configure_theme(control_width="large", show_logo=False, show_share_button=False)
        server.gui.main_panel.dock_right()
        home = arm_geometry(self._kin, self.twin.description.home)
        self._build_scene(server, home)
        self._build_panel(server)
        return f"http://{self.host}:{server.get_port()}/"

    def _build_scene(self, server: ViserServer, home: ArmGeometry) -> None:
        s = server.scene
        base = home.frames[0, :3, 3] * M_PER_MM
        s.add_grid("/floor", 6.0, 6.0, cell_size=0.25, section_size=1.0, position=base)
        self._links = s.add_line_segments(
            "/arm/links", home.segments * M_PER_MM, ARM_RGB, thickness=0.07
        )
        self._frames = s.add_batched_axes(
            "/arm/frames",
            _wxyz(home.frames[:, :3, :3]),
            home.frames[:, :3, 3] * M_PER_MM,
            axes_length=0.22,
            axes_radius=0.012,
        )
        self._ghost = None
        if self.twin.ghost is not None:
            self._ghost = s.add_line_segments(
                "/arm/ghost", home.segments * M_PER_MM, GHOST_RGB, thickness=0.02
            )
        self._tcp = s.add_icosphere(
            "/twin/tcp", radius=0.04, color=TCP_RGB, position=home.polyline[-1] * M_PER_MM
        )
        self._tracker = s.add_icosphere(
            "/tracker/latest", radius=0.03, color=TRACKER_RGB, visible=False
        )
        self._pose_cloud = s.add_point_cloud(
            "/tracker/poses",
            np.zeros((1, 3), dtype=np.float32),
            TRACKER_RGB,
            point_size=0.018,
            point_shape="circle",
            precision="float32",
            visible=False,
        )
        self._errors = s.add_line_segments(
            "/tracker/errors", np.zeros((1, 2, 3)), ERROR_RGB, thickness=0.012, visible=False
        )
        cam, look = camera_pose(home.polyline)
        server.initial_camera.position = tuple(cam * M_PER_MM)
        server.initial_camera.look_at = tuple(look * M_PER_MM)

    def _build_panel(self, server: ViserServer) -> None:
        g = server.gui
        g.add_markdown(f"**twin view** · {self.title}")
        self._status = g.add_markdown("starting")
        self._phase = g.add_markdown("")
        self._numbers = g.add_markdown("")
        self._tracking = g.add_markdown("")
        mag = g.add_button_group("error vectors ×", MAGNIFICATIONS)

        @mag.on_click
        def _(event: GuiEvent[Any]) -> None:
            self.factor = float(event.target.value)

        if isinstance(self.source, ReplaySource):
            self._build_replay_controls(server, self.source)
        with g.add_folder("calibration"):
            g.add_markdown(self._calibration_text())

    def _build_replay_controls(self, server: ViserServer, source: ReplaySource) -> None:
        g = server.gui
        clock = source.clock
        with g.add_folder("replay"):
            play = g.add_button("Pause" if clock.playing else "Play")
            speeds = list(SPEEDS)
            if f"{clock.speed:g}" not in speeds:
                speeds.append(f"{clock.speed:g}")
            speed = g.add_dropdown("speed ×", speeds, initial_value=f"{clock.speed:g}")
            slider = self._slider = g.add_slider(
                "time s", 0.0, max(round(source.duration_s, 2), 0.01), 0.01, 0.0
            )

        @play.on_click
        def _(_event: GuiEvent[Any]) -> None:
            if clock.playing:
                clock.pause()
            else:
                clock.play()
            play.label = "Pause" if clock.playing else "Play"

        @speed.on_update
        def _(event: GuiEvent[Any]) -> None:
            clock.set_speed(float(event.target.value))

        @slider.on_update
        def _(event: GuiEvent[Any]) -> None:
            if event.client is not None:  # a person moved it (not our own progress update)
                clock.seek(float(event.target.value))

        self._play_button = play

    def _calibration_text(self) -> str:
        t = self.twin
        parts = [f"model: {t.source}"]
        if t.ghost is not None:
            parts.append(
                f"grey: the nominal model on the calibrated base, its deviation ×{GHOST_MAGNIFY:g}"
            )
        if t.stage_table:
            parts.append(_markdown_table(t.stage_table))
        if t.effects:
            parts.append("added effects: " + "; ".join(t.effects))
        elif t.calibrated:
            parts.append("added effects: none")
        else:
            parts.append("no calibration (`twin run` writes one; give it with --model)")
        return "\n\n".join(parts)

    # -- updates -----------------------------------------------------------------------------
    def draw(self, snap: Snapshot) -> None:
        """Set the scene's nodes from one snapshot (one atomic message group)."""
        assert self._server is not None
        k = self.factor
        with self._server.atomic():
            if snap.q_deg is not None and np.isfinite(snap.q_deg).all():
                arm = arm_geometry(self._kin, snap.q_deg)
                self._links.points = (arm.segments * M_PER_MM).astype(np.float32)
                self._frames.batched_positions = (arm.frames[:, :3, 3] * M_PER_MM).astype(
                    np.float32
                )
                self._frames.batched_wxyzs = _wxyz(arm.frames[:, :3, :3]).astype(np.float32)
                if self._ghost is not None and self.twin.ghost is not None:
                    ghost = arm_geometry(self.twin.ghost, snap.q_deg)
                    line = magnified(arm.polyline, ghost.polyline, GHOST_MAGNIFY)
                    self._ghost.points = (
                        np.stack([line[:-1], line[1:]], axis=1) * M_PER_MM
                    ).astype(np.float32)
            if snap.tcp_mm is not None:
                self._tcp.position = tuple(snap.tcp_mm * M_PER_MM)
            if snap.tracker_mm is not None:
                self._tracker.position = tuple(snap.tracker_mm * M_PER_MM)
            self._tracker.visible = snap.tracker_mm is not None
            n_pose = len(snap.pose_points_mm)
            if n_pose:
                self._pose_cloud.points = (snap.pose_points_mm * M_PER_MM).astype(np.float32)
                seg = error_segments(snap.pose_points_mm, snap.pose_twin_mm, k)
                if len(seg):
                    self._errors.points = (seg * M_PER_MM).astype(np.float32)
                self._errors.visible = bool(len(seg))
            else:
                self._errors.visible = False
            self._pose_cloud.visible = bool(n_pose)

    def _panel(self, snap: Snapshot) -> None:
        if snap.duration_s is not None:
            state = "playing" if snap.playing else "paused"
            status = (
                f"**replay {snap.t_s:.2f} s of {snap.duration_s:.2f} s** · {state} ×{snap.speed:g}"
            )
            if self._slider is not None:
                self._slider.value = round(snap.t_s, 2)
            if self._play_button is not None:
                self._play_button.label = "Pause" if snap.playing else "Play"
        else:
            status = f"**live {snap.t_s:.1f} s** since the first grating sample"
        self._status.content = status + (f"  \n{snap.note}" if snap.note else "")
        self._phase.content = f"phase: **{snap.phase}**"
        rows = []
        if snap.tcp_mm is not None:
            x, y, z = snap.tcp_mm
            rows.append(f"TCP {x:.2f}, {y:.2f}, {z:.2f} mm")
        if snap.q_deg is not None:
            rows.append("q " + ", ".join(f"{v:.3f}" for v in snap.q_deg) + " °")
        n_pose = len(snap.pose_points_mm)
        if n_pose:
            err = np.linalg.norm(snap.pose_points_mm - snap.pose_twin_mm, axis=1)
            err = err[np.isfinite(err)]
            if len(err):
                rows.append(
                    f"{n_pose} poses: |tracker − twin| mean {err.mean():.4f} mm, "
                    f"max {err.max():.4f} mm (vectors ×{self.factor:g})"
                )
        stream = "live twin" if snap.duration_s is None else "recorded gratings"
        if snap.rate_hz is not None:
            rows.append(f"{stream}: {snap.rate_hz:.0f} samples/s")
        if snap.latency_ms is not None:
            what = "latency" if snap.duration_s is None else "receive − mapped"
            rows.append(f"{what} p50 {snap.latency_ms[0]:.1f} ms, p99 {snap.latency_ms[1]:.1f} ms")
        view = f"view: {self.stats.rate_hz:.1f} frames/s (update {self.stats.update_ms_p50:.1f} ms"
        if self.stats.age_ms_p50 is not None:
            view += f", drawn sample {self.stats.age_ms_p50:.1f} ms after the twin sent it"
        rows.append(view + ")")
        self._numbers.content = "  \n".join(rows)
        if snap.tracking != self._tracking.content:
            self._tracking.content = snap.tracking

    def run(self, duration_s: float | None = None) -> FrameStats:
        """Update the page at ``fps`` until :meth:`stop` (or ``duration_s``); the stats."""
        period = 1.0 / self.fps
        started = time.monotonic()
        next_frame = started
        next_panel = started
        while not self._stopped.is_set():
            now = time.monotonic()
            if duration_s is not None and now - started >= duration_s:
                break
            snap = self.source.latest()
            self.draw(snap)
            self.stats.frames += 1
            self._frame_times.append(now)
            done = time.monotonic()
            self._update_ms.append((done - now) * 1e3)
            if snap.published_ns is not None:
                self._age_ms.append((time.time_ns() - snap.published_ns) * 1e-6)
            if done >= next_panel:
                recent = [t for t in self._frame_times if t > done - 1.0]
                span = done - recent[0] if len(recent) > 1 else 0.0
                self.stats.rate_hz = (len(recent) - 1) / span if span > 0 else 0.0
                p50, p99 = np.percentile(self._update_ms, [50, 99])
                self.stats.update_ms_p50, self.stats.update_ms_p99 = float(p50), float(p99)
                if self._age_ms:
                    a50, a99 = np.percentile(self._age_ms, [50, 99])
                    self.stats.age_ms_p50, self.stats.age_ms_p99 = float(a50), float(a99)
                self._panel(snap)
                next_panel = done + self.panel_period_s
            # a fixed schedule, not sleep(period): a frame a little late is made up by the
            # next; one more than a period behind drops the missed ticks (no burst)
            next_frame += period
            if done - next_frame > period:
                next_frame = done
            self._stopped.wait(max(next_frame - time.monotonic(), 0.0))
        return self.stats

    def stop(self) -> None:
        self._stopped.set()

    def close(self) -> None:
        self.stop()
        if self._server is not None:
            with _quiet_stdout():
                self._server.stop()
            self._server = None
