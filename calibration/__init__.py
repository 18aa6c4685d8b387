"""The twin: robot description, kinematics, grating-scale calibration, identification.

This package never imports ``sim_devices``: the twin must not know the emulator's truth.
"""

from calibration.description import RobotDescription, load_robot, preset_names
from calibration.errors import CalibrationError, DataFileError, DescriptionError
from calibration.inverse_kinematics import IKResult, JointLimits, select_solution, solve_ik
from calibration.kinematics import (
    KinematicModel,
    flange_poses,
    geometric_jacobian,
    identification_jacobian,
    tcp_positions,
)

__all__ = [
    "CalibrationError",
    "DataFileError",
    "DescriptionError",
    "IKResult",
    "JointLimits",
    "KinematicModel",
    "RobotDescription",
    "flange_poses",
    "geometric_jacobian",
    "identification_jacobian",
    "load_robot",
    "preset_names",
    "select_solution",
    "solve_ik",
    "tcp_positions",
]
