"""``twin export``: the campaign's phases found in a recording, as the documented files.

twin export --replay run.mcap --robot kr500 --out DIR

writes ``home.csv``, ``sweep.csv`` (docs/scale-calibration.md), ``scale.toml`` (the scale
calibration of those, needed for the joint angles), ``campaign.csv``
(docs/identification.md) and ``phases.json`` (what was found, lost stops, lost intervals).
See docs/twin-run.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from edges.command import progress
from edges.options import integer
from edges.outputs import OutputSet


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "export",
        help="write the phases found in a recording as home.csv, sweep.csv, campaign.csv",
        description="Find the campaign's phases (dwells, Home returns, sweeps, poses) in an "
        "MCAP recording of the daemon, pair tracker and grating samples, and write the "
        "documented files. See docs/twin-run.md.",
    )
    p.add_argument("--replay", required=True, metavar="FILE.mcap", help="the recording")
    p.add_argument("--robot", default="kr500", help="nominal robot: preset or .toml (kr500)")
    p.add_argument("--out", required=True, metavar="DIR", help="directory for the files")
    p.add_argument(
        "--encoder-counts-per-rev",
        type=integer(1),
        default=None,
        help="motor encoder counts/turn (131072: 17-bit)",
    )
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="use the readable part of a damaged recording (said on stderr and in phases.json)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=run_export)


def run_export(args: argparse.Namespace) -> int:
    from calibration.errors import OutputFileError
    from calibration.model.description import load_robot
    from calibration.twin.streams import read_recording_streams

    say = progress("twin export", args.quiet)
    robot_file = args.robot if Path(args.robot).exists() else None
    with OutputSet([args.replay, robot_file], error=OutputFileError) as outputs:
        staged = outputs.directory(args.out, "--out")
        robot = load_robot(args.robot)
        say(f"reading {args.replay}")
        streams = read_recording_streams(args.replay, allow_partial=args.allow_partial)
        if streams.note:  # said whatever --quiet says: the data is not the whole recording
            print(f"twin export: warning: {args.replay}: {streams.note}", file=sys.stderr)
        # the measurement's modules (scipy among them) load once the input is read
        from calibration.cli.run_files import write_campaign_files
        from calibration.twin.campaign_measurement import ENCODER_COUNTS_PER_REV
        from calibration.twin.run_documents import export_campaign

        cpr = args.encoder_counts_per_rev or ENCODER_COUNTS_PER_REV
        export = export_campaign(streams, robot, encoder_counts_per_rev=cpr, say=say)
        files = write_campaign_files(staged, export)
        csvs = ", ".join(files[k].name for k in ("home", "sweep", "scale", "campaign"))
        say(f"wrote {csvs} ({len(export.campaign)} poses)")
        written = {name: outputs.final(path) for name, path in files.items()}
    print(json.dumps(export.phases["phases"]))
    for name, path in written.items():
        print(f"wrote {name}: {path}")
    return 0
