"""``twin view``: the arm's geometry, the phase at an instant, the replay clock, bad input,
and the page itself in a real browser.

The browser test starts ``twin view --replay`` as a process on the committed test
recording (``tests/data/campaign_small.mcap``, docs/twin-run.md "Replay tests"), opens
the page in headless Chromium (Debian's ``chromium``; ``make test`` installs it, through
scripts/need-chromium), and checks that the robot is drawn (the scene's pixels differ from
an empty viser scene's, and the arm's colour is there) and that the page's status reads
the replay's time. No Chromium is a failure, not a skip.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel, flange_poses, tcp_positions
from calibration.twin.phase_detection import Dwell, HomeReturn, Phases, Pose, SweepStop
from view.phases import PhaseTimeline
from view.scene import arm_geometry, error_segments, ghost_model, magnified
from view.sources import ReplayClock

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "campaign_small.mcap"
TWIN = [sys.executable, "-m", "calibration.cli"]
WINDOW = (1100, 700)


# -- the arm as geometry ----------------------------------------------------------------------
def test_the_drawn_arm_ends_at_the_twins_tcp_and_its_frames_are_the_chain():
    robot = load_robot("kr500")
    model = KinematicModel.from_description(robot)
    q = np.array([10.0, -20.0, 35.0, 60.0, -45.0, 120.0])
    arm = arm_geometry(model, q)
    n = robot.n_joints
    assert arm.frames.shape == (n + 1, 4, 4) and arm.polyline.shape == (2 * n + 2, 3)
    np.testing.assert_allclose(arm.polyline[-1], tcp_positions(model, np.radians(q)), atol=1e-9)
    np.testing.assert_allclose(arm.frames[-1], flange_poses(model, np.radians(q)), atol=1e-9)
    np.testing.assert_allclose(arm.polyline[0], model.base_mm)
    # every link's two legs: a along the previous x, then d along the joint's z
    leg_a = np.linalg.norm(arm.polyline[1:-1:2] - arm.polyline[0:-2:2], axis=1)
    leg_d = np.linalg.norm(arm.polyline[2:-1:2] - arm.polyline[1:-2:2], axis=1)
    np.testing.assert_allclose(leg_a, np.abs(model.a_mm), atol=1e-9)
    np.testing.assert_allclose(leg_d, np.abs(model.d_mm), atol=1e-9)
    assert arm.segments.shape == (2 * n + 1, 2, 3)


def test_error_vectors_are_magnified_from_the_measured_point_and_skip_nan():
    measured = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [np.nan, 0.0, 0.0]])
    twin = np.array([[0.01, 0.0, 0.0], [1.0, 1.0, 1.02], [0.0, 0.0, 0.0]])
    seg = error_segments(measured, twin, 100.0)
    assert seg.shape == (2, 2, 3)
    np.testing.assert_allclose(seg[:, 0], measured[:2])
    np.testing.assert_allclose(seg[0, 1], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(seg[1, 1], [1.0, 1.0, 3.0])
    np.testing.assert_allclose(magnified([1.0, 2.0], [1.5, 2.0], 10.0), [6.0, 2.0])


def test_the_ghost_is_the_nominal_geometry_on_the_calibrated_base():
    nominal = load_robot("kr500")
    base = nominal.base.__class__(3010.0, -480.0, -1230.0, 0.1, -0.2, 149.0)
    calibrated = nominal.__class__(
        nominal.name, nominal.joints, nominal.tool, base, nominal.home_deg
    )
    ghost = ghost_model(nominal, calibrated)
    np.testing.assert_allclose(ghost.base_mm, [3010.0, -480.0, -1230.0])
    np.testing.assert_allclose(ghost.a_mm, KinematicModel.from_description(nominal).a_mm)


# -- the phase at an instant --------------------------------------------------------------
def _dwell(k: int, t0_s: float, t1_s: float) -> Dwell:
    return Dwell(k, 10 * k, 10 * k + 5, int(t0_s * 1e9), int(t1_s * 1e9), np.zeros(2))


def test_the_phase_names_the_dwell_or_the_move_at_an_instant():
    dwells = [_dwell(k, 10.0 * k, 10.0 * k + 5) for k in range(6)]
    phases = Phases(
        dwells=dwells,
        sweeps=[SweepStop(2, "forward", 0, 0), SweepStop(2, "forward", 1, 1)],
        home_returns=[HomeReturn(1, 1, 2, 1)],
        poses=[Pose("id000", "identify", 3), Pose("val000", "validate", 4)],
        home_counts=np.zeros(2),
        step_counts={2: 100.0},
        other=[5],
    )
    tl = PhaseTimeline.from_phases(phases)
    s = 1_000_000_000
    assert tl.label_at(-1) == "before the first dwell"
    assert tl.label_at(2 * s) == "sweep of joint 2, forward, stop 1 of 2"
    assert tl.label_at(7 * s) == "moving: sweep of joint 2"
    assert tl.label_at(22 * s) == "Home return of joint 1, trial 1"
    assert tl.label_at(27 * s) == "moving to pose 1 of 2 (identify)"
    assert tl.label_at(41 * s) == "pose 2 of 2 (validate)"
    assert tl.label_at(51 * s) == "dwell (other)"
    assert tl.label_at(99 * s) == "moving (after the last dwell)"


# -- the replay clock ---------------------------------------------------------------------
def test_the_replay_clock_plays_pauses_seeks_and_stops_at_the_end():
    clock = ReplayClock(10.0, speed=100.0)
    time.sleep(0.03)
    assert 1.0 < clock.now_s() <= 10.0
    clock.pause()
    t = clock.now_s()
    time.sleep(0.02)
    assert clock.now_s() == t and not clock.playing
    clock.seek(4.0)
    assert clock.now_s() == 4.0
    clock.set_speed(1000.0)
    clock.play()
    time.sleep(0.05)
    assert clock.now_s() == 10.0 and not clock.playing  # stopped at the end, paused
    clock.play()  # at the end: from the start
    assert clock.now_s() < 5.0
    with pytest.raises(ValueError):
        clock.set_speed(0.0)


# -- the sources ----------------------------------------------------------------------------
def test_a_replayed_campaign_gives_the_arm_the_poses_and_the_phase_at_each_instant():
    from calibration.twin.campaign_measurement import measure_campaign
    from calibration.twin.streams import read_recording_streams
    from view.model import provisional_twin
    from view.sources import ReplaySource, pose_points

    streams = read_recording_streams(DATA)
    meas = measure_campaign(streams, load_robot("kr500"))
    twin = provisional_twin("kr500", meas)
    source = ReplaySource(
        streams, twin, timeline=PhaseTimeline.from_phases(meas.phases),
        poses=pose_points(meas, twin),
    )  # fmt: skip
    assert not source.clock.playing  # until the page is served
    early, end = source.snapshot_at(5.0), source.snapshot_at(source.duration_s)
    assert len(early.pose_points_mm) == 0 and len(end.pose_points_mm) == 250
    # the nominal arm on a registered base, read through maps of this recording's sweeps:
    # the tracker sees the TCP within the nominal model's error (about 1 mm)
    err = np.linalg.norm(end.pose_points_mm - end.pose_twin_mm, axis=1)
    assert 0.1 < float(np.mean(err)) < 3.0, np.mean(err)
    dwell = meas.phases.dwells[meas.poses[10].dwell]  # a few ms: the campaign ran at 160x
    at_pose = source.snapshot_at(((dwell.t0_ns + dwell.t1_ns) // 2 - source.t_start_ns) * 1e-9)
    assert at_pose.phase == "pose 11 of 250 (identify)", at_pose.phase
    np.testing.assert_allclose(at_pose.tcp_mm, at_pose.tracker_mm, atol=5.0)
    assert len(at_pose.pose_points_mm) == 10
    assert at_pose.rate_hz == pytest.approx(1000.0, rel=0.05)
    assert at_pose.latency_ms is not None and 0 < at_pose.latency_ms[0] < 100


def test_the_live_source_keeps_the_latest_twin_sample_and_the_twins_health():
    from daq.bus import ChannelPublisher, SchemaServer, open_session
    from daq.columnar import Column, StreamSchema
    from daq.testing import free_port, loopback_sink, loopback_source
    from view.model import nominal_twin
    from view.sources import LiveSource

    port = free_port()
    src = open_session(loopback_source(port))
    dst = open_session(loopback_sink(port))
    source = None
    try:
        schema = StreamSchema(
            "twin/c/robot/r/state",
            (
                Column("seq", "uint64", (), "", None, ""),
                Column("t_mapped_ns", "int64", (), "ns", "host_utc", ""),
                Column("t_publish_ns", "int64", (), "ns", "host_utc", ""),
                Column("q_deg", "float64", (6,), "deg", None, ""),
                Column("tcp_mm", "float64", (3,), "mm", None, ""),
            ),
        )
        schemas = SchemaServer(src, "twin")
        pub = ChannelPublisher(src, schema, schemas=schemas)
        health = src.declare_publisher("twin/c/robot/r/health")
        from calibration.twin.twin_keys import tracking_schema

        names = ("base.x_mm", "joint2.length_scale")
        tracking = ChannelPublisher(
            src, tracking_schema("twin/c/robot/r/tracking", names, "c", "r", "m"), schemas=schemas
        )
        source = LiveSource(dst, nominal_twin("kr500"), phase_period_s=0.2)
        deadline = time.monotonic() + 20
        k = 0
        while source.latest().q_deg is None or source.latest().q_deg[0] < k - 1:
            assert time.monotonic() < deadline, "no twin sample reached the live source"
            k += 1
            now = time.time_ns()
            pub.publish(
                {"seq": np.array([k, k + 1]), "t_mapped_ns": np.array([now - 5, now]),
                 "t_publish_ns": np.array([now, now + 1]),
                 "q_deg": np.array([[0.0] * 6, [float(k)] * 6]),
                 "tcp_mm": np.array([[0.0] * 3, [1.0, 2.0, float(k)]])}
            )  # fmt: skip
            health.put(json.dumps({"rate_hz": 999.0, "latency_ms": {"p50": 1.5, "p99": 4.0}}))
            tracking.publish(
                {"seq": np.array([k]), "t_mapped_ns": np.array([now]),
                 "t_publish_ns": np.array([now]), "point_mm": np.zeros((1, 3)),
                 "predicted_mm": np.zeros((1, 3)), "error_mm": np.array([0.02]),
                 "parameters": np.array([[1000.0 + 0.01 * k, 1.0]]),
                 "standard_errors": np.array([[0.001, 1e-6]]), "lambda": np.array([0.99]),
                 "state": np.array([2], np.uint8), "displacement_mm": np.array([0.3]),
                 "steps": np.array([1], np.uint32), "alarms": np.array([1], np.uint32)}
            )  # fmt: skip
            time.sleep(0.05)
        snap = source.latest()
        assert snap.duration_s is None  # live
        assert snap.q_deg[0] == snap.tcp_mm[2] and snap.tcp_mm[0] == 1.0  # the batch's last
        assert snap.published_ns == snap.t_ns + 1  # the last row's publication time
        time.sleep(0.2)
        snap = source.latest()
        assert snap.rate_hz == 999.0 and snap.latency_ms == (1.5, 4.0)
        # the twin's tracking: the alarm state, the error history, each parameter's drift
        assert "tracking: **alarm**" in snap.tracking and "alarms 1" in snap.tracking
        assert "base.x_mm" in snap.tracking and "drift +" in snap.tracking, snap.tracking
    finally:
        if source is not None:
            source.close()
        dst.close()
        src.close()


# -- bad input: one line, exit 2 ------------------------------------------------------------
@pytest.mark.parametrize(
    ("args", "names"),
    [
        (["--replay", "{tmp}/missing.mcap"], "missing.mcap"),
        (["--replay", "{tmp}/text.mcap"], "text.mcap"),
        (["--replay", "{tmp}"], "--replay"),
        (["--replay", str(DATA), "--model", "{tmp}/missing.toml"], "missing.toml"),
        (["--port", "70000"], "--port"),
        (["--speed", "0"], "--speed"),
        (["--fps", "nan"], "--fps"),
        (["--replay", str(DATA), "--connect", "tcp/127.0.0.1:7447"], "--connect"),
        (["--connect", "nonsense"], "--connect"),
        (["--allow-partial"], "--allow-partial"),
        (["--replay", str(DATA), "--cell", "cell1"], "--cell"),
        (["--cell", "a/b"], "--cell"),
    ],
)
def test_bad_input_is_one_line_naming_it_and_exit_2(tmp_path, args, names):
    (tmp_path / "text.mcap").write_text("joint,counts\n1,2\n")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args]
    proc = subprocess.run(
        [*TWIN, "view", *argv, "--quiet", "--duration", "1"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("twin view: error:") and names in lines[0], lines[0]


# -- the page in a real browser -----------------------------------------------------------
def _chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        pytest.fail(
            "headless Chromium not found: install Debian's package (apt-get install "
            "chromium; `make test` installs it, scripts/need-chromium)"
        )
    return found


def _kill_group(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)


class _Browser:
    """Headless Chromium driven over its DevTools protocol on loopback: load a page, read
    its text, take screenshots. Every wait is bounded; ``close`` kills its processes."""

    def __init__(self, profile: Path) -> None:
        self.proc = subprocess.Popen(
            [
                _chromium(),
                "--headless",
                "--no-sandbox",  # root in CI
                "--disable-gpu",
                "--enable-unsafe-swiftshader",  # WebGL in software
                "--hide-scrollbars",
                "--mute-audio",
                "--no-first-run",
                "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0",
                f"--user-data-dir={profile}",
                f"--window-size={WINDOW[0]},{WINDOW[1]}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        self.ws = None
        self._id = 0
        try:
            self._connect(profile)
        except BaseException:
            self.close()
            raise

    def _connect(self, profile: Path) -> None:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not (port_file.exists() and port_file.read_text().strip()):
            assert self.proc.poll() is None, f"chromium exited {self.proc.returncode}"
            assert time.monotonic() < deadline, "chromium did not open its DevTools port"
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=20) as r:
            page = next(t for t in json.load(r) if t["type"] == "page")
        from websockets.sync.client import connect

        self.ws = connect(page["webSocketDebuggerUrl"], max_size=1 << 26, open_timeout=20)

    def call(self, method: str, **params: object) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self._id:
                assert "error" not in msg, msg["error"]
                return msg["result"]

    def goto(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def text(self) -> str:
        got = self.call(
            "Runtime.evaluate",
            expression="document.body ? document.body.innerText : ''",
            returnByValue=True,
        )
        return str(got["result"].get("value", ""))

    def wait_text(self, pattern: str, timeout_s: float = 60.0) -> re.Match:
        deadline = time.monotonic() + timeout_s
        while True:
            m = re.search(pattern, self.text())
            if m or time.monotonic() > deadline:
                assert m, f"no {pattern!r} in the page after {timeout_s:g} s"
                return m
            time.sleep(0.3)

    def screenshot(self) -> np.ndarray:
        from PIL import Image

        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        with Image.open(io.BytesIO(png)) as img:
            return np.asarray(img.convert("RGB"), dtype=np.int16)

    def close(self) -> None:
        if self.ws is not None:
            with contextlib.suppress(Exception):
                self.ws.close()
        _kill_group(self.proc)


def _scene_region(rgb: np.ndarray) -> np.ndarray:
    # left of the panel (docked on the right) and below viser's notices (top left)
    h, w, _ = rgb.shape
    return rgb[int(0.25 * h) :, : int(0.6 * w)]


def _arm_pixels(rgb: np.ndarray) -> int:
    """Pixels of the arm's orange (ARM_RGB, drawn lighter by the client: about 240, 187,
    125): red high, green between red and blue; not the red axes, green tracker points,
    grey ghost or white."""
    r, g, b = (rgb[..., k] for k in range(3))
    return int(np.count_nonzero((r > 200) & (r - b > 80) & (g - b > 30) & (r - g > 30)))


def _empty_scene(browser: _Browser) -> np.ndarray:
    """viser with nothing in its scene, same window and panel placement."""
    import viser

    from view.server import _quiet_stdout

    with _quiet_stdout():
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        server.gui.configure_theme(control_width="large", show_logo=False, show_share_button=False)
        server.gui.main_panel.dock_right()
        server.gui.add_markdown("empty scene")
        browser.goto(f"http://127.0.0.1:{server.get_port()}/")
        browser.wait_text("empty scene")
        time.sleep(2.0)  # let the canvas draw its frames
        return browser.screenshot()
    finally:
        with _quiet_stdout():
            server.stop()


def _recording_duration_s() -> float:
    from calibration.twin.streams import read_recording_streams

    t = read_recording_streams(DATA).grating.t_ns
    return float(t.max() - t.min()) * 1e-9


@pytest.mark.timeout(240)
def test_the_page_draws_the_robot_and_reads_the_replay_time(tmp_path):
    assert DATA.exists(), f"{DATA} missing (docs/twin-run.md says how it is made)"
    _chromium()  # fail early, with the message, when there is no browser
    start_s = 20.0
    view = subprocess.Popen(
        [*TWIN, "view", "--replay", str(DATA), "--port", "0", "--start", str(start_s),
         "--duration", "150", "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(view.stdout), daemon=True)
    reader.start()
    (tmp_path / "profile").mkdir()
    browser = None
    try:
        browser = _Browser(tmp_path / "profile")
        blank = _scene_region(_empty_scene(browser))  # while the view reads the recording
        deadline = time.monotonic() + 90
        while not lines and view.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert lines, f"no URL from twin view (exit {view.poll()}): {view.stderr.read()[-2000:]}"
        served = json.loads(lines[0])
        url = served["view"]
        assert served["mode"] == "replay" and url.startswith("http://127.0.0.1:")

        browser.goto(url)
        m = browser.wait_text(r"replay (\d+\.\d+) s of (\d+\.\d+) s")
        t_s, total_s = float(m.group(1)), float(m.group(2))
        assert total_s == pytest.approx(_recording_duration_s(), abs=0.01)
        assert start_s <= t_s <= total_s  # playing from --start, never past the end
        phase = browser.wait_text(r"phase: ([^\n]+)").group(1).strip()
        assert phase not in ("phases not known", ""), phase
        later = float(browser.wait_text(r"replay (\d+\.\d+) s of").group(1))
        assert later >= t_s  # the status follows the replay

        # the arm: poll the screenshot (bounded) until the scene has arrived and drawn
        deadline = time.monotonic() + 60
        while True:
            page = _scene_region(browser.screenshot())
            arm = _arm_pixels(page)
            if arm > 400 or time.monotonic() > deadline:
                break
            time.sleep(1.0)
        assert page.shape == blank.shape
        changed = np.abs(page - blank).max(axis=2) > 40
        assert _arm_pixels(blank) < 50
        assert arm > 400, f"no arm drawn ({arm} arm pixels)"
        assert changed.mean() > 0.01, f"the scene looks empty ({changed.mean():.4f} changed)"
    finally:
        if browser is not None:
            browser.close()
        _kill_group(view)


def test_a_sigterm_right_after_the_url_line_is_a_clean_stop(monkeypatch, capsys):
    """The stop handler is in place before the line a supervisor waits for: a SIGTERM sent
    on reading it stops the view cleanly (exit 0), never kills it (CI saw -15 once when the
    handler came after the line)."""
    import view.cli
    from calibration.cli import main

    order: list[str] = []
    real_write = sys.stdout.write

    def write(text: str) -> int:
        if text.startswith('{"view"'):
            order.append("url line")
        return real_write(text)

    monkeypatch.setattr(view.cli, "on_stop_signals", lambda action: order.append("handler"))
    monkeypatch.setattr(sys.stdout, "write", write)
    argv = ["view", "--replay", str(DATA), "--port", "0", "--duration", "0.05", "--quiet"]
    assert main(argv) == 0
    assert order == ["handler", "url line"], order
    assert json.loads(capsys.readouterr().out.splitlines()[0])["mode"] == "replay"


# -- where the package sits in the import graph -------------------------------------------
def test_view_is_loaded_only_by_the_command_line_and_never_sees_the_emulator():
    """The layering itself is tests/test_import_graph.py's (view may import calibration,
    daq and edges; nothing but the command line loads view, by name)."""
    from tests.test_import_graph import MAY_IMPORT, graph

    g = graph()
    assert not any(d.split(".")[0] == "view" for n, deps in g.items() if not n.startswith("view")
                   for d in deps)  # fmt: skip
    assert "sim_devices" not in MAY_IMPORT["view"]
    assert {n for n in g if n.startswith("view.")} >= {"view.cli", "view.scene", "view.server"}
    from calibration.cli import SUBCOMMANDS

    assert SUBCOMMANDS["view"][0] == "view.cli"
