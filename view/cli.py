"""``twin view``: the twin in a web browser, on a recording or live.

twin view --replay run.mcap [--model DIR/calibrated.toml] [--port N]
twin view [--connect EP] [--cell NAME] [--model DIR/calibrated.toml] [--port N]

Serves a local page (127.0.0.1, viser's own client; nothing from the internet) and prints
one JSON line with its URL; stops on Ctrl-C / SIGTERM or after ``--duration``. See
docs/view.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from daq.cells import cell_name
from edges.command import progress
from edges.options import integer, number, path_text
from edges.stop_signals import on_stop_signals
from view.errors import ViewError
from view.scene import MAGNIFICATIONS

if TYPE_CHECKING:
    import zenoh

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``twin view`` and its options, on the ``twin`` command's subparsers ``sub``. Long
    as a flat list of ``add_argument`` calls, one per option, in ``--help``'s order."""
    p = sub.add_parser(
        "view",
        help="the twin in the browser: the arm, the TCP, the tracker's errors, the phase",
        description="Serve a local web page with the robot drawn as the gratings drive it, "
        "the tracker's points with their error vectors to the twin (magnified), the "
        "campaign phase, the stage table of a calibration and the stream's rate and "
        "latency. Replay a recording (play, pause, speed, time slider) or follow the "
        "daemon and the live twin over zenoh. See docs/view.md.",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--replay", metavar="FILE.mcap", type=path_text, help="a recording")
    src.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="EP",
        help=f"live: zenoh endpoint of the daemon (and/or the twin) ({DEFAULT_CONNECT})",
    )
    p.add_argument(
        "--cell",
        type=cell_name,
        metavar="NAME",
        help="live: that cell's keys only (cell/NAME/**, twin/NAME/**); without it, the "
        "only cell up, and a bus with several cells asks for one",
    )
    p.add_argument(
        "--model",
        metavar="calibrated.toml",
        type=path_text,
        help="a twin run's calibrated model (scale.toml, phases.json, report/ beside it)",
    )
    p.add_argument(
        "--robot",
        help="nominal robot, preset or .toml (default: the one the calibration started "
        "from, else kr500)",
    )
    p.add_argument("--port", type=integer(0, 65535), default=8080, help="HTTP port (8080)")
    p.add_argument(
        "--speed", type=number(0.0, above=True, hi=1e4), default=1.0, help="replay speed (1)"
    )
    p.add_argument(
        "--start",
        type=number(0.0),
        default=0.0,
        metavar="S",
        help="replay from S seconds after the recording's first grating sample (0)",
    )
    p.add_argument(
        "--fps",
        type=number(1.0, hi=120.0),
        default=40.0,
        help="scene updates per second sent to the page, latest sample wins (40)",
    )
    p.add_argument(
        "--duration",
        type=number(0.0, above=True),
        default=None,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C)",
    )
    p.add_argument(
        "--magnify",
        choices=MAGNIFICATIONS,
        default=MAGNIFICATIONS[0],
        help="error vectors and the ghost's deviation drawn this many times larger at "
        f"first (a switch on the page; {MAGNIFICATIONS[0]})",
    )
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="with --replay: show the readable part of a damaged recording (said on stderr)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=run_view)


def _replay_source(args: argparse.Namespace, say: Any) -> tuple[Any, Any, str]:
    from calibration.errors import CalibrationError, TwinRunError
    from calibration.twin.campaign_measurement import measure_campaign
    from calibration.twin.phase_detection import find_phases
    from calibration.twin.streams import read_recording_streams
    from view.model import load_calibration, nominal_twin, provisional_twin
    from view.phases import PhaseTimeline
    from view.sources import ReplaySource, pose_points

    path = Path(args.replay)
    if not path.is_file():
        raise ViewError(f"--replay {path}: " + ("not a file" if path.exists() else "no such file"))
    model = load_calibration(args.model, args.robot) if args.model else None
    say(f"reading {path}")
    streams = read_recording_streams(path, allow_partial=args.allow_partial)
    if streams.note:  # said whatever --quiet says
        print(f"twin view: warning: {path}: {streams.note}", file=sys.stderr)
    duration_s = float(streams.grating.t_ns.max() - streams.grating.t_ns.min()) * 1e-9
    if args.start > duration_s:
        raise ViewError(f"--start {args.start:g}: the recording lasts {duration_s:.2f} s")
    robot = args.robot or "kr500"
    nominal = model.description if model else nominal_twin(robot).description
    if streams.grating.values.shape[1] != nominal.n_joints:
        raise ViewError(
            f"--replay {path}: the gratings have {streams.grating.values.shape[1]} strips, "
            f"the robot {nominal.name!r} {nominal.n_joints} joints (--robot)"
        )
    say("finding the campaign's phases and poses")
    meas = None
    try:
        meas = measure_campaign(streams, nominal)
    except (TwinRunError, CalibrationError) as exc:
        say(f"no campaign to measure ({exc}): phases only")
    if model is None:
        if meas is not None:
            say("fitting scale maps from the recording's sweeps (the twin's round 1)")
            try:
                model = provisional_twin(robot, meas)
            except CalibrationError as exc:
                say(f"no scale maps ({exc}): the arm stays at Home")
        model = model or nominal_twin(robot)
    if meas is not None:
        timeline = PhaseTimeline.from_phases(meas.phases)
        poses = pose_points(meas, model)
    else:
        g = streams.grating
        timeline = PhaseTimeline.from_phases(find_phases(g.t_ns, g.values))
        poses = None
    note = "" if model.calibrated else "provisional twin: no --model"
    source = ReplaySource(
        streams, model, timeline=timeline, poses=poses, speed=args.speed, note=note
    )
    source.clock.seek(args.start)
    return source, model, f"replay {path.name}"


