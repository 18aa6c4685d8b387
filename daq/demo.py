"""The demo: emulated cell with an undeclared effect → daemon → MCAP → twin → stage table.

``make demo`` runs ``python -m daq.demo``:

1. writes the emulated cell's configuration (``sim-cell.toml`` in the output directory):
   the KR500 running the whole calibration campaign (10 Home returns per joint, 2° sweeps
   limit to limit and back for all six joints, 100 identification and 150 validation
   poses, 1 s dwells) on a simulated clock ``--speed`` times faster than real time, with
   an effect the twin is not told about (``--effect``, default gravity deflection after
   the ring); the tracker measures the target on link J during joint J's Home returns and
   sweeps and the TCP target during the poses (``[tracker] target = "program"``: the
   operator moves the reflector between the phases, 20 s of robot time each);
2. runs the acquisition daemon on it (``daq run --sim-config ... --record``, a separate
   process) for the program's length, recording every stream to MCAP;
3. runs the twin on the recording (``twin run --replay``: phases found in the data,
   scale calibration, identification, closed loop, reports);
4. prints the stage table (nominal → geometric → + found effects), where the reports are,
   and the time each step took.

``--plan DIR`` runs a planned campaign instead of the random poses: ``DIR/campaign_joints.csv``
of ``twin plan`` (its identify poses then its validate poses, each in the plan's order, as
``[cell] plan``), the tracker honouring the reflector's cone and range
(``[tracker] line_of_sight = true``), and ``twin run --identify-poses N`` (the plan's N).
Without it the campaign is the default one.

``--record-only`` stops after step 2 (how the replay tests' recording is made, see
docs/twin-run.md). Zenoh stays on loopback (``--port``), no scouting.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

#: A planned campaign holds at Home this many wall seconds first: the daemon's devices
#: connect within seconds on a loaded host, the tracker last (4.6 s measured), and a short
#: campaign's first sweeps would be lost.
START_HOLD_WALL_S = 8.0

EFFECTS = ("gravity_deflection", "grating_cyclic", "thermal_drift", "tracker_scale", "none")


def sim_config_text(
    robot: str,
    seed: int,
    speed: float,
    effect: str,
    *,
    encoders: bool,
    rate_hz: float,
    plan: str = "",
) -> str:
    """The emulated cell's ``cell.toml``; ``plan``: a plan's ``campaign_joints.csv`` (its
    poses instead of the random ones, and the tracker's line of sight on)."""
    lines = [
        "[cell]",
        f"robot = {json.dumps(robot)}",  # a JSON string is a TOML basic string
        f"seed = {seed}",
        f"speed = {speed}",
        'program = "campaign"',
    ]
    if plan:
        lines.append(f"plan = {json.dumps(plan)}  # twin plan's poses")
        # the devices connect within seconds (wall): the campaign starts after them
        lines.append(f"start_hold_s = {START_HOLD_WALL_S * speed:g}")
    lines += [
        "",
        "[grating]",
        f"rate_hz = {rate_hz}",
        "",
        "[encoders]",
        f"enabled = {'true' if encoders else 'false'}",
        "",
        "[tracker]",
        'target = "program"  # link J for joint J\'s scale calibration, TCP for the poses',
    ]
    if plan:
        lines.append("line_of_sight = true  # the reflector's cone and range, as a tracker")
    lines += [
        "",
    ]
    if effect != "none":
        lines += ["[effects.undeclared]", f"{effect} = true", ""]
    return "\n".join(lines)


def prepare(args: argparse.Namespace, sim: Path) -> tuple[str, float, int]:
    """The emulated cell's configuration text, its program's length in simulated seconds
    and its identification poses, checked before anything is written (``--robot`` is
    named when it is wrong, a bad plan by its file, line and column)."""
    from sim_devices.config import CellConfig, robot_option
    from sim_devices.plant import Plant

    robot_option(args.robot)
    text = sim_config_text(
        args.robot,
        args.seed,
        args.speed,
        args.effect,
        encoders=not args.no_encoders,
        rate_hz=args.rate,
        plan=plan_file(args),
    )
    config = CellConfig.loads(text, source=f"{sim} (from the demo's options)")
    trajectory = Plant.from_config(config).trajectory
    n_identify = sum(label.startswith("identification ") for label in trajectory.labels)
    return text, float(trajectory.end_s), n_identify


def plan_file(args: argparse.Namespace) -> str:
    """``--plan DIR``'s ``campaign_joints.csv``, absolute ("" without ``--plan``)."""
    if not args.plan:
        return ""
    from daq.errors import DaqError

    path = Path(args.plan) / "campaign_joints.csv"
    if not path.is_file():
        raise DaqError(f"--plan {args.plan}: no campaign_joints.csv in it (twin plan --out DIR)")
    return str(path.resolve())


def record(
    args: argparse.Namespace, out_dir: Path, mcap: Path, prepared: tuple[str, float, int] | None
) -> dict[str, Any]:
    sim = out_dir / "sim-cell.toml"
    text, length, _ = prepared or prepare(args, sim)
    sim.write_text(text, encoding="utf-8")
    duration = length / args.speed + args.margin_s
    env = dict(os.environ)
    # coarser batches than the default 1 ms: a smaller file, faster to replay
    env.setdefault("DAQ_PUBLISH_MAX_BATCH_AGE_S", str(args.batch_age_s))
    env.setdefault("DAQ_PUBLISH_MAX_BATCH_SAMPLES", "200")
    cmd = [
        sys.executable,
        "-m",
        "daq.cli",
        "run",
        "--sim-config",
        str(sim),
        "--duration",
        f"{duration:.1f}",
        "--record",
        str(mcap),
        "--rate",
        str(args.rate),
        "--listen",
        f"tcp/127.0.0.1:{args.port}",
    ]
    print(
        f"demo: emulated {args.robot} campaign, {length:.0f} s of robot time at {args.speed:g}x "
        f"= {length / args.speed:.0f} s; undeclared effect: {args.effect}",
        flush=True,
    )
    print(f"demo: {' '.join(cmd)}", flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)
    try:
        lines = _follow(proc, duration, length, mcap, args.port, args.progress_s)
    finally:
        if proc.poll() is None:  # interrupted: stop the daemon (it writes its summary)
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    wall = time.perf_counter() - t0
    last = {}
    for line in lines:
        if line.startswith("{"):
            last = json.loads(line)
    if proc.returncode != 0:
        raise SystemExit(f"demo: daq run exited with {proc.returncode}")
    size = mcap.stat().st_size
    print(
        f"demo: recorded {mcap} ({size / 1e6:.1f} MB) in {wall:.0f} s; devices "
        + json.dumps(last.get("devices", {})),
        flush=True,
    )
    return {"record_s": wall, "mcap_bytes": size, "program_s": length}


class _Health:
    """Samples per device so far, from the daemon's health keys (a zenoh client of it);
    progress only: anything that goes wrong here leaves the figures out."""

    def __init__(self, port: int) -> None:
        self.samples: dict[str, int] = {}
        self._session: Any = None
        self._sub: Any = None
        try:
            from daq.bus import open_session
            from daq.config import ZenohConfig

            zc = ZenohConfig(mode="client", listen=(), connect=(f"tcp/127.0.0.1:{port}",))
            self._session = open_session(zc)
            self._sub = self._session.declare_subscriber("cell/*/robot/*/*/health", self._on)
        except Exception:  # progress is best effort
            self.close()

    def _on(self, sample: Any) -> None:
        try:
            doc = json.loads(sample.payload.to_bytes())
            self.samples[str(doc["device"])] = int(doc["samples"])
        except (ValueError, KeyError, TypeError):
            pass

    def close(self) -> None:
        sub, session, self._sub, self._session = self._sub, self._session, None, None
        with contextlib.suppress(Exception):  # already closed
            if sub is not None:
                sub.undeclare()
        with contextlib.suppress(Exception):
            if session is not None:
                session.close()


def _progress_line(
    elapsed: float, duration: float, length: float, mcap: Path, health: _Health
) -> str:
    if elapsed > duration:
        return f"demo: recording done ({duration:.0f} s), the daemon is closing {mcap.name}"
    robot_s = min(length, elapsed * length / max(duration, 1e-9))
    try:
        size = f"{mcap.stat().st_size / 1e6:.1f} MB"
    except OSError:
        size = "0 MB"
    devices = ", ".join(f"{k} {v:,}" for k, v in sorted(health.samples.items()))
    return (
        f"demo: recording {elapsed:3.0f} / {duration:.0f} s ({100 * elapsed / duration:3.0f} %), "
        f"robot time {robot_s:.0f} / {length:.0f} s, {mcap.name} {size}"
        + (f"; samples: {devices}" if devices else "")
    )


def _follow(
    proc: subprocess.Popen[str],
    duration: float,
    length: float,
    mcap: Path,
    port: int,
    every_s: float,
) -> list[str]:
    """The daemon's stdout lines, once it has stopped; meanwhile progress: on a terminal
    one line rewritten every second, else a line every ``every_s`` seconds (0: none)."""
    import queue
    import threading

    lines: list[str] = []
    q: queue.SimpleQueue[str | None] = queue.SimpleQueue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            q.put(line)
        q.put(None)

    threading.Thread(target=pump, name="daq-run-stdout", daemon=True).start()
    tty = sys.stdout.isatty()
    period = 1.0 if tty else every_s
    t0 = time.monotonic()
    next_t = t0 + period
    health: _Health | None = None
    shown = False
    # bounded: the daemon stops by itself after ``duration``; allow it a generous end
    deadline = t0 + duration + 120.0
    try:
        while time.monotonic() < deadline:
            try:
                line = q.get(timeout=0.2)
            except queue.Empty:
                line = ""
            if line is None:
                break
            if line:
                lines.append(line)
                if health is None and period > 0 and line.startswith('{"daq": "running"'):
                    health = _Health(port)
                    t0 = time.monotonic()  # the daemon's --duration runs from here
                    next_t = t0 + period
            now = time.monotonic()
            if period > 0 and now >= next_t and health is not None:
                text = _progress_line(now - t0, duration, length, mcap, health)
                print(("\r" + text + "  ") if tty else text, end="" if tty else "\n", flush=True)
                shown = True
                next_t += period * max(1, int((now - next_t) // period) + 1)
        else:
            raise SystemExit(f"demo: daq run did not stop within {duration + 120:.0f} s")
    finally:
        if health is not None:
            health.close()
        if tty and shown:
            print(flush=True)
    proc.wait(30)
    return lines


def build_parser() -> argparse.ArgumentParser:
    from edges.options import OptionParser, integer, number, path_text

    p = OptionParser(prog="python -m daq.demo", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=path_text, default="demo-out", help="output directory")
    p.add_argument("--robot", default="kr500")
    p.add_argument("--seed", type=integer(0), default=3)
    p.add_argument(
        "--speed",
        type=number(0.0, above=True, hi=10_000.0),
        default=100.0,
        help="simulated clock speed (100)",
    )
    p.add_argument("--effect", default="gravity_deflection", choices=EFFECTS)
    p.add_argument(
        "--rate",
        type=number(0.0, above=True, hi=100_000.0),
        default=1000.0,
        help="device rates, Hz (1000)",
    )
    p.add_argument("--no-encoders", action="store_true", help="leave the motor encoders out")
    p.add_argument("--batch-age-s", type=number(0.0), default=0.02, help="daemon batch age (0.02)")
    p.add_argument("--margin-s", type=number(0.0), default=8.0, help="extra recording time (8 s)")
    p.add_argument(
        "--port", type=integer(1, 65535), default=17447, help="zenoh port on 127.0.0.1 (17447)"
    )
    p.add_argument("--record-only", action="store_true", help="stop after the recording")
    p.add_argument(
        "--progress-s",
        type=number(0.0),
        default=10.0,
        help="a progress line this often while recording, when not on a terminal "
        "(10 s; on a terminal one line updated every second; 0: none)",
    )
    p.add_argument(
        "--plan",
        type=path_text,
        metavar="DIR",
        help="run the planned campaign of twin plan --out DIR (its campaign_joints.csv) "
        "instead of random poses, the tracker's line of sight on (default: random poses)",
    )
    p.add_argument("--mcap", type=path_text, help="recording path (default OUT/campaign.mcap)")
    return p


def _check_outputs(out_dir: Path, mcap: Path) -> None:
    """Refuse before anything runs: ``--out`` a file, the recording a directory or
    where nothing can be written (the recording is streamed, not staged)."""
    from daq.errors import DaqError
    from daq.recording_writer import check_stream_output

    if out_dir.exists() and not out_dir.is_dir():
        raise DaqError(f"--out {out_dir}: exists and is not a directory")
    for parent in out_dir.parents:
        if parent.exists():
            if not parent.is_dir():
                raise DaqError(f"--out {out_dir}: {parent} is not a directory")
            break
    if mcap.parent == out_dir and not out_dir.exists():
        return  # created below, with the directory
    check_stream_output(mcap, "--mcap", [out_dir / "sim-cell.toml"], create_dirs=True)


def _main(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    out_dir = Path(args.out)
    mcap = Path(args.mcap) if args.mcap else out_dir / "campaign.mcap"
    _check_outputs(out_dir, mcap)
    prepared = prepare(args, out_dir / "sim-cell.toml")
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = record(args, out_dir, mcap, prepared)
    if args.record_only:
        return 0
    from calibration.cli import main as twin_main

    t0 = time.perf_counter()
    twin_out = out_dir / "twin"
    twin_args = ["run", "--replay", str(mcap), "--robot", args.robot, "--out", str(twin_out)]
    if args.plan:  # the plan's identify poses come first
        twin_args += ["--identify-poses", str(prepared[2])]
    print(f"demo: twin {' '.join(twin_args)}", flush=True)
    rc = twin_main(twin_args)
    twin_s = time.perf_counter() - t0
    total = time.perf_counter() - started
    print(
        f"demo: recording {rec['record_s']:.0f} s, twin {twin_s:.0f} s, total {total:.0f} s "
        f"(wall); recording {rec['mcap_bytes'] / 1e6:.1f} MB",
        flush=True,
    )
    return rc


def main(argv: list[str] | None = None) -> int:
    """Options checked first (one line, exit 2), then the run behind the boundary."""
    from daq.errors import DaqError
    from edges.command import run_command, take_debug_flag

    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    from calibration.errors import CalibrationError
    from sim_devices.errors import SimError

    errors: tuple[type[BaseException], ...] = (DaqError, CalibrationError, SimError)
    return run_command("python -m daq.demo", lambda: _main(args), user_errors=errors, debug=debug)


if __name__ == "__main__":
    sys.exit(main())
