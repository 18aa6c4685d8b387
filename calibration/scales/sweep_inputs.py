"""What the scale calibration of one joint is given: its sweep stops (:class:`JointSweep`),
the tracker's data-sheet weights (:class:`TrackerSpec`) and the options
(:class:`ScaleOptions`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.scales.scale_relation import TERMS

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


PASSES: tuple[str, str] = ("forward", "backward")


MIN_STOPS_PER_PASS = 6


@dataclass(frozen=True)
class TrackerSpec:
    """Data-sheet MPE of the tracker: ``±(mpe_um + mpe_um_per_m · distance)`` at ``mpe_sigmas``.

    Gives the *relative* weights of the points (the tracker sits at the origin of its
    frame); the noise level itself is estimated from the residuals.
    """

    mpe_um: float = 15.0
    mpe_um_per_m: float = 6.0
    mpe_sigmas: float = 2.0

    def sigma_mm(self, points_mm: ArrayLike) -> FloatArray:
        """Per-axis standard deviation (mm) of a measurement of each point, ``(N,)``."""
        dist_m = np.linalg.norm(np.atleast_2d(points_mm), axis=-1) / 1000.0
        sigma: FloatArray = 1e-3 * (self.mpe_um + self.mpe_um_per_m * dist_m) / self.mpe_sigmas
        return sigma


# -- input and result types ----------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class JointSweep:
    """The sweep stops of one joint, in any order. Arrays ``(S,)`` / ``(S, 3)``.

    ``rows`` are the source-file row numbers (for messages), or -1. ``chain_counts``
    ``(S, n)`` holds every joint's raw grating reading at the stop (None: not recorded),
    for taking the other joints' motion out (:mod:`calibration.scales.chain_scale`).
    """

    joint: int
    pass_name: NDArray[np.str_]
    step: IntArray
    counts: IntArray
    points_mm: FloatArray
    rows: IntArray | None = None
    chain_counts: IntArray | None = None
    target: IntArray | None = None  # (S,) reflector of each row: T targets per stop

    @property
    def n_stops(self) -> int:
        """Stops (one per pass and step, whatever the number of targets)."""
        if self.target is None:
            return int(self.step.shape[0])
        return len({(p, int(k)) for p, k in zip(self.pass_name, self.step, strict=True)})

    @property
    def n_targets(self) -> int:
        return 1 if self.target is None else len(set(self.target.tolist()))


@dataclass(frozen=True)
class ScaleOptions:
    """Options of :func:`calibrate_joint`."""

    alpha: float = 0.01  # family-wise false-term rate per joint
    candidate_terms: tuple[str, ...] = tuple(TERMS)
    tracker: TrackerSpec = TrackerSpec()
    counts_per_mm: float = 1000.0  # strip resolution, for the effective radius
    step_deg: float = 2.0  # commanded step, for the zero from the sweep crossing
    outlier_alpha: float = 1e-3  # per-joint false wild-point rate (circle and relation)
    # 1σ read noise of the grating head at a stop before rounding to whole counts (the
    # rounding adds 1/12 count²): each stop's angle about the relation carries it
    read_noise_counts: float = 0.5
    min_stops_per_pass: int = MIN_STOPS_PER_PASS