def _zenoh_client(endpoints: tuple[str, ...]) -> Any:
    """A zenoh client of ``endpoints``; TLS to a router from the environment, as the live
    twin's (docs/deployment.md: DAQ_ZENOH_TLS_CA, _CERTIFICATE, _PRIVATE_KEY)."""
    from daq.bus import open_session
    from daq.config import ZenohConfig, env_overrides

    env = env_overrides().get("zenoh", {})
    zc = ZenohConfig(
        mode="client",
        listen=(),
        connect=endpoints,
        tls_ca=str(env.get("tls_ca", "")),
        tls_certificate=str(env.get("tls_certificate", "")),
        tls_private_key=str(env.get("tls_private_key", "")),
    )
    try:
        # a client of the daemon: its session routes the cell's and the twin's keys
        return open_session(zc)
    except Exception as exc:  # zenoh refuses a malformed endpoint with its own error type
        reason = str(exc).split(" at /", 1)[0]  # zenoh appends its Rust source location
        raise ViewError(f"--connect {' '.join(endpoints)}: {reason}") from None


def pick_cell(
    session: zenoh.Session, cell: str | None, where: str, say: Callable[[str], None]
) -> str | None:
    """The cell the live view follows: ``cell`` (``--cell``), else the only cell up on the
    bus (said on stderr); several up: a :class:`ViewError` naming them (the view would
    draw one robot from several cells' gratings); none up yet: None, every cell."""
    from daq.cells import cells_on_bus

    if cell is not None:
        return cell
    up = cells_on_bus(session)
    if len(up) > 1:
        cells = ", ".join(up)
        raise ViewError(f"--connect {where}: cells {cells} are up there: pick one with --cell")
    if up:
        say(f"cell {up[0]}: the only cell up (--cell picks another)")
        return up[0]
    say("no cell up yet: following every cell (cell/**, twin/**; --cell picks one)")
    return None


def _live_source(args: argparse.Namespace, say: Any) -> tuple[Any, Any, str]:
    from view.model import load_calibration, nominal_twin
    from view.sources import LiveSource

    model = load_calibration(args.model, args.robot) if args.model else None
    model = model or nominal_twin(args.robot or "kr500")
    endpoints = tuple(args.connect or [DEFAULT_CONNECT])
    where = " ".join(endpoints)
    say(f"connecting to {', '.join(endpoints)}")
    session = _zenoh_client(endpoints)
    try:
        cell = pick_cell(session, getattr(args, "cell", None), where, say)
        source = LiveSource(session, model, say=say, cell=cell)
    except Exception:
        session.close()
        raise
    title = f"live {', '.join(endpoints)}" + (f", cell {cell}" if cell else "")
    return source, model, title


def run_view(args: argparse.Namespace) -> int:
    from view.server import TwinView
    from view.sources import LiveSource

    say = progress("twin view", args.quiet)
    if args.allow_partial and not args.replay:
        raise ViewError("--allow-partial goes with --replay (a recording)")
    if args.cell is not None and args.replay:
        raise ViewError("--cell goes with --connect (live): a recording holds its own cell")
    if args.model is not None and not Path(args.model).is_file():
        raise ViewError(f"--model {args.model}: no such file")
    source, model, title = (_replay_source if args.replay else _live_source)(args, say)
    view = TwinView(
        source, model, title=title, port=args.port, fps=args.fps, magnify=float(args.magnify)
    )
    try:
        url = view.start()
        if args.replay:
            source.clock.play()
        mode = "replay" if args.replay else "live"
        up = {"view": url, "port": int(url.rsplit(":", 1)[1].strip("/")), "mode": mode}
        if isinstance(source, LiveSource):
            up["cell"] = source.cell  # the cell it follows (None: every cell)
        # before the line a supervisor waits for: a SIGTERM right after it is a clean stop
        on_stop_signals(view.stop)  # not in the handler: edges/stop_signals.py
        print(json.dumps(up), flush=True)
        say(f"serving {url} ({model.source})")
        started = time.monotonic()
        stats = view.run(args.duration)
        elapsed = max(time.monotonic() - started, 1e-9)
        age = (
            f", the drawn sample {stats.age_ms_p50:.1f} ms (p50) / {stats.age_ms_p99:.1f} ms "
            "(p99) after the twin sent it"
            if stats.age_ms_p50 is not None
            else ""
        )
        say(
            f"stopped: {stats.frames} scene updates in {elapsed:.1f} s "
            f"({stats.frames / elapsed:.1f} frames/s; update p50 {stats.update_ms_p50:.1f} ms, "
            f"p99 {stats.update_ms_p99:.1f} ms){age}"
        )
    finally:
        view.close()
        source.close()
        if isinstance(source, LiveSource):
            source.session.close()
    return 0
