"""The cost of following the robot: one tracker update against a batch refit, same run.

Data: the KR500 preset, seed 1, the default campaign calibrated (geometry), then an
8-hour production run with thermal growth, base creep and a remounted tool (240 checks).

Rows:

* ``track_update``: :func:`calibration.twin.tracking.track_update` over every check, default
  set (12 parameters): ``ours_ms_per_update`` (target <= 1 ms).
* ``batch refit``: what a tracker without the recursive form would do per check: a
  Gauss-Newton refit (3 iterations) of the same parameters over the last 30 checks
  (``identification_jacobian`` of the window each iteration), ``ms_per_update`` and
  ``update_speedup`` (its time / ours).
* ``identify``: a whole recalibration from the campaign's 100 identification poses
  (:func:`calibration.identify.identification.identify`), once: the cost a new campaign's fit has.

    python -m benchmarks.bench_tracking [--quick]
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from benchmarks import best_time, format_table
from calibration.effects.calibrate import calibrate
from calibration.identify.identification import identify
from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel, identification_jacobian
from calibration.twin.tracking import TrackingSetup, start_tracking, track_update, tracking_setup
from sim_devices.drift import CellDrift
from sim_devices.pose_campaign import (
    CampaignSettings,
    CheckProgram,
    emulated_campaign,
    emulated_checks,
)

Row = dict[str, Any]
WINDOW = 30
DRIFT = CellDrift(thermal=True, creep=True, steps=("tool_remount",))


def _updates(setup: TrackingSetup, q: np.ndarray, pts: np.ndarray) -> None:
    state = start_tracking(setup)
    for qi, pi in zip(q, pts, strict=True):
        state, _ = track_update(setup, state, qi, pi)


def _batch_refits(setup: TrackingSetup, q: np.ndarray, pts: np.ndarray) -> None:
    """Per check, Gauss-Newton on the window before it (3 iterations, the same ridge)."""
    k = len(setup.names)
    ridge = setup.settings.forgetting.damping * setup.sigma_mm**2 * np.eye(k)
    for i in range(1, len(q)):
        lo = max(0, i - WINDOW)
        theta = np.zeros(k)
        for _ in range(3):
            p, jac = identification_jacobian(setup.model(theta), q[lo:i])
            h = (jac @ setup.basis).reshape(-1, k)
            r = (pts[lo:i] - p).reshape(-1)
            theta = theta + np.linalg.solve(h.T @ h + ridge, h.T @ r)


def run(quick: bool) -> list[Row]:
    """Time the updates, the batch refits and one identification on the same data."""
    nominal = load_robot("kr500")
    data = emulated_campaign(nominal, 1)
    program = CheckProgram(hours=0.5 if quick else 8.0, drift=DRIFT)
    checks = emulated_checks(data, 1, program, CampaignSettings()).checks
    desc = calibrate(nominal, data.campaign, effects=False).description
    setup = tracking_setup(desc)
    q, pts = np.radians(checks.q_deg), checks.xyz_mm
    m = len(q)
    repeat = 1 if quick else 3
    ours = best_time(lambda: _updates(setup, q, pts), repeat)
    batch = best_time(lambda: _batch_refits(setup, q, pts), repeat)
    idm = data.campaign.mask("identify")
    model = KinematicModel.from_description(nominal)
    full = best_time(
        lambda: identify(model, data.campaign.q_rad[idm], data.campaign.xyz_mm[idm]), 1
    )
    per = 1e3 * ours / m
    return [
        {
            "benchmark": "track_update (default set)",
            "n": m,
            "parameters": len(setup.names),
            "ms_per_update": per,
            "note": "target <= 1 ms per update",
        },
        {
            "benchmark": f"batch refit, window {WINDOW}",
            "n": m - 1,
            "parameters": len(setup.names),
            "ms_per_update": 1e3 * batch / (m - 1),
            "update_speedup": (batch / (m - 1)) / (ours / m),
            "note": "Gauss-Newton, 3 iterations per check",
        },
        {
            "benchmark": "identify (100 poses)",
            "n": 1,
            "ms_per_update": 1e3 * full,
            "update_speedup": full / (ours / m),
            "note": "a whole recalibration, once",
        },
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_tracking")
    parser.add_argument("--quick", action="store_true", help="half an hour of checks: a smoke run")
    args = parser.parse_args(argv)
    print(format_table(run(args.quick)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
