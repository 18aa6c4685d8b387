"""Find the calibration campaign's phases in the grating data itself.

Nobody tells the twin what the robot is doing: the robot may run the emulator's program,
its own controller's or a pendant operator's. Everything here comes from the grating counts
``(N, n)`` and their mapped times ``(N,)``:

1. **Dwells.** A sample is *still* when no strip moved by more than ``still_counts`` to
   the previous and to the next sample (and no time gap separates them). A dwell is a run
   of at least ``min_dwell_samples`` still samples whose total span on every strip is at
   most ``span_counts`` (slow creep is not a dwell). A gap in the grating stream ends a
   dwell.
2. **Sweeps.** Between consecutive dwells one joint *steps* when it moved and every other
   joint moved by at most ``single_joint_ratio`` of that. A sweep pass is a run of at least
   ``min_sweep_stops`` - 1 steps of the same joint, in the same direction, of the same size
   (each within ``step_tolerance`` of the run's median step). A pass immediately followed by
   a pass of the same joint in the opposite direction shares its turn-around dwell with it.
   The first pass of a joint in time is ``forward``, the next ``backward`` (method.md §2:
   limit to limit, then back); the counts-to-angle sign is not assumed, the scale fit finds
   it from the circle.
3. **Home.** The Home reading of joint k is the median of joint k's counts over the sweep
   stops of the *other* joints (during the default campaign's sweeps every other joint
   sits at Home), where that is within ``span_counts`` of the most visited dwell position
   (the non-sweep dwells within ``home_tolerance`` sweep steps of one dwell on every
   joint: the Home returns, ~10 a joint, make it Home); else that position's median (a
   planned sweep holds the other joints away from Home). A dwell is *at Home* when every
   joint is within ``home_tolerance`` sweep steps of that vector.
4. **Home returns.** A Home dwell (not a sweep stop) approached by one joint alone (the
   other joints' excursion at most ``single_joint_ratio`` of its, counted from the last
   sample where another joint was away from Home), at the sweep speed: its
   final approach, from the last standstill or reversal, is no faster than
   ``home_speed_ratio`` times that joint's fastest sweep move (the method's returns and
   sweeps both run at 3 %). A quick return to Home (e.g. after a sweep) is not a return.
5. **Poses.** Every other dwell with at least two joints away from Home. In time order,
   the first ``identify_fraction`` of them (rounded, 100 of 250 for the method's
   campaign) are ``identify`` poses, the rest ``validate`` (method.md §3: 100
   identification poses, then 150 others); or the first ``identify_count`` (a planned
   campaign's, which the emulated cell runs identify poses first).
6. Everything else (dwells away from Home on one joint, Home dwells approached fast or by
   several joints) is ``other``, counted in the summary.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PhaseOptions:
    still_counts: int = 4
    span_counts: int = 12
    min_dwell_samples: int = 5
    gap_factor: float = 5.0  # a time step over this many median periods is a gap
    single_joint_ratio: float = 0.02
    step_tolerance: float = 0.03
    min_sweep_stops: int = 6
    home_tolerance: float = 0.25  # sweep steps
    home_speed_ratio: float = 1.5
    identify_fraction: float = 0.4
    #: the first this many poses are ``identify`` (a planned campaign's count, ``twin run
    #: --identify-poses``); None: ``identify_fraction`` of them
    identify_count: int | None = None


@dataclass(frozen=True)
class Dwell:
    """A stationary interval: grating sample indices ``[i0, i1]``, mapped times (ns)."""

    index: int
    i0: int
    i1: int
    t0_ns: int
    t1_ns: int
    counts: FloatArray  # (n,) mean counts over the dwell

    @property
    def duration_s(self) -> float:
        return (self.t1_ns - self.t0_ns) * 1e-9


@dataclass(frozen=True)
class SweepStop:
    joint: int  # 1-based
    pass_name: str  # "forward" | "backward"
    step: int
    dwell: int  # Dwell.index


@dataclass(frozen=True)
class HomeReturn:
    joint: int
    trial: int
    dwell: int
    approach: int  # +1 / -1: direction of the final approach in counts


@dataclass(frozen=True)
class Pose:
    name: str
    set: str  # identify | validate
    dwell: int


@dataclass
class Phases:
    """Everything found: dwells and what each one is."""

    dwells: list[Dwell]
    sweeps: list[SweepStop]
    home_returns: list[HomeReturn]
    poses: list[Pose]
    home_counts: FloatArray  # (n,), NaN where unknown
    step_counts: dict[int, float]  # joint -> median |counts per sweep step|
    other: list[int] = field(default_factory=list)  # dwell indices

    def summary(self) -> dict[str, Any]:
        passes: dict[str, dict[str, int]] = {}
        for s in self.sweeps:
            passes.setdefault(str(s.joint), {}).setdefault(s.pass_name, 0)
            passes[str(s.joint)][s.pass_name] += 1
        homes: dict[str, int] = {}
        for h in self.home_returns:
            homes[str(h.joint)] = homes.get(str(h.joint), 0) + 1
        return {
            "dwells": len(self.dwells),
            "sweep_stops": passes,
            "home_returns": homes,
            "poses": {
                "identify": sum(p.set == "identify" for p in self.poses),
                "validate": sum(p.set == "validate" for p in self.poses),
            },
            "other_dwells": len(self.other),
            "step_counts": {str(j): round(v, 3) for j, v in sorted(self.step_counts.items())},
        }


def find_dwells(t_ns: IntArray, counts: IntArray, opts: PhaseOptions) -> list[Dwell]:
    """Stationary runs of the grating stream (``t_ns`` (N,), ``counts`` (N, n))."""
    n = counts.shape[0]
    if n < opts.min_dwell_samples:
        return []
    step = np.abs(np.diff(counts, axis=0)).max(axis=1)  # (N-1,)
    dt = np.diff(t_ns)
    period = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    gap = (dt > opts.gap_factor * period) | (dt <= 0)
    calm = (step <= opts.still_counts) & ~gap  # transition i -> i+1 is calm
    # run boundaries: a run is a maximal sequence of samples linked by calm transitions
    breaks = np.flatnonzero(~calm)  # transition indices that split runs
    starts = np.concatenate(([0], breaks + 1))
    ends = np.concatenate((breaks, [n - 1]))
    out: list[Dwell] = []
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        if b - a + 1 < opts.min_dwell_samples:
            continue
        seg = counts[a : b + 1]
        if int((seg.max(axis=0) - seg.min(axis=0)).max()) > opts.span_counts:
            continue
        out.append(Dwell(len(out), a, b, int(t_ns[a]), int(t_ns[b]), seg.mean(axis=0)))
    return out


def _single_joint(delta: FloatArray, ratio: float) -> int | None:
    a = np.abs(delta)
    j = int(np.argmax(a))
    if a[j] <= 0:
        return None
    others = np.delete(a, j)
    return j if others.size == 0 or float(others.max()) <= ratio * a[j] else None


def _find_sweeps(
    dwells: list[Dwell], opts: PhaseOptions
) -> tuple[list[SweepStop], dict[int, float]]:
    """Sweep passes as runs of equal single-joint steps between consecutive dwells."""
    m = len(dwells)
    # per transition k (dwell k -> k+1): joint and signed step, or None
    trans: list[tuple[int, float] | None] = []
    for k in range(m - 1):
        d = dwells[k + 1].counts - dwells[k].counts
        j = _single_joint(d, opts.single_joint_ratio)
        trans.append(None if j is None else (j, float(d[j])))
    runs: list[tuple[int, int, int, float]] = []  # (first transition, last, joint, median step)
    k = 0
    while k < len(trans):
        t = trans[k]
        if t is None:
            k += 1
            continue
        j, s = t
        e = k
        steps = [s]  # the steps of transitions k..e
        while e + 1 < len(trans):
            nt = trans[e + 1]
            if nt is None or nt[0] != j or np.sign(nt[1]) != np.sign(s):
                break
            trial = [*steps, nt[1]]
            med = float(np.median(trial))
            if any(abs(x - med) > opts.step_tolerance * abs(med) for x in trial):
                break
            steps = trial
            e += 1
        if e - k + 2 >= opts.min_sweep_stops:
            runs.append((k, e, j, float(np.median(steps))))
            k = e + 1
        else:
            k += 1
    stops: list[SweepStop] = []
    seen: dict[int, int] = {}
    step_counts: dict[int, list[float]] = {}
    for k, e, j, med in runs:
        joint = j + 1
        count = seen.get(joint, 0)
        seen[joint] = count + 1
        if count >= 2:  # a third pass of the same joint: not the method's; keep the first two
            continue
        name = "forward" if count == 0 else "backward"
        for step, dw in enumerate(range(k, e + 2)):
            stops.append(SweepStop(joint, name, step, dw))
        step_counts.setdefault(joint, []).append(abs(med))
    return stops, {j: float(np.median(v)) for j, v in step_counts.items()}


def _home_vector(
    dwells: list[Dwell], stops: list[SweepStop], n: int, tol: FloatArray, span: float
) -> FloatArray:
    """Home ``(n,)`` counts, NaN where unknown: the most visited dwell position (dwells
    within ``tol`` ``(n,)`` of one another: the Home returns, ~10 a joint, make it Home),
    its median; per joint the median of its counts over the other joints' sweep stops
    instead where that agrees with it within ``span`` counts (a dwell's own span: the
    default campaign holds every other joint at Home during a sweep, and its result stays
    what it was; a planned sweep holds them away from Home and would bias it)."""
    home = np.full(n, np.nan)
    for k in range(n):
        vals = [dwells[s.dwell].counts[k] for s in stops if s.joint != k + 1]
        if vals:
            home[k] = float(np.median(vals))
    visited = _most_visited(dwells, {s.dwell for s in stops}, tol)
    if visited is None:
        return home
    agree = np.abs(home - visited) <= span  # False where either is NaN
    return np.where(agree, home, visited)


#: how many dwells :func:`_most_visited` tries as the centre of the most visited position
MOST_VISITED_CENTRES = 1000


def _most_visited(dwells: list[Dwell], skip: set[int], tol: FloatArray) -> FloatArray | None:
    """The median counts ``(n,)`` of the largest set of dwells (not in ``skip``) within
    ``tol`` of one of them on every joint with a finite tolerance (None: no such joint or
    dwell)."""
    known = np.isfinite(tol)
    rest = np.array([d.counts for d in dwells if d.index not in skip])
    if not known.any() or rest.shape[0] == 0:
        return None
    c = rest[:, known]
    # the centres tried: at most MOST_VISITED_CENTRES dwells, evenly spread (a day's
    # production recording has thousands; Home stays the most visited among any spread)
    centres = c[np.linspace(0, len(c) - 1, min(len(c), MOST_VISITED_CENTRES)).astype(int)]
    near = np.ones((len(centres), len(c)), dtype=bool)
    for k in range(c.shape[1]):  # joint by joint: (centres, m) at a time
        near &= np.abs(centres[:, None, k] - c[None, :, k]) <= tol[known][k]
    best = int(np.argmax(near.sum(axis=1)))
    out: FloatArray = np.median(rest[near[best]], axis=0)
    return out


def find_phases(t_ns: IntArray, counts: IntArray, opts: PhaseOptions | None = None) -> Phases:
    """Dwells, sweep stops, Home returns and poses of a grating stream.

    ``t_ns`` (N,) int64 mapped time; ``counts`` (N, n) int64 unwrapped counts (the driver's
    ``grating<k>_counts``).
    """
    opts = opts or PhaseOptions()
    counts = np.asarray(counts, dtype=np.int64)
    n = counts.shape[1]
    dwells = find_dwells(np.asarray(t_ns, dtype=np.int64), counts, opts)
    stops, step_counts = _find_sweeps(dwells, opts)
    # joints without a sweep: the smallest step of the swept joints sets their tolerance
    fallback = min(step_counts.values()) if step_counts else np.nan
    tol = np.array(
        [opts.home_tolerance * step_counts.get(k + 1, fallback) for k in range(n)], dtype=float
    )
    home = _home_vector(dwells, stops, n, tol, opts.span_counts)
    in_sweep = {s.dwell for s in stops}
    sweep_speed = _sweep_speeds(t_ns, counts, dwells, stops)
    homes: list[HomeReturn] = []
    poses_idx: list[int] = []
    other: list[int] = []
    trials: dict[int, int] = {}
    for d in dwells:
        if d.index in in_sweep:
            continue
        off = np.abs(d.counts - home)
        known = np.isfinite(off) & np.isfinite(tol)
        at_home = bool(np.all(off[known] <= tol[known])) and bool(known.any())
        if at_home and d.i0 > 0:
            ret = _home_approach(t_ns, counts, dwells, d, home, tol, sweep_speed, opts)
            if ret is None:
                other.append(d.index)
                continue
            joint, approach = ret
            trials[joint] = trials.get(joint, 0) + 1
            homes.append(HomeReturn(joint, trials[joint], d.index, approach))
            continue
        n_away = np.count_nonzero(off[known] > tol[known]) if known.any() else n
        if n_away >= 2:
            poses_idx.append(d.index)
        else:
            other.append(d.index)
    n_id = round(opts.identify_fraction * len(poses_idx))
    if opts.identify_count is not None:
        n_id = min(opts.identify_count, len(poses_idx))
    poses = [
        Pose(
            f"{'id' if k < n_id else 'val'}{k if k < n_id else k - n_id:03d}",
            "identify" if k < n_id else "validate",
            di,
        )
        for k, di in enumerate(poses_idx)
    ]
    return Phases(dwells, stops, homes, poses, home, step_counts, other)


def _sweep_speeds(
    t_ns: IntArray, counts: IntArray, dwells: list[Dwell], stops: list[SweepStop]
) -> dict[int, float]:
    """Sweep speed per joint: the median over the moves between its consecutive stops of
    their (robust) fastest |counts per second|."""
    sweep_speed: dict[int, float] = {}
    by_joint: dict[int, list[SweepStop]] = {}
    for s in stops:
        by_joint.setdefault(s.joint, []).append(s)
    for j, ss in by_joint.items():
        speeds = []
        for a, b in itertools.pairwise(ss):
            if b.dwell == a.dwell + 1:
                speeds.append(
                    _peak_speed(t_ns, counts[:, j - 1], dwells[a.dwell].i1, dwells[b.dwell].i0)
                )
        if speeds:
            sweep_speed[j] = float(np.median(speeds))
    return sweep_speed


def _home_approach(
    t_ns: IntArray,
    counts: IntArray,
    dwells: list[Dwell],
    d: Dwell,
    home: FloatArray,
    tol: FloatArray,
    sweep_speed: dict[int, float],
    opts: PhaseOptions,
) -> tuple[int, int] | None:
    """The joint (1-based) that came back to Home for the dwell ``d`` at Home, and its
    direction of approach (±1), when one joint alone made the final approach, slowly
    against its sweep speed; None otherwise."""
    n = counts.shape[1]
    prev_end = dwells[d.index - 1].i1 if d.index > 0 else 0
    seg = counts[prev_end : d.i0 + 1]
    # the approaching joint is the one away from Home last; the approach starts
    # after the last sample with any other joint away from Home
    dev = np.abs(seg - home[None, :])
    away = dev > tol[None, :]
    rows = np.flatnonzero(away.any(axis=1))
    if rows.size:
        jj = int(np.argmax(dev[rows[-1]] / tol))
        others = np.flatnonzero(np.delete(away, jj, axis=1).any(axis=1))
        if others.size:
            prev_end += int(others[-1]) + 1
            dev = dev[int(others[-1]) + 1 :]
    exc = dev.max(axis=0) if dev.shape[0] else np.zeros(n)
    exc = np.where(np.isfinite(exc), exc, 0.0)
    j = int(np.argmax(exc))
    rest = np.delete(exc, j)
    single = rest.size == 0 or float(rest.max()) <= opts.single_joint_ratio * exc[j]
    if not (single and (j + 1) in sweep_speed and exc[j] > 10 * opts.still_counts):
        return None
    i_start = _final_approach_start(counts[:, j], prev_end, d.i0)
    speed = _peak_speed(t_ns, counts[:, j], i_start, d.i0)
    if not speed <= opts.home_speed_ratio * sweep_speed[j + 1]:
        return None
    return j + 1, int(np.sign(counts[d.i0, j] - counts[i_start, j]))


def _peak_speed(t_ns: IntArray, c: IntArray, i0: int, i1: int) -> float:
    """Largest |counts per second| between samples ``i0`` and ``i1`` (robust: 2nd largest)."""
    if i1 - i0 < 2:
        return 0.0
    dc = np.abs(np.diff(c[i0 : i1 + 1]).astype(np.float64))
    dt = np.diff(t_ns[i0 : i1 + 1]).astype(np.float64) * 1e-9
    v = dc / np.where(dt > 0, dt, np.inf)
    if v.size < 2:
        return float(v.max(initial=0.0))
    return float(np.sort(v)[-2])


def _final_approach_start(c: IntArray, lo: int, hi: int) -> int:
    """Start of the last monotone stretch of ``c`` ending at ``hi`` (not before ``lo``)."""
    if hi - lo < 2:
        return lo
    d = np.diff(c[lo : hi + 1])
    sign = np.sign(d[np.flatnonzero(np.abs(d) > 0)[-1]]) if np.any(d) else 0
    k: int = d.shape[0] - 1
    # skip the still tail, then walk back while moving the same way
    while k >= 0 and np.sign(d[k]) != sign:
        k -= 1
    while k >= 0 and np.sign(d[k]) == sign:
        k -= 1
    return lo + k + 1
