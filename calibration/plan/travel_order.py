"""The order a campaign's poses are measured in: short, and not a function of the clock.

A leg takes ``max_j |Δq_j| / v_j`` (synchronous PTP at the joints' top speeds). The
shortest closed tour from Home (nearest neighbour, then 2-opt) sweeps the region once, so a
pose's time is a smooth function of where it is: a drift in time (the arm warming up, the
tracker's air) is then a smooth function of the pose as well, and the fit takes it into the
geometry. **Forward then back** (``passes=2``, ``twin plan``'s default) measures every other
pose of that tour on the way out and the rest on the way back, so neighbouring poses are
half a campaign apart in time and the mean time along the path is the same everywhere: a
drift linear in time is orthogonal to any smooth function of the pose (the reversal a
metrologist uses against drift, as the scale sweeps' forward and backward passes do).
It costs travel, about 1.35× the one-pass tour; on a steady arm it changes nothing but the
noise draw each pose gets, on a drifting one it lowers the error (docs/planning.md, "The
order against a drift in time").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: The orders a plan may take: one pass (the shortest tour), or forward then back.
PASSES = (1, 2)
#: Within a pass of the forward-then-back order, 2-opt reverses runs of at most this
#: fraction of the pass: short enough that the pass keeps its direction along the path.
_LOCAL_FRACTION = 0.2


@dataclass(frozen=True, eq=False)
class TravelOrder:
    """A closed tour from Home: ``order`` (rows of the poses), leg times and total (s)."""

    order: IntArray
    time_s: float
    random_time_s: float  # mean over random orders of the same poses
    via_home: IntArray  # positions in ``order`` reached through Home (a direct leg collides)
    back_from: int = -1  # the position in ``order`` where the way back starts (-1: one pass)

    @property
    def passes(self) -> int:
        """1: the shortest tour; 2: forward then back (module text)."""
        return 1 if self.back_from < 0 else 2


def leg_times_s(q_rad: FloatArray, speeds_rad_s: FloatArray) -> FloatArray:
    """Synchronous PTP times ``(N, N)`` s between joint vectors ``(N, n)``."""
    d = np.abs(q_rad[:, None, :] - q_rad[None, :, :]) / speeds_rad_s
    times: FloatArray = d.max(axis=2)
    return times


def tour_time_s(times: FloatArray, tour: IntArray) -> float:
    """The time of the closed tour ``tour`` (node 0 = Home first, returning to it)."""
    path = np.append(tour, tour[0])
    return float(times[path[:-1], path[1:]].sum())


def _two_opt(
    times: FloatArray, tour: IntArray, lo: int = 1, hi: int | None = None, longest: int = 0
) -> IntArray:
    """2-opt on a closed tour until no reversal shortens it, reversing only runs inside
    positions ``[lo, hi)`` (default: all but position 0) of at most ``longest`` nodes
    (0: any length)."""
    t = tour.copy()
    n = len(t)
    hi = n if hi is None else hi
    improved = True
    while improved:
        improved = False
        for i in range(lo, hi - 1):
            end = hi if longest <= 0 else min(hi, i + longest)  # the run is t[i : i + j + 2]
            a, b = t[i - 1], t[i]
            c = t[i + 1 : end]
            d = t[(np.arange(i + 2, end + 1)) % n]
            delta = times[a, c] + times[b, d] - times[a, b] - times[c, d]
            j = int(np.argmin(delta))
            if delta[j] < -1e-9:
                t[i : i + j + 2] = t[i : i + j + 2][::-1]
                improved = True
    return t


def _shortest_tour(times: FloatArray) -> IntArray:
    """Nearest neighbour from node 0 (Home), then 2-opt."""
    n = len(times)
    tour = [0]
    left = np.ones(n, dtype=bool)
    left[0] = False
    for _ in range(n - 1):
        rest = np.flatnonzero(left)
        nxt = int(rest[np.argmin(times[tour[-1], rest])])
        tour.append(nxt)
        left[nxt] = False
    return _two_opt(times, np.array(tour, dtype=np.intp))


def forward_then_back(
    times: FloatArray, tour: IntArray, group: NDArray[np.int_] | None = None
) -> tuple[IntArray, int]:
    """The closed tour ``tour`` (node 0 = Home first) as two passes: every other pose of
    each ``group`` (per node, Home's ignored: the identification and the validation poses
    alternate apart, so each set is measured forward then back) in tour order forward,
    then the others backward; then 2-opt inside each pass on short runs only, so each
    keeps its direction along the path. Also the position (in the order, Home not counted)
    where the way back starts."""
    path = tour[1:]
    g = np.zeros(len(path), dtype=int) if group is None else np.asarray(group)[path]
    rank = np.zeros(len(path), dtype=int)
    for value in np.unique(g):
        rank[g == value] = np.arange(np.count_nonzero(g == value))
    out, back = path[rank % 2 == 0], path[rank % 2 == 1][::-1]
    t = np.concatenate([[0], out, back]).astype(np.intp)
    split = 1 + len(out)
    for lo, hi in ((1, split), (split, len(t))):
        t = _two_opt(times, t, lo, hi, longest=max(3, int(_LOCAL_FRACTION * (hi - lo))))
    return t, len(out)


def travel_order(
    q_rad: FloatArray,
    home_rad: FloatArray,
    speeds_rad_s: FloatArray,
    rng: np.random.Generator,
    passes: int = 1,
    group: NDArray[np.int_] | None = None,
) -> TravelOrder:
    """A short closed tour from Home through every joint vector ``q_rad`` ``(N, n)``:
    nearest neighbour then 2-opt, as one pass or forward then back (``passes`` 2, module
    text; each ``group`` ``(N,)`` of poses, such as the identification set, alternates
    between the passes on its own); the random baseline is the mean of 20 random orders."""
    if passes not in PASSES:
        raise ValueError(f"passes must be one of {PASSES}, got {passes}")
    nodes = np.vstack([home_rad, q_rad])
    times = leg_times_s(nodes, speeds_rad_s)
    n = len(nodes)
    best = _shortest_tour(times)
    back_from = -1
    if passes == 2 and n > 4:
        groups = None if group is None else np.append(-1, group)
        best, back_from = forward_then_back(times, best, groups)
    randoms = [
        tour_time_s(times, np.concatenate([[0], 1 + rng.permutation(n - 1)])) for _ in range(20)
    ]
    return TravelOrder(
        order=best[1:] - 1,
        time_s=tour_time_s(times, best),
        random_time_s=float(np.mean(randoms)),
        via_home=np.empty(0, dtype=np.intp),
        back_from=back_from,  # three poses or fewer: one pass even when two were asked
    )
