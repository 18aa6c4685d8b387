"""The tracker's step test: a CUSUM on the a-priori errors, and its false-alarm rate.

With ``S`` the predicted error covariance of a check and ``NIS = eᵀS⁻¹e`` (χ²₃ while the
model holds), relative to the recent error level ``L`` (an EWMA of NIS/3, at least 1), the
log-likelihood ratio of an error variance ``ρ_v`` times larger is
``ℓ = ½(1 − 1/ρ_v)·NIS/L − (3/2)·ln ρ_v``, capped at ``cap·h``;
``g(t) = max(0, g(t−1) + ℓ)`` and a step is declared when ``g > h``. How the tracker
uses it (a capped point held as a suspect, the memory reopened on a step):
:mod:`calibration.twin.tracking`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StepTest:
    """The CUSUM of the a-priori errors and what follows a step (module docstring)."""

    variance_ratio: float = 9.0  # ρ_v: the alternative, errors 3× the predicted σ
    threshold: float = 12.0  # h
    cap: float = 0.6  # one point adds at most cap·h
    reopen: float = 1e-3  # information kept when the memory reopens
    settle_nis: float = 11.34  # χ²₃ 99 %: a point that fits the followed model again
    settle_rows: int = 3  # consecutive fitting points that end the 'step' state
    level_smoothing: float = 0.95  # of the recent error level L (a memory of ~20 checks)
    level_max: float = 10.0  # one point raises L by at most this NIS/3

    def llr(self, nis: float) -> float:
        """ℓ of one point, capped (``nis``: its normalised innovation squared)."""
        rho = self.variance_ratio
        value = 0.5 * (1.0 - 1.0 / rho) * nis - 1.5 * math.log(rho)
        return min(value, self.cap * self.threshold)

    @property
    def suspect_llr(self) -> float:
        return self.cap * self.threshold


def false_alarm_rate(test: StepTest, rows: int, runs: int, seed: int = 0) -> float:
    """Steps per check the test declares when the model holds (NIS ~ χ²₃ drawn from
    ``seed``): ``runs`` runs of ``rows`` checks with :func:`track_update`'s rule (a capped
    suspect's share withdrawn when the next point is no suspect), restarted after a step.
    The error level L is held at 1 here (it only ever lowers ℓ): an upper bound."""
    rng = np.random.default_rng(seed)
    rho = test.variance_ratio
    nis = rng.chisquare(3, size=(rows, runs))
    llr = np.minimum(0.5 * (1.0 - 1.0 / rho) * nis - 1.5 * math.log(rho), test.suspect_llr)
    g = np.zeros(runs)
    held = np.full(runs, np.nan)  # the CUSUM before a held suspect
    alarms = 0
    for step in llr:
        suspect = step >= test.suspect_llr
        base = np.where(~np.isnan(held) & ~suspect, held, g)
        new = np.maximum(0.0, base + step)
        hit = new > test.threshold
        alarms += int(hit.sum())
        held = np.where(~hit & suspect & np.isnan(held), base, np.nan)
        g = np.where(hit, 0.0, new)
    return alarms / (rows * runs)
