"""Each joint's sweep configuration: the other joints' angles while it was swept, read at
its sweep stops through a round's scale maps.

A scale map fitted on a sweep absorbs the swept link's gravity deflection in that sweep's
configuration, so the closed loop's gravity term is relative to it
(:attr:`~calibration.effects.effect_base.EffectData.sweep_reference`). The default sweep
holds the other joints at Home; a planned one (``[cell] plan_sweeps``, the plan's
``sweeps.csv``) holds them where the plan put them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from calibration.model.description import RobotDescription
from calibration.scales.chain_scale import ScaleCampaignResult
from calibration.scales.grating_scale import JointSweep

FloatArray = NDArray[np.float64]

#: A joint whose median reading over another joint's sweep stops is within this of Home
#: (deg, 180″) is taken at Home exactly: far above how far a joint held at Home reads off
#: it (gear torsion and backlash under the changing load: up to 26″ in the emulator's scale
#: campaign, seed 1, ``tests/calibration/test_sweep_configuration.py``), far below a planned
#: position (degrees), so that a campaign swept at Home keeps exactly the Home reference.
HOME_SNAP_DEG = 0.05


def stop_angles_rad(
    robot: RobotDescription, scales: ScaleCampaignResult, sweep: JointSweep
) -> FloatArray:
    """Every joint's angle ``(S, n)`` rad at a sweep's stops, its raw readings
    (``chain_counts``) read through ``scales``."""
    by_joint = {r.joint: r.scale for r in scales}
    assert sweep.chain_counts is not None
    return np.radians(
        np.column_stack(
            [
                by_joint[i + 1].counts_to_joint_deg(sweep.chain_counts[:, i])
                for i in range(robot.n_joints)
            ]
        )
    )


def sweep_configurations(
    robot: RobotDescription, sweeps: Mapping[int, JointSweep], scales: ScaleCampaignResult
) -> FloatArray:
    """Per joint ``(n, n)`` rad, row j the configuration joint j+1 was swept in: the median
    over its stops of the other joints' angles (:func:`stop_angles_rad`), each within
    :data:`HOME_SNAP_DEG` of Home taken as Home. Its own entry, and the row of a joint not
    swept (or swept without every joint's readings), are Home."""
    n = robot.n_joints
    home = np.radians(np.asarray(robot.home, dtype=float))
    configs = np.tile(home, (n, 1))
    for j, sweep in sweeps.items():
        if sweep.chain_counts is None:
            continue
        median = np.median(stop_angles_rad(robot, scales, sweep), axis=0)
        near = np.abs(np.degrees(median - home)) <= HOME_SNAP_DEG
        near[j - 1] = True  # the swept joint's own entry: unused
        configs[j - 1] = np.where(near, home, median)
    return configs
