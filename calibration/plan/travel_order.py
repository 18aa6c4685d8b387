"""The order a campaign's poses are measured in: short, and not a function of the clock.

A leg takes ``max_j |Δq_j| / v_j`` (synchronous PTP at the joints' top speeds). The
shortest closed tour from Home (nearest neighbour, then 2-opt) sweeps the region once, so a
pose's time is a smooth function of where it is: a drift in time (the arm warming up, the
tracker's air) is then a smooth function of the pose as well, and the fit takes it into the
geometry. **Forward then back** (``passes=2``, ``twin plan``'s default) measures one of
every two neighbouring poses of that tour on the way out and the other on the way back
(which one goes which way chosen by the planner's drift criterion, then for the shorter
travel), so neighbouring poses are half a campaign apart in time and the mean time along
the path is the same everywhere: a drift linear in time is orthogonal to any smooth
function of the pose (the reversal a metrologist uses against drift, as the scale sweeps'
forward and backward passes do).
It costs travel, 1.2–1.3× the one-pass tour; on a steady arm it changes nothing but the
noise draw each pose gets, on a drifting one it lowers the error (docs/planning.md, "The
order against a drift in time").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
#: The bias a drift in time would leave in the twin fitted from a campaign measured in
#: this order (rows of the poses, first measured first): mm² over the region per mm² of
#: drift, lower is better (:func:`calibration.plan.plan_criterion.drift_bias` of the
#: identification poses).
DriftCost = Callable[[IntArray], float]

#: The orders a plan may take: one pass (the shortest tour), or forward then back.
PASSES = (1, 2)
#: Within a pass of the forward-then-back order, 2-opt reverses runs of at most this
#: fraction of the pass: short enough that the pass keeps its direction along the path.
_LOCAL_FRACTION = 0.2
#: Sweeps over the pairs of the forward-then-back order, swapping which of a pair goes
#: back, at most (a bound; they stop at the first sweep that shortens nothing).
_MAX_SWAP_SWEEPS = 10


@dataclass(frozen=True, eq=False)
class TravelOrder:
    """A closed tour from Home: ``order`` (rows of the poses), leg times and total (s)."""

    order: IntArray
    time_s: float
    random_time_s: float  # mean over random orders of the same poses
    via_home: IntArray  # positions in ``order`` reached through Home (a direct leg collides)
    back_from: int = -1  # the position in ``order`` where the way back starts (-1: one pass)
    #: the drift's bias (:data:`DriftCost`) of this order, of the one-pass tour and the mean
    #: of the random orders' (NaN when no drift criterion was given)
    drift_bias: tuple[float, float, float] = (np.nan, np.nan, np.nan)

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


def _ranks(g: NDArray[np.int_]) -> NDArray[np.int_]:
    """Each node's rank among the nodes of its own group, in path order."""
    rank = np.zeros(len(g), dtype=int)
    for value in np.unique(g):
        rank[g == value] = np.arange(np.count_nonzero(g == value))
    return rank


def _two_passes(path: IntArray, back: NDArray[np.bool_]) -> IntArray:
    """Home, the nodes of ``path`` not ``back`` in path order, then the others reversed."""
    return np.concatenate([[0], path[~back], path[back][::-1]]).astype(np.intp)


def _pair_partners(g: NDArray[np.int_], offset: int) -> NDArray[np.intp]:
    """For the first node of every two consecutive nodes of a group (pairs from its rank
    ``offset`` on) the other's index; −1 elsewhere."""
    partner = np.full(len(g), -1, dtype=np.intp)
    for value in np.unique(g):
        nodes = np.flatnonzero(g == value)
        first = nodes[offset : len(nodes) - 1 : 2]
        partner[first] = nodes[offset + 1 :: 2][: len(first)]
    return partner


def _swap_pairs(
    back: NDArray[np.bool_],
    partner: NDArray[np.intp],
    cost: Callable[[NDArray[np.bool_]], float],
    allowed: Callable[[NDArray[np.bool_]], bool] = lambda b: True,
) -> NDArray[np.bool_]:
    """``back`` with a pair's two swapped between the passes while a swap lowers ``cost``
    (and the split stays ``allowed``, asked only of a swap that lowers it)."""
    back = back.copy()
    best = cost(back)
    for _ in range(_MAX_SWAP_SWEEPS):
        improved = False
        for a in np.flatnonzero(partner >= 0):
            pair = [a, partner[a]]
            back[pair] = back[pair[::-1]]
            c = cost(back)
            if c < best - 1e-12 * abs(best) and allowed(back):
                best, improved = c, True
            else:
                back[pair] = back[pair[::-1]]
        if not improved:
            break
    return back


