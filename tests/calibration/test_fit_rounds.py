"""The joint fit's rounds (calibration.twin.fit_rounds) on a synthetic over-correction.

Each round takes a deflection out of the sweeps and its loop finds one back; here that
map is linear and over-corrects, ``found = d* − c·(taken − d*)`` with ``0 < c < 1``: an
error taken out comes back with the opposite sign, as the demo's rounds did (issue 29,
seed 13: the deflection of joints 2 and 3 up, down, up between rounds). No data, no loop:
the rounds' own bookkeeping, fast.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from calibration.twin import fit_rounds

FIXED = {1: np.full((6, 3), 2e-5), 2: np.full((5, 3), -1e-5)}  # d*, rad (S, n) per sweep
ERROR = 3e-5  # round 1's error, rad (15 times the noise's standard deviation per stop)
NOISE_VAR = 2e-12  # per stop and joint, rad²


def _rounds(monkeypatch: pytest.MonkeyPatch, c: float) -> list[Any]:
    """The rounds of an over-correcting joint fit (gain ``−c``), round 1's error
    :data:`ERROR` on every stop."""

    def found(taken: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        return {j: FIXED[j] - c * (taken[j] - FIXED[j]) for j in FIXED}

    def sweep_deflections(meas: Any, scales: Any, campaign: Any, loop: Any) -> Any:
        stops = sum(len(d) for d in FIXED.values())
        return found(scales), np.full(3, NOISE_VAR * stops)

    monkeypatch.setattr(fit_rounds, "sweep_deflections", sweep_deflections)
    first = SimpleNamespace(loop=None)
    start = {j: d + ERROR for j, d in FIXED.items()}

    def one_round(deflection: Any) -> Any:  # the round's "maps" are what it took out
        return SimpleNamespace(loop=None, scales=deflection, campaign=None,
                               deflection_rad=deflection)  # fmt: skip

    meas = SimpleNamespace(robot=None)
    return list(fit_rounds._refitted_rounds(meas, first, start, one_round, lambda _s: None))  # type: ignore[arg-type]


def _error(rnd: Any) -> float:
    """Largest distance (rad) of what the round took out from the fixed point."""
    return max(float(np.max(np.abs(rnd.deflection_rad[j] - FIXED[j]))) for j in FIXED)


def test_alternating_rounds_settle_on_the_fixed_point(monkeypatch: pytest.MonkeyPatch) -> None:
    """Gain −0.9: taken out as found, round 3's error is still 0.9 of round 1's, with the
    sign flipped (the rounds alternate). The twin's rounds take the mean of what they took
    out and what they found: the last round's error is a small fraction of the first's."""
    rounds = _rounds(monkeypatch, c=0.9)
    assert len(rounds) == fit_rounds.MAX_ROUNDS
    assert _error(rounds[1]) == pytest.approx(ERROR)
    assert _error(rounds[-1]) < 0.1 * ERROR


def test_a_converging_joint_fit_still_converges(monkeypatch: pytest.MonkeyPatch) -> None:
    """Gain −0.2 (a round corrects most of the error): the mean costs speed (round 3's
    error 0.4 of round 1's where taken out as found it would be 0.2), but the rounds still
    close in on the fixed point, and round 2 is untouched (round 1's deflection taken out
    whole)."""
    rounds = _rounds(monkeypatch, c=0.2)
    assert _error(rounds[1]) == pytest.approx(ERROR)
    assert _error(rounds[-1]) == pytest.approx(0.4 * ERROR)
