"""The twin: robot description, kinematics, grating-scale calibration, identification,
the closed loop and compensation.

This package never imports ``sim_devices``: the twin must not know the emulator's truth.

The names below are the public API. The light ones are imported at once; the solvers
(``run_closed_loop``, ``calibrate_scales``, ``compensate``, ``identify``) on first use
(PEP 562), so a command that does not need them does not pay for their imports.
:func:`calibrate` is the one way from a campaign to a calibrated robot (identification,
then the closed loop), as ``twin identify`` and ``twin run`` use it::

    from calibration import calibrate, load_robot, read_campaign

    robot = load_robot("kr500")
    campaign = read_campaign("campaign.csv", robot.n_joints)
    result = calibrate(robot, campaign)
    result.description.save("calibrated.toml")
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from calibration.effects.calibrate import CalibrationResult, calibrate
from calibration.errors import CalibrationError, DataFileError, DescriptionError
from calibration.identify.campaign_files import Campaign, read_campaign, read_joint_readings
from calibration.model.description import RobotDescription, load_robot, preset_names
from calibration.model.ik_results import IKResult, JointLimits
from calibration.model.inverse_kinematics import select_solution, solve_ik
from calibration.model.kinematics import (
    KinematicModel,
    flange_poses,
    geometric_jacobian,
    identification_jacobian,
    tcp_positions,
)

if TYPE_CHECKING:
    from calibration.effects.closed_loop import ClosedLoopResult, run_closed_loop
    from calibration.effects.model_effects import predict_tcp
    from calibration.identify.identification import identify
    from calibration.identify.identification_result import IdentificationResult
    from calibration.scales.chain_scale import calibrate_scales
    from calibration.scales.scale_files import read_scale_toml
    from calibration.twin.compensation import CompensationResult, compensate

#: name -> module, imported on first use
_LAZY = {
    "calibrate_scales": "calibration.scales.chain_scale",
    "ClosedLoopResult": "calibration.effects.closed_loop",
    "run_closed_loop": "calibration.effects.closed_loop",
    "CompensationResult": "calibration.twin.compensation",
    "compensate": "calibration.twin.compensation",
    "IdentificationResult": "calibration.identify.identification_result",
    "identify": "calibration.identify.identification",
    "predict_tcp": "calibration.effects.model_effects",
    "read_scale_toml": "calibration.scales.scale_files",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'calibration' has no attribute {name!r}")


__all__ = [
    "CalibrationError",
    "CalibrationResult",
    "Campaign",
    "ClosedLoopResult",
    "CompensationResult",
    "DataFileError",
    "DescriptionError",
    "IKResult",
    "IdentificationResult",
    "JointLimits",
    "KinematicModel",
    "RobotDescription",
    "calibrate",
    "calibrate_scales",
    "compensate",
    "flange_poses",
    "geometric_jacobian",
    "identification_jacobian",
    "identify",
    "load_robot",
    "predict_tcp",
    "preset_names",
    "read_campaign",
    "read_joint_readings",
    "read_scale_toml",
    "run_closed_loop",
    "select_solution",
    "solve_ik",
    "tcp_positions",
]