def _split_pairs(
    times: FloatArray,
    path: IntArray,
    g: NDArray[np.int_],
    offset: int,
    bias: Callable[[NDArray[np.bool_]], float],
    bound: float,
) -> NDArray[np.bool_]:
    """Which nodes of ``path`` go back (of every two consecutive nodes of a group one each
    way; a node left over alternates), from the alternate split: the pairs swapped first to
    lower the drift's ``bias``, then to shorten the travel while it stays at most
    ``bound``."""
    back = (_ranks(g) + offset) % 2 == 1
    partner = _pair_partners(g, offset)
    back = _swap_pairs(back, partner, bias)
    return _swap_pairs(
        back,
        partner,
        lambda b: tour_time_s(times, _two_passes(path, b)),
        lambda b: bias(b) <= bound,
    )


def _local_two_opt(times: FloatArray, t: IntArray, split: int) -> IntArray:
    """2-opt inside each pass (way out ``[1, split)``, way back ``[split, …)``) on runs of
    at most :data:`_LOCAL_FRACTION` of it."""
    for lo, hi in ((1, split), (split, len(t))):
        t = _two_opt(times, t, lo, hi, longest=max(3, int(_LOCAL_FRACTION * (hi - lo))))
    return t


def forward_then_back(
    times: FloatArray,
    tour: IntArray,
    group: NDArray[np.int_] | None = None,
    drift: DriftCost | None = None,
) -> tuple[IntArray, int]:
    """The closed tour ``tour`` (node 0 = Home first) as two passes: of every two poses
    next to each other along it within a ``group`` (per node, Home's ignored: the
    identification and the validation poses are paired apart, so each set is measured
    forward then back) one on the way out in tour order, the other on the way back; then
    2-opt inside each pass on short runs only, so each keeps its direction along the path.
    Which of a pair goes which way alternates; with ``drift`` (:data:`DriftCost`; rows of
    the poses = nodes − 1) it is chosen to lower the bias a drift would leave, then to
    shorten the travel, and the shortest order found (the pairs taken from either end)
    whose bias is at most the alternate order's is kept, so neither its travel nor its
    bias is above that order's. Also the position (in the order, Home not counted) where
    the way back starts. A pair's two poses keep their places in the passes whichever
    goes which way, so the pair's mean time is half the campaign either way."""
    path = tour[1:]
    g = np.zeros(len(path), dtype=int) if group is None else np.asarray(group)[path]

    def orders(back: NDArray[np.bool_]) -> tuple[IntArray, IntArray, int]:
        """The split's order, the same after 2-opt inside the passes, the way back's start."""
        t = _two_passes(path, back)
        split = 1 + int(np.count_nonzero(~back))
        return t, _local_two_opt(times, t, split), split - 1

    _, best, back_from = orders(_ranks(g) % 2 == 1)
    if drift is None:
        return best, back_from
    bound = drift(best[1:] - 1)
    best_time = tour_time_s(times, best)

    def bias(back: NDArray[np.bool_]) -> float:
        return drift(_two_passes(path, back)[1:] - 1)

    for offset in (0, 1):
        plain, local, split = orders(_split_pairs(times, path, g, offset, bias, bound))
        # 2-opt's order unless it raised the bias above the bound, then the split's own
        t = next((t for t in (local, plain) if drift(t[1:] - 1) <= bound), None)
        if t is not None and tour_time_s(times, t) < best_time:
            best, best_time, back_from = t, tour_time_s(times, t), split
    return best, back_from


def travel_order(
    q_rad: FloatArray,
    home_rad: FloatArray,
    speeds_rad_s: FloatArray,
    rng: np.random.Generator,
    passes: int = 1,
    group: NDArray[np.int_] | None = None,
    drift: DriftCost | None = None,
) -> TravelOrder:
    """A short closed tour from Home through every joint vector ``q_rad`` ``(N, n)``:
    nearest neighbour then 2-opt, as one pass or forward then back (``passes`` 2, module
    text; each ``group`` ``(N,)`` of poses, such as the identification set, split between
    the passes on its own, alternately or by ``drift``: :func:`forward_then_back`); the
    random baseline is the mean of 20 random orders, also of the drift's bias."""
    if passes not in PASSES:
        raise ValueError(f"passes must be one of {PASSES}, got {passes}")
    nodes = np.vstack([home_rad, q_rad])
    times = leg_times_s(nodes, speeds_rad_s)
    n = len(nodes)
    one = best = _shortest_tour(times)
    back_from = -1
    if passes == 2 and n > 4:
        groups = None if group is None else np.append(-1, group)
        best, back_from = forward_then_back(times, best, groups, drift)
    randoms = [np.concatenate([[0], 1 + rng.permutation(n - 1)]) for _ in range(20)]
    bias = (np.nan, np.nan, np.nan)
    if drift is not None:
        bias = (
            drift(best[1:] - 1),
            drift(one[1:] - 1),
            float(np.mean([drift(t[1:] - 1) for t in randoms])),
        )
    return TravelOrder(
        order=best[1:] - 1,
        time_s=tour_time_s(times, best),
        random_time_s=float(np.mean([tour_time_s(times, t) for t in randoms])),
        via_home=np.empty(0, dtype=np.intp),
        back_from=back_from,  # three poses or fewer: one pass even when two were asked
        drift_bias=bias,
    )
