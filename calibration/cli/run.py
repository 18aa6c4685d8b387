"""``twin run``: the twin end to end, on a recording or on the daemon's live streams.

twin run --replay run.mcap --robot kr500 --out DIR     # offline, deterministic
twin run --robot kr500 --out DIR [--connect EP] ...    # live: collect, calibrate, publish

See docs/twin-run.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from calibration.errors import DataFileError, OptionError, OutputFileError
from edges.command import progress
from edges.inputs import MAX_TOML_BYTES, read_input_bytes
from edges.options import integer, number
from edges.outputs import OutputSet


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "run",
        help="the twin end to end: phases, scale calibration, identification, live twin",
        description="Find the campaign in the data, calibrate the gratings, identify the "
        "geometry and the effects it lacks, write the reports and the calibrated model; "
        "live, then publish the twin. See docs/twin-run.md.",
    )
    p.add_argument("--replay", metavar="FILE.mcap", help="a recording (default: live zenoh)")
    p.add_argument("--robot", default="kr500", help="nominal robot: preset or .toml (kr500)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--from",
        dest="from_dir",
        metavar="DIR",
        help="live: skip the campaign, publish the twin calibrated by an earlier run in DIR",
    )
    p.add_argument("--no-effects", action="store_true", help="the geometry alone")
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="with --replay: use the readable part of a damaged recording (said on stderr, "
        "recorded in phases.json and report.json)",
    )
    p.add_argument(
        "--max-effects",
        type=integer(0),
        default=None,
        metavar="N",
        help="add at most N effects (default 6); the report names the best candidate left",
    )
    p.add_argument(
        "--identify-poses",
        type=integer(1),
        default=None,
        metavar="N",
        help="the first N poses found identify, the rest validate (a planned campaign's "
        "count, identify poses first; default: the first 40 %%)",
    )
    p.add_argument("--no-report", action="store_true", help="no figures (report.json only)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    live = p.add_argument_group("live (without --replay)")
    _add_zenoh_options(live)
    _add_live_options(live)
    p.set_defaults(func=run_run)


def _add_zenoh_options(live: argparse._ArgumentGroup) -> None:
    """How the live twin meets the daemon."""
    live.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="EP",
        help="zenoh endpoint of the daemon (tcp/127.0.0.1:7447)",
    )
    live.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="EP",
        help="zenoh endpoints to listen on (default: none; needs --mode peer)",
    )
    live.add_argument(
        "--mode",
        choices=("client", "peer"),
        default=None,
        help="zenoh mode: client of the daemon (default: the daemon's session routes the "
        "twin's keys to everyone connected to it), or peer (default with --listen)",
    )


def _add_live_options(live: argparse._ArgumentGroup) -> None:
    """What the live twin publishes, and when collection and publication end."""
    live.add_argument(
        "--effects-radius-deg",
        type=number(0.0, hi=5.0),
        default=0.25,
        help="the modelled effects' share of the TCP is linearised within this many degrees "
        "of the pose it was evaluated at (0.25; 0: the full predictor for every batch)",
    )
    live.add_argument(
        "--frames-hz",
        type=number(0.0),
        default=30.0,
        help="publish the link frames (twin/.../frames) at most this often (30; 0: never)",
    )
    live.add_argument(
        "--no-tracking",
        action="store_true",
        help="publish the calibrated model as it is: do not follow the robot through its "
        "production dwells (default: follow it when the model has [tracking]; "
        "docs/tracking.md)",
    )
    live.add_argument(
        "--alarm-mm",
        type=number(0.0, above=True),
        default=None,
        help="tracking: alarm when the tracked model moves the TCP at the validation poses "
        "by more than this (mm; default: no alarm)",
    )
    live.add_argument(
        "--wait-s",
        type=number(0.0, above=True),
        default=60.0,
        help="--from: wait at most this long for the first grating batch (60 s)",
    )
    live.add_argument("--key", default="cell/**", help="key expression of the data (cell/**)")
    live.add_argument(
        "--idle-s",
        type=number(0.0, above=True),
        default=10.0,
        help="the campaign is over when the robot has not moved for this long "
        "after the last pose (10 s)",
    )
    live.add_argument(
        "--collect-s",
        type=number(0.0),
        default=0.0,
        help="collect for at most this long (0: until idle)",
    )
    live.add_argument(
        "--publish-s",
        type=number(0.0),
        default=0.0,
        help="publish the live twin for this long, then stop (0: until Ctrl-C or SIGTERM)",
    )


def _earlier_run(from_dir: str) -> dict[str, Any]:
    """run.json of an earlier ``twin run --out DIR`` (the files it names must exist), its
    paths resolved from this working directory."""
    from calibration.cli.run_files import RUN_PATHS_RELATIVE_TO, resolve_run_path

    path = Path(from_dir) / "run.json"
    raw = read_input_bytes(path, limit=MAX_TOML_BYTES, error=DataFileError)
    try:
        run: Any = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise DataFileError(f"{path}: not the run.json of a twin run: {exc}") from None
    need = {"calibrated": str, "files": dict}
    for key, kind in need.items():
        if not isinstance(run, dict) or not isinstance(run.get(key), kind):
            raise DataFileError(f"{path}: key '{key}': missing or not a {kind.__name__}")
    for key in ("scale", "phases"):
        if not isinstance(run["files"].get(key), str):
            raise DataFileError(f"{path}: key 'files.{key}': missing or not a path")
    # paths relative to run.json's directory (older run.json: to the first run's cwd)
    beside = run.get("paths_relative_to") == RUN_PATHS_RELATIVE_TO
    run["calibrated"] = str(resolve_run_path(from_dir, run["calibrated"], beside))
    files = dict(run["files"])
    for key, name in files.items():
        if isinstance(name, str):
            files[key] = str(resolve_run_path(from_dir, name, beside))
    run["files"] = files
    checked: dict[str, Any] = run
    for key, name in (
        ("calibrated", run["calibrated"]),
        ("files.scale", files["scale"]),
        ("files.phases", files["phases"]),
    ):
        if not Path(name).is_file():
            raise DataFileError(f"{path}: key '{key}' names {name}, which is not there any more")
    return checked


def run_run(args: argparse.Namespace) -> int:
    say = progress("twin run", args.quiet)
    _check_live_options(args)
    if args.from_dir:
        return _publish_earlier(args, say)
    live = None
    robot_file = args.robot if Path(args.robot).exists() else None
    outputs = OutputSet([args.replay, robot_file], error=OutputFileError)
    try:
        staged = outputs.directory(args.out, "--out")
        if args.replay:
            from calibration.twin.streams import read_recording_streams

            say(f"reading {args.replay}")
            streams = read_recording_streams(args.replay, allow_partial=args.allow_partial)
            if streams.note:  # said whatever --quiet says
                print(f"twin run: warning: {args.replay}: {streams.note}", file=sys.stderr)
        else:
            from calibration.twin.live_twin import LiveSettings, LiveTwin

            live = LiveTwin(LiveSettings.from_options(args), say)
            streams = live.collect()
        # the twin's modules (scipy among them) load once the input is read: a file that is
        # not a recording is refused in a fraction of a second
        from calibration.cli.run_files import write_twin_run
        from calibration.twin.phase_detection import PhaseOptions
        from calibration.twin.twin_run import run_twin

        phases = PhaseOptions(identify_count=args.identify_poses)
        result = run_twin(
            streams, args.robot, effects=not args.no_effects, max_effects=args.max_effects,
            phase_options=phases, say=say,
        )  # fmt: skip
        run = write_twin_run(staged, Path(args.out), result, report=not args.no_report, say=say)
        outputs.commit()  # before publishing, which may go on until Ctrl-C
        print(run["stage_table"])
        print(f"calibrated model: {run['calibrated']}")
        print(f"report: {run['report']}/report.md (scale: {args.out}/scale-report/report.md)")
        print(f"phases: {run['files']['phases']}", flush=True)
        if live is not None:  # the twin as written, named by its file as --from names it
            from calibration.twin.live_twin import CalibratedTwin

            return live.publish(CalibratedTwin.from_twin_run(result, run["calibrated"]))
        return 0 if result.success else 1
    finally:
        outputs.discard()
        if live is not None:
            live.close()


def _check_live_options(args: argparse.Namespace) -> None:
    """The zenoh options checked together (one line naming the option, exit 2; the numbers
    are checked by their argparse types); ``--mode`` resolved: ``peer`` when listening,
    else ``client``."""
    if args.allow_partial and not args.replay:
        raise OptionError("--allow-partial goes with --replay (a recording)")
    if args.mode is None:
        args.mode = "peer" if args.listen and args.listen != ["none"] else "client"
    elif args.mode == "client" and args.listen and args.listen != ["none"]:
        raise OptionError("--listen: a zenoh client listens nowhere; use --mode peer")
    if args.mode == "client" and args.connect == ["none"]:
        raise OptionError("--connect none: a zenoh client needs an endpoint to connect to")


def _publish_earlier(args: argparse.Namespace, say: Callable[[str], None]) -> int:
    """``--from DIR``: publish the twin an earlier run wrote, read from its files."""
    from calibration.twin.live_twin import CalibratedTwin, LiveSettings, LiveTwin

    twin = CalibratedTwin.from_run(_earlier_run(args.from_dir))
    live = LiveTwin(LiveSettings.from_options(args), say)
    try:
        return live.publish(twin)
    finally:
        live.close()
