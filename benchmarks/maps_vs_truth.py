"""The twin's scale maps of a recording against the emulated cell's true strips.

    python -m benchmarks.maps_vs_truth demo-out/campaign.mcap demo-out/sim-cell.toml

Runs the twin's joint fit on the recording (``calibration.twin.fit_rounds``: phases, pairing,
maps in chain order, identification, closed loop, the deflection taken out of the sweeps)
and prints, per round and joint, the terms the map kept, its relation residual, the RMS
over the sweep stops of the map minus the true strip relation (from the emulator's
configuration: the same cell, its strips), and what each round's closed loop added. The
truth is read from the emulator (``sim_devices``); the twin never sees it.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from calibration.errors import CalibrationError
from calibration.model.description import load_robot
from calibration.scales.scale_relation import ARCSEC_PER_DEG, COUNTER_MODULUS
from calibration.twin.campaign_measurement import measure_campaign
from calibration.twin.fit_rounds import calibrate_twin
from calibration.twin.streams import read_recording_streams
from daq.errors import DaqError
from edges.command import run_command, take_debug_flag
from edges.options import OptionParser
from sim_devices.config import load_cell
from sim_devices.errors import SimError
from sim_devices.plant import Plant
from sim_devices.truth import GratingStrip


def ring_angle_rad(strip: GratingStrip, counts: np.ndarray) -> np.ndarray:
    """The true ring angle of raw counter values (Newton on the strip's relation)."""
    k = strip.radius_mm * (1 + 1e-6 * strip.scale_error_ppm) * strip.counts_per_mm
    k *= strip.direction
    half = COUNTER_MODULUS / 2
    unwrapped = strip.zero_counts + np.mod(counts - strip.zero_counts + half, COUNTER_MODULUS)
    unwrapped -= half
    q = (unwrapped - strip.zero_counts) / k
    for _ in range(8):
        slope = k + strip.direction * strip.eccentricity_mm * strip.counts_per_mm * np.cos(
            q + strip.eccentricity_phase_rad
        )
        q = q - (strip.ideal_counts(q) - unwrapped) / slope
    return q


def main(argv: list[str] | None = None) -> int:
    argv, debug = take_debug_flag(sys.argv[1:] if argv is None else argv)
    parser = OptionParser(prog="python -m benchmarks.maps_vs_truth", description=__doc__)
    parser.add_argument("recording", help="the MCAP of daq run on the emulated cell")
    parser.add_argument("sim_config", help="the cell's sim-cell.toml (the truth's source)")
    parser.add_argument(
        "--allow-partial", action="store_true", help="use a damaged recording's readable part"
    )
    args = parser.parse_args(argv)
    return run_command(
        "python -m benchmarks.maps_vs_truth",
        lambda: _compare(args),
        user_errors=(CalibrationError, SimError, DaqError),
        debug=debug,
    )


def _compare(args: argparse.Namespace) -> int:
    """Every joint-fit round's scale maps of ``args.recording`` against the cell's strips."""
    config = load_cell(args.sim_config)
    strips = Plant.from_config(config).cell.strips
    robot = load_robot(config.cell.robot)
    streams = read_recording_streams(args.recording, allow_partial=args.allow_partial)
    if streams.note:
        print(f"warning: {args.recording}: {streams.note}", file=sys.stderr)
    meas = measure_campaign(streams, robot)
    twin = calibrate_twin(meas)
    for k, rnd in enumerate(twin.rounds, start=1):
        print(f"round {k}: deflection taken out of the sweeps: {rnd.deflection_rad is not None}")
        for r in rnd.scales:
            strip = strips[r.joint - 1]
            counts = r.stop_counts
            true = ring_angle_rad(strip, counts) - ring_angle_rad(
                strip, np.array([r.scale.zero_counts])
            )
            err = (r.scale.counts_to_angle_deg(counts) - np.degrees(true)) * ARCSEC_PER_DEG
            print(
                f"  joint {r.joint}: terms {', '.join(r.scale.terms) or '-':<20} residual "
                f"{r.residual_rms_arcsec:5.2f}″  map − strip {np.sqrt(np.mean(err**2)):6.2f}″"
            )
        if rnd.loop is not None:
            stages = ", ".join(f"{s.label} {s.mean_ap('validate'):.4f}" for s in rnd.loop.stages)
            print(f"  closed loop (validation mean AP, mm): {stages}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
