"""Pair tracker measurements with the grating readings at the same instant.

Both streams carry ``t_mapped_ns`` (device time mapped to host UTC, re-fitted over the
settled part of the data by :meth:`calibration.twin.streams.Stream.remapped`). For each dwell
the twin needs a tracker point at (sweep stops, poses):

1. Tracker samples inside the dwell, less ``margin`` at both ends (the clock maps agree
   to about ±2 ms; the margin shrinks to a sixth of the dwell for very short dwells),
   are candidates. Samples outside any dwell are never paired: **the robot was moving**.
2. A candidate whose status lacks the *valid* bit or whose coordinates are not finite is
   rejected: **the beam was broken** (or the tracker dropped the point).
3. The grating counts at the tracker sample's instant are interpolated linearly between
   the grating samples around it, within the dwell only; a pair whose interpolated counts
   differ from the dwell's mean by more than ``still_counts`` on any strip is rejected
   (**moving**: the dwell edge, a timing slip).
4. Tracker points further than ``max(point_floor_mm, 5 · robust σ)`` from the dwell's
   median point are rejected (**moving** target, a point measured during the approach).
5. The stop's measurement is the mean of the accepted pairs (point and counts); fewer than
   ``min_pairs`` accepted pairs: the stop is **lost**, with the reason.

Encoders (optional): the mean of the encoder samples in the same window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.twin.phase_detection import Dwell
from calibration.twin.streams import Stream

FloatArray = NDArray[np.float64]

VALID_BIT = 1


@dataclass(frozen=True)
class PairingOptions:
    margin_s: float = 0.002
    min_pairs: int = 2
    still_counts: float = 4.0
    point_floor_mm: float = 0.05


@dataclass(frozen=True)
class StopMeasurement:
    """One dwell's paired measurement (or why there is none)."""

    dwell: int
    ok: bool
    reason: str  # "" when ok
    n_pairs: int
    n_rejected_beam: int
    n_rejected_moving: int
    t_ns: int  # mid-time of the accepted pairs (or of the dwell)
    counts: FloatArray  # (n,) mean grating counts at the accepted tracker instants
    point_mm: FloatArray  # (3,) mean tracker point, NaN if not ok
    point_std_mm: float  # RMS spread of the accepted points about their mean
    encoder_counts: FloatArray | None  # (n,) mean encoder counts in the window


def pair_dwell(
    dwell: Dwell,
    grating: Stream,
    tracker: Stream,
    encoders: Stream | None = None,
    opts: PairingOptions | None = None,
) -> StopMeasurement:
    """The tracker ↔ grating pairs of one dwell (module docstring)."""
    opts = opts or PairingOptions()
    lo, hi = _window(dwell, opts)
    a = int(np.searchsorted(tracker.t_ns, lo, side="left"))
    b = int(np.searchsorted(tracker.t_ns, hi, side="right"))
    tt = tracker.t_ns[a:b]
    pts = tracker.values[a:b]
    enc = _encoder_mean(encoders, lo, hi)
    mid = (dwell.t0_ns + dwell.t1_ns) // 2
    if tt.size == 0:
        return _lost(dwell, "no tracker samples in the dwell", (0, 0, 0), mid, enc)
    valid = np.all(np.isfinite(pts), axis=1)
    if tracker.status is not None:
        valid &= np.all((tracker.status[a:b] & VALID_BIT) != 0, axis=1)
    n_beam = int(np.count_nonzero(~valid))
    ci = _counts_at(tt, dwell, grating)
    still = np.all(np.abs(ci - dwell.counts[None, :]) <= opts.still_counts, axis=1)
    ok = valid & still
    n_moving = int(np.count_nonzero(valid & ~still))
    if np.count_nonzero(ok) >= opts.min_pairs:
        near = _near_median(pts, ok, opts.point_floor_mm)
        n_moving += int(np.count_nonzero(ok & ~near))
        ok &= near
    n_ok = int(np.count_nonzero(ok))
    if n_ok < opts.min_pairs:
        reason = "beam broken" if n_beam >= tt.size - opts.min_pairs + 1 else "robot moving"
        if n_beam == 0 and n_moving == 0:
            reason = f"only {n_ok} tracker samples in the dwell"
        return _lost(dwell, reason, (n_ok, n_beam, n_moving), mid, enc)
    p = pts[ok].mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((pts[ok] - p) ** 2, axis=1))))
    t_mid = int(np.rint(np.mean((tt[ok] - tt[ok][0]).astype(np.float64)))) + int(tt[ok][0])
    return StopMeasurement(
        dwell.index, True, "", n_ok, n_beam, n_moving, t_mid, ci[ok].mean(axis=0), p, spread, enc
    )


def _window(dwell: Dwell, opts: PairingOptions) -> tuple[int, int]:
    """The dwell less the margin at both ends (ns; a sixth of a very short dwell)."""
    span = dwell.t1_ns - dwell.t0_ns
    margin = int(min(opts.margin_s * 1e9, span / 6))
    return dwell.t0_ns + margin, dwell.t1_ns - margin


def _encoder_mean(encoders: Stream | None, lo: int, hi: int) -> FloatArray | None:
    """Mean encoder counts ``(n,)`` of the samples in ``[lo, hi]`` ns (None: no samples)."""
    if encoders is None or not len(encoders):
        return None
    ea = int(np.searchsorted(encoders.t_ns, lo, side="left"))
    eb = int(np.searchsorted(encoders.t_ns, hi, side="right"))
    if eb <= ea:
        return None
    mean: FloatArray = encoders.values[ea:eb].astype(np.float64).mean(axis=0)
    return mean


def _counts_at(t_ns: NDArray[np.int64], dwell: Dwell, grating: Stream) -> FloatArray:
    """Grating counts ``(k, n)`` at the instants ``t_ns`` ``(k,)``, interpolated linearly
    between the grating samples of the dwell."""
    gt = grating.t_ns[dwell.i0 : dwell.i1 + 1]
    gc = grating.values[dwell.i0 : dwell.i1 + 1].astype(np.float64)
    ci = np.empty((t_ns.size, gc.shape[1]))
    for k in range(gc.shape[1]):
        ci[:, k] = np.interp(t_ns, gt, gc[:, k])
    return ci


def _near_median(
    points_mm: FloatArray, ok: NDArray[np.bool_], floor_mm: float
) -> NDArray[np.bool_]:
    """Points ``(k, 3)`` mm within ``max(floor_mm, 5 · robust σ)`` of the median of the
    ``ok`` ones (σ per axis from their median distance: 1.538 σ for a Maxwell distance)."""
    med = np.median(points_mm[ok], axis=0)
    dist = np.linalg.norm(points_mm - med[None, :], axis=1)
    sig = 1.4826 * float(np.median(dist[ok])) / 1.538 if np.any(ok) else 0.0
    near: NDArray[np.bool_] = dist <= max(floor_mm, 5.0 * sig)
    return near


def _lost(
    dwell: Dwell,
    reason: str,
    tally: tuple[int, int, int],
    mid_ns: int,
    enc: FloatArray | None,
) -> StopMeasurement:
    """A stop without a measurement: ``tally`` is (accepted pairs, rejected for the beam,
    rejected as moving)."""
    n_ok, n_beam, n_moving = tally
    nan = np.full(3, np.nan)
    return StopMeasurement(
        dwell.index,
        False,
        reason,
        n_ok,
        n_beam,
        n_moving,
        mid_ns,
        dwell.counts,
        nan,
        float("nan"),
        enc,
    )
