"""What the scale calibration of one joint found (:class:`JointScaleResult`): the Home zero,
the term tests, the stops' angles and residuals, the Cramér-Rao bound."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.scales.circle_fit import CircleFit
from calibration.scales.scale_relation import ARCSEC_PER_DEG, COUNTER_MODULUS, GratingScale
from calibration.scales.target_set_fit import TargetSetFit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


RESOLUTION_STD_COUNTS = 1.0 / math.sqrt(12.0)  # whole counts: rectangular ±½ count


@dataclass(frozen=True)
class HomeZero:
    """The counter value taken as Home and how it was obtained."""

    counts: float  # raw counter value in [0, 2³²)
    spread_counts: float  # standard deviation of the individual readings/estimates
    n: int
    source: str  # "home" (mean of the returns) or "sweep-crossing"

    @property
    def std_counts(self) -> float:
        """Standard deviation of the zero (the mean).

        The spread is floored at the counter's resolution (1/√12 count): identical whole
        readings do not make the zero exact.
        """
        return max(self.spread_counts, RESOLUTION_STD_COUNTS) / math.sqrt(max(self.n, 1))


@dataclass(frozen=True)
class TermTest:
    """Nested-model F-test of one candidate term."""

    term: str
    kept: bool
    f_statistic: float
    dof_term: int
    dof_residual: int
    p_value: float
    threshold: float  # the p-value below which the term is kept


@dataclass(frozen=True, eq=False)
class JointScaleResult:
    """Everything the calibration of one joint found. Arrays are over the S stops."""

    joint: int
    scale: GratingScale
    home: HomeZero
    # common circle of both sweeps (or the common fit of a target set), oriented with the
    # joint's + direction; one per sweep below, same orientation
    circle: CircleFit | TargetSetFit
    pass_circles: Mapping[str, CircleFit | TargetSetFit]
    tests: tuple[TermTest, ...]
    pass_name: NDArray[np.str_]  # (S,)
    step: IntArray  # (S,)
    offset_counts: FloatArray  # (S,) u: counts from the zero, unwrapped
    stop_angle_deg: FloatArray  # (S,) angle from the circle, relative to Home
    stop_angle_std_deg: FloatArray  # (S,) its standard deviation (common offset excluded)
    residual_deg: FloatArray  # (S,) circle angle minus relation (NaN for dropped stops)
    used: NDArray[np.bool_]  # (S,) stops used in the relation
    dropped: tuple[tuple[int, str], ...]  # (index in the JointSweep, reason with pass/step/row)
    variance_factor: float  # s² of the published relation (tracker noise relative to its model)
    crb_covariance_rad2: FloatArray  # (p, p) bound on the relation coefficients (rad units)
    notes: tuple[str, ...] = ()

    @property
    def residual_rms_deg(self) -> float:
        return float(np.sqrt(np.mean(self.residual_deg[self.used] ** 2)))

    @property
    def residual_rms_arcsec(self) -> float:
        return ARCSEC_PER_DEG * self.residual_rms_deg

    @property
    def strip_direction(self) -> int:
        """+1 when the counts rise with the joint angle, −1 otherwise."""
        return 1 if self.scale.scale_deg_per_count > 0 else -1

    @property
    def kept_terms(self) -> tuple[str, ...]:
        return self.scale.terms

    @property
    def tracker_sigma_um(self) -> float:
        """Tracker per-axis noise estimated from the common circle's residuals (median)."""
        return 1e3 * float(np.median(self.circle.point_sigma_mm))

    @property
    def stop_counts(self) -> FloatArray:
        """Raw counter value of every stop (float, wrapped), ``(S,)``."""
        return np.mod(self.offset_counts + self.scale.zero_counts, COUNTER_MODULUS)

    @property
    def stop_direction(self) -> FloatArray:
        """Direction of motion at every stop: −1 forward sweep, +1 backward, ``(S,)``."""
        return np.where(self.pass_name == "backward", 1.0, -1.0)

    def test(self, term: str) -> TermTest | None:
        """The selection test of ``term``, if it was a candidate."""
        return next((t for t in self.tests if t.term == term), None)

    @property
    def crb_angle_std_deg(self) -> FloatArray:
        """Cramér-Rao bound on the relation at every stop (zero excluded), ``(S,)`` deg."""
        s = np.zeros_like(self.offset_counts)  # direction average
        _, x = self.scale.basis.columns(self.offset_counts, s, self.scale.terms)
        cov = self.crb_covariance_rad2[1:, 1:]
        std: FloatArray = np.degrees(np.sqrt(np.einsum("ij,jk,ik->i", x, cov, x)))
        return std
