"""Kinematics speed: forward kinematics, Jacobians and inverse kinematics of the KR500 preset.

Each row times our vectorized call on all ``n`` poses against, in the same run,

* ``loop``: the same function of ours called once per pose in a Python loop, measured on
  the first ``loop_measured_n`` poses and scaled to ``n`` (per-pose cost × n);
* ``rtb``: roboticstoolbox-python on an ETS of the same model (checked equal in
  ``tests/test_reference_crosscheck.py``): ``fkine`` on an array of joint vectors, and
  ``jacob0`` / ``ik_LM`` (its C++ Levenberg-Marquardt; rtb has no analytic IK for a
  general arm) once per pose, measured on ``rtb_measured_n`` poses and scaled to ``n``.

``speedup_vs_*`` is that time divided by ours. The issue's targets: >= 10 vs the loop, >= 1
vs rtb. The rtb IK solves one branch from a seed 0.05 rad (rms) from the answer ("the
previous sample"); ours solves all eight branches and selects (closed form, and the
calibrated model with ``branches="all"``), or polishes only the best seeds of a calibrated
model (``branches="chosen"``, the like-for-like row); both to ~1e-9 mm.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from benchmarks import Row, best_time
from calibration.model.description import load_robot
from calibration.model.ik_results import JointLimits
from calibration.model.inverse_kinematics import solve_ik
from calibration.model.kinematics import (
    KinematicModel,
    flange_poses,
    geometric_jacobian,
    identification_jacobian,
)

ROBOT = "kr500"
# work sizes: (n, per-pose loop subset, rtb subset)
FULL = {
    "fk": (1_000_000, 2_000, 100_000),
    "jac": (100_000, 1_000, 2_000),
    "ik": (10_000, 200, 1_000),
}
QUICK = {"fk": (2_000, 20, 200), "jac": (300, 10, 10), "ik": (40, 4, 4)}
SEED_NOISE_RAD = 0.05
RTB_IK_TOL = 1e-18  # rtb's residual E = ½·|e|², e in mm and rad: |e| <= 1.4e-9


def reference_ets(
    model: KinematicModel, limits: JointLimits | None = None, *, tcp: bool = False
) -> Any:
    """rtb ETS of ``model`` in the world frame (base pose in front), flange or TCP last."""
    from roboticstoolbox import ET

    (x, y, z), (rx, ry, rz) = model.base_mm, model.base_rad
    ets = ET.tx(x) * ET.ty(y) * ET.tz(z) * ET.Rz(rz) * ET.Ry(ry) * ET.Rx(rx)
    for i in range(model.n_joints):
        qlim = None if limits is None else [limits.lower_rad[i], limits.upper_rad[i]]
        # One ET at a time: rtb numbers the joints in the order they are appended.
        ets = ets * ET.Rx(model.alpha_rad[i]) * ET.tx(model.a_mm[i]) * ET.Ry(model.beta_rad[i])
        ets = ets * ET.Rz(model.theta_offset_rad[i]) * ET.Rz(qlim=qlim) * ET.tz(model.d_mm[i])
    if tcp:
        ets = ets * ET.tx(model.tool_mm[0]) * ET.ty(model.tool_mm[1]) * ET.tz(model.tool_mm[2])
    return ets


def calibrated(model: KinematicModel, seed: int = 0) -> KinematicModel:
    """A non-spherical 'calibrated' model: ~1 mm, ~0.1° deviations including betas."""
    rng = np.random.default_rng(seed)
    x = model.parameter_vector().copy()
    per_joint = x[:30].reshape(6, 5)
    per_joint[:, [0, 2]] += rng.normal(0.0, 1.0, (6, 2))
    per_joint[:, [1, 3, 4]] += rng.normal(0.0, np.radians(0.1), (6, 3))
    return model.with_parameters(x)


def _per_pose(fn: Callable[[np.ndarray], object], items: np.ndarray) -> Callable[[], None]:
    def loop() -> None:
        for item in items:
            fn(item)

    return loop


def _row(
    benchmark: str,
    n: int,
    ours_s: float,
    loop: tuple[float, int],
    rtb: tuple[float, int],
    note: str,
    **extra: object,
) -> Row:
    """One table row; loop and rtb are (seconds, poses measured), scaled here to ``n``."""
    (loop_s, loop_n), (rtb_s, rtb_n) = loop, rtb
    loop_scaled, rtb_scaled = loop_s / loop_n * n, rtb_s / rtb_n * n
    return {
        "benchmark": benchmark,
        "n": n,
        "ours_s": ours_s,
        "ours_us_per_pose": ours_s / n * 1e6,
        "loop_s": loop_scaled,
        "loop_measured_n": loop_n,
        "rtb_s": rtb_scaled,
        "rtb_measured_n": rtb_n,
        "speedup_vs_loop": loop_scaled / ours_s,
        "speedup_vs_rtb": rtb_scaled / ours_s,
        "targets_met": bool(loop_scaled / ours_s >= 10 and rtb_scaled / ours_s >= 1),
        **extra,
        "note": note,
    }


def run(quick: bool) -> list[Row]:
    """Time FK (1e6 poses), Jacobians (1e5) and IK (1e4); tiny sizes when ``quick``."""
    sizes = QUICK if quick else FULL
    repeat = 3 if quick else 2  # best-of: the machine may be shared
    desc = load_robot(ROBOT)
    model = KinematicModel.from_description(desc)
    limits = JointLimits.from_description(desc)
    rng = np.random.default_rng(2024)
    rows: list[Row] = []

    # Forward kinematics: flange poses in the world frame.
    n, n_loop, n_rtb = sizes["fk"]
    q = rng.uniform(limits.lower_rad, limits.upper_rad, (n, 6))
    flange = reference_ets(model, limits)
    ours = best_time(lambda: flange_poses(model, q), repeat)
    loop = best_time(_per_pose(lambda qi: flange_poses(model, qi), q[:n_loop]), repeat)
    rtb = best_time(lambda: flange.fkine(q[:n_rtb]), repeat)
    check = np.abs(np.array(flange.fkine(q[:20]).A) - flange_poses(model, q[:20])).max()
    rows.append(
        _row(
            "forward kinematics, flange pose (world)",
            n,
            ours,
            (loop, n_loop),
            (rtb, n_rtb),
            "rtb: fkine on an (N, 6) array",
            max_diff_vs_rtb=float(check),
        )
    )

    # Jacobians at the TCP.
    n, n_loop, n_rtb = sizes["jac"]
    q = q[:n]
    tcp = reference_ets(model, limits, tcp=True)
    rtb = best_time(_per_pose(tcp.jacob0, q[:n_rtb]), repeat)
    ours = best_time(lambda: identification_jacobian(model, q), repeat)
    loop = best_time(_per_pose(lambda qi: identification_jacobian(model, qi), q[:n_loop]), repeat)
    rows.append(
        _row(
            "identification Jacobian 3x39 (TCP, world)",
            n,
            ours,
            (loop, n_loop),
            (rtb, n_rtb),
            "rtb has none: its 6x6 jacob0 per pose is the nearest work",
        )
    )
    ours = best_time(lambda: geometric_jacobian(model, q, frame="world"), repeat)
    loop = best_time(
        _per_pose(lambda qi: geometric_jacobian(model, qi, frame="world"), q[:n_loop]), repeat
    )
    check = np.abs(
        np.stack([tcp.jacob0(qi) for qi in q[:20]])
        - geometric_jacobian(model, q[:20], frame="world")
    ).max()
    rows.append(
        _row(
            "geometric Jacobian 6x6 (TCP, world)",
            n,
            ours,
            (loop, n_loop),
            (rtb, n_rtb),
            "rtb: jacob0 per pose",
            max_diff_vs_rtb=float(check),
        )
    )

    # Inverse kinematics: the nominal (closed form) and a calibrated model (LM polish).
    for label, geometry, branches in (
        ("nominal, closed form", model, "all"),
        ("calibrated, + LM, all branches", calibrated(model), "all"),
        ("calibrated, + LM, chosen branch", calibrated(model), "chosen"),
    ):
        # The same poses and seeds for every IK row: rtb's time depends on the sample.
        ik_rng = np.random.default_rng(7)
        rows.append(_ik_row(label, geometry, branches, limits, sizes["ik"], 3, ik_rng))
    return rows


def _ik_row(
    label: str,
    model: KinematicModel,
    branches: Literal["all", "chosen"],
    limits: JointLimits,
    sizes: tuple[int, int, int],
    repeat: int,
    rng: np.random.Generator,
) -> Row:
    n, n_loop, n_rtb = sizes
    q = rng.uniform(limits.lower_rad, limits.upper_rad, (n, 6))
    poses = flange_poses(model, q)
    q_now = q + rng.normal(0.0, SEED_NOISE_RAD, q.shape)  # "the previous sample"
    ets = reference_ets(model, limits)

    def ours(sl: slice) -> Any:
        return solve_ik(
            model,
            poses[sl],
            frame="world",
            limits=limits,
            q_current_rad=q_now[sl],
            branches=branches,
        )

    def rtb() -> list[bool]:
        return [
            ets.ik_LM(poses[i], q0=q_now[i], slimit=1, tol=RTB_IK_TOL).success for i in range(n_rtb)
        ]

    ours_s = best_time(lambda: ours(slice(None)), repeat)
    loop_s = best_time(_per_pose(lambda i: ours(slice(i, i + 1)), np.arange(n_loop)), repeat)
    rtb_s = best_time(rtb, repeat)
    result = ours(slice(None))
    return _row(
        f"inverse kinematics, {label}",
        n,
        ours_s,
        (loop_s, n_loop),
        (rtb_s, n_rtb),
        f"ours: {'8 branches' if branches == 'all' else 'best seeds'} + selection; "
        "rtb: ik_LM, 1 branch, seeded",
        ours_found=float(np.mean(result.selection.found)),
        ours_max_residual_mm=float(np.nanmax(result.residual_mm)),
        rtb_success=float(np.mean(rtb())),
    )
