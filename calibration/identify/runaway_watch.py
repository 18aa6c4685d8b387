"""The watch over every accepted LM iterate: free parameters that ran away (non-finite,
or moved beyond what the arm's reach makes credible) or whose Jacobian column collapsed
are named, to be dropped before the identification restarts."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.errors import IdentificationError
from calibration.identify.identifiability import (
    NO_EFFECT,
    arm_reach_mm,
    column_rms,
)
from calibration.model.kinematics import (
    KinematicModel,
)
from edges.errors import NumericalError

FloatArray = NDArray[np.float64]


#: A free column whose RMS falls below this fraction of its start value has collapsed.
COLLAPSE_RATIO = 1e-6


#: Why a parameter is dropped during the iterations (details follow in parentheses).
COLLAPSED = NO_EFFECT + " during the iterations"


RAN_AWAY = "ran away during the iterations"


class RunAway(NumericalError):
    """Raised by :class:`RunawayWatch`: free parameters (full-vector index -> reason) to drop."""

    def __init__(self, reasons: dict[int, str]) -> None:
        super().__init__("; ".join(reasons.values()))
        self.reasons = reasons


def credible_moves(start: KinematicModel, meas: FloatArray, n_effects: int) -> FloatArray:
    """Largest credible |identified − start| ``(5n + 9 + n_effects,)`` (rad, mm).

    π for an angle; the arm's reach for a length of the arm or tool; for the base
    translation the reach plus the farthest point from the start base (every point lies
    within reach of the true base); no limit for effect parameters (arbitrary units).
    """
    reach = arm_reach_mm(start)
    far = float(np.max(np.linalg.norm(meas - start.base_mm, axis=1)))
    moves = [
        math.pi if n.endswith("_rad") else reach + far if n.startswith("base.") else reach
        for n in start.parameter_names()
    ]
    return np.concatenate([moves, np.full(n_effects, np.inf)])


@dataclass(frozen=True)
class RunawayWatch:
    """Checks every accepted LM iterate of one run for free parameters that ran away
    (non-finite, or moved beyond credibility) or whose column collapsed."""

    names: tuple[str, ...]  # (k,) free parameter names
    index: NDArray[np.intp]  # (k,) their positions in the full vector
    x_start: FloatArray  # (k,) at the start point
    max_move: FloatArray  # (k,)
    start_rms: FloatArray  # (k,) column RMS of this run's weighted Jacobian at the start

    def __call__(self, nit: int, x: FloatArray, f: FloatArray, j: FloatArray) -> None:
        why = self.reasons(nit, x, j)
        if not why and not np.all(np.isfinite(f)):
            raise IdentificationError(f"the residuals are not finite at iteration {nit}")
        if why:
            raise RunAway({int(self.index[i]): r for i, r in why.items()})

    def reasons(self, nit: int, x: FloatArray, j: FloatArray) -> dict[int, str]:
        """Free position -> why it must go, for the iterate ``x`` ``(k,)`` with the
        weighted Jacobian ``j`` ``(3m, k)``."""
        why: dict[int, str] = {}
        bad = ~np.isfinite(x) | ~np.all(np.isfinite(j), axis=0)
        for i in np.flatnonzero(bad).tolist():
            why[i] = f"{RAN_AWAY} (non-finite value or column at iteration {nit})"
        move = np.abs(x - self.x_start)
        for i in np.flatnonzero(move > self.max_move).tolist():
            why.setdefault(i, _moved(self.names[i], move[i], self.max_move[i], nit))
        ratio = column_rms(j) / self.start_rms
        for i in np.flatnonzero(ratio < COLLAPSE_RATIO).tolist():
            why.setdefault(
                i,
                f"{COLLAPSED} (its column fell to {ratio[i]:.1e} of its start RMS by "
                f"iteration {nit})",
            )
        return why


def _moved(name: str, move: float, limit: float, nit: int) -> str:
    if name.endswith("_rad"):
        return (
            f"{RAN_AWAY} (moved {math.degrees(move):.3g}° from its start by iteration "
            f"{nit}, beyond ±180°)"
        )
    return (
        f"{RAN_AWAY} (moved {move:.4g} mm from its start by iteration {nit}, beyond {limit:.0f} mm)"
    )
