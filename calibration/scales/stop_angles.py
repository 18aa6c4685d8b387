"""Each sweep stop's angle about the joint axis from the tracker points (method §2, step
3): 3-D circle fits for one reflector, the target set's rigid rotation for several; the
stops in order of the commanded angle, both sweeps on one turn, wild points dropped."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from calibration.errors import CircleFitError, ScaleError
from calibration.scales.circle_fit import CircleFit, fit_circle_3d
from calibration.scales.scale_relation import signed_offset_counts
from calibration.scales.sweep_inputs import PASSES, JointSweep, ScaleOptions
from calibration.scales.target_set_fit import TargetSetFit, fit_target_set

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


#: a circle fit or a target-set fit (both can be oriented)
_Fit = TypeVar("_Fit", CircleFit, TargetSetFit)


def _orient_like(fit: _Fit, normal: FloatArray) -> _Fit:
    return fit if fit.normal @ normal >= 0 else fit.flipped()


def unwrap_inliers(angle: FloatArray, inlier: NDArray[np.bool_]) -> FloatArray:
    """Unwrap along the order using inliers only; outliers take their nearest inlier's turn."""
    out = angle.copy()
    idx = np.flatnonzero(inlier)
    out[idx] = np.unwrap(angle[idx])
    for k in np.flatnonzero(~inlier):
        j = idx[np.argmin(np.abs(idx - k))]
        out[k] = out[j] + np.angle(np.exp(1j * (angle[k] - angle[j])))
    return out


@dataclass(frozen=True, eq=False)
class StopAngles:
    """The stops ordered by increasing commanded angle, with their circle angles."""

    order: IntArray
    pass_name: NDArray[np.str_]
    step: IntArray
    u_raw: FloatArray
    theta: FloatArray
    inlier: NDArray[np.bool_]
    circle: CircleFit | TargetSetFit
    pass_circles: Mapping[str, CircleFit | TargetSetFit]
    dropped: list[tuple[int, str]]


def _stop_sets(sweep: JointSweep) -> tuple[IntArray, FloatArray]:
    """Rows grouped into stops: each stop's first row ``(K,)`` and its targets' points
    ``(K, T, 3)`` (NaN for a target not measured there), stops in file order."""
    assert sweep.target is not None
    targets = sorted(set(sweep.target.tolist()))
    keys: dict[tuple[str, int], int] = {}
    first: list[int] = []
    for i, key in enumerate(zip(sweep.pass_name.tolist(), sweep.step.tolist(), strict=True)):
        if key not in keys:
            keys[key] = len(first)
            first.append(i)
    points = np.full((len(first), len(targets), 3), np.nan)
    for i, key in enumerate(zip(sweep.pass_name.tolist(), sweep.step.tolist(), strict=True)):
        points[keys[key], targets.index(int(sweep.target[i]))] = sweep.points_mm[i]
    return np.array(first, dtype=np.int64), points


def _target_set_angles(sweep: JointSweep, reference: float, opt: ScaleOptions) -> StopAngles:
    """As :func:`stop_angles` for T ≥ 2 reflectors: each stop's angle from the rigid
    rotation of the target set (:func:`calibration.scales.target_set_fit.fit_target_set`)."""
    j = sweep.joint
    first, points = _stop_sets(sweep)
    pass_of = sweep.pass_name[first]
    step_of = sweep.step[first]
    passes, stops = _by_angle(pass_of, step_of, j, opt)
    pts = points[stops]
    sigma = opt.tracker.sigma_mm(np.nan_to_num(pts.reshape(-1, 3))).reshape(pts.shape[:2])
    pass_name = pass_of[stops]
    dropped: list[tuple[int, str]] = []
    pass_fits = {}
    for p in passes:
        m = np.flatnonzero(pass_name == p)
        try:
            pass_fits[p] = fit_target_set(pts[m], sigma[m], outlier_alpha=opt.outlier_alpha)
        except CircleFitError as exc:
            raise ScaleError(f"joint {j}: {p} sweep: {exc}") from exc
    try:
        common = fit_target_set(pts, sigma, outlier_alpha=opt.outlier_alpha)
    except CircleFitError as exc:
        raise ScaleError(f"joint {j}: common fit of the target set: {exc}") from exc
    common = _orient_like(common, pass_fits[passes[0]].normal)
    for k, t in common.outlier_points:
        dropped.append((int(first[stops[k]]), f"target-set fit: wild point of target {t + 1}"))
    inlier = common.inlier.copy()
    theta = np.empty(stops.size)
    for p in passes:
        m = np.flatnonzero(pass_name == p)
        theta[m] = unwrap_inliers(common.angle_rad[m], inlier[m])
    u_raw = signed_offset_counts(sweep.counts[first[stops]], reference)
    if len(passes) == 2:
        _same_turn(theta, pass_name, inlier, u_raw)
    pass_fits = {p: _orient_like(c, common.normal) for p, c in pass_fits.items()}
    return StopAngles(
        first[stops], pass_name, step_of[stops], u_raw, theta, inlier, common, pass_fits, dropped
    )


def _same_turn(
    theta: FloatArray, pass_name: NDArray[np.str_], inlier: NDArray[np.bool_], u_raw: FloatArray
) -> None:
    """Put the backward sweep on the forward sweep's turn by matching counts (in place)."""
    f = np.flatnonzero((pass_name == "forward") & inlier)
    b = np.flatnonzero((pass_name == "backward") & inlier)
    i, k = np.unravel_index(
        np.argmin(np.abs(u_raw[f][:, None] - u_raw[b][None, :])), (f.size, b.size)
    )
    turns = np.round((theta[f[i]] - theta[b[k]]) / (2 * np.pi))
    theta[pass_name == "backward"] += 2 * np.pi * turns


def _by_angle(
    pass_name: NDArray[np.str_], step: IntArray, joint: int, opt: ScaleOptions
) -> tuple[list[str], IntArray]:
    """The passes present, and the stops in order of increasing commanded angle (forward
    reversed, then backward); a pass with too few stops is an error."""
    passes = [p for p in PASSES if np.any(pass_name == p)]
    if not passes:
        raise ScaleError(f"joint {joint}: no sweep stops")
    parts = []
    for p in passes:
        idx = np.flatnonzero(pass_name == p)
        idx = idx[np.argsort(step[idx], kind="stable")]
        if idx.size < opt.min_stops_per_pass:
            raise ScaleError(
                f"joint {joint}: {p} sweep has {idx.size} stops; "
                f"at least {opt.min_stops_per_pass} are needed"
            )
        parts.append(idx[::-1] if p == "forward" else idx)  # increasing joint angle
    return passes, np.concatenate(parts)


def stop_angles(sweep: JointSweep, reference: float, opt: ScaleOptions) -> StopAngles:
    if sweep.n_targets > 1:
        return _target_set_angles(sweep, reference, opt)
    j = sweep.joint
    passes, order = _by_angle(sweep.pass_name, sweep.step, j, opt)
    pass_name = sweep.pass_name[order]
    points = sweep.points_mm[order]
    sigma = opt.tracker.sigma_mm(points)
    u_raw = signed_offset_counts(sweep.counts[order], reference)
    n_stops = order.size

    pass_circles: dict[str, CircleFit] = {}
    inlier = np.ones(n_stops, dtype=bool)
    dropped: list[tuple[int, str]] = []
    for p in passes:
        m = np.flatnonzero(pass_name == p)
        try:
            fit = fit_circle_3d(points[m], sigma[m], outlier_alpha=opt.outlier_alpha)
        except CircleFitError as exc:
            raise ScaleError(f"joint {j}: {p} sweep: {exc}") from exc
        pass_circles[p] = fit  # points given in increasing joint angle: oriented with it
        for k in fit.outliers:
            inlier[m[k]] = False
            dropped.append((int(order[m[k]]), f"{p} circle: wild tracker point"))
    idx_in = np.flatnonzero(inlier)
    try:
        common = fit_circle_3d(points[idx_in], sigma[idx_in], outlier_alpha=opt.outlier_alpha)
    except CircleFitError as exc:
        raise ScaleError(f"joint {j}: common circle: {exc}") from exc
    common = _orient_like(common, pass_circles[passes[0]].normal)
    for k in common.outliers:
        inlier[idx_in[k]] = False
        dropped.append((int(order[idx_in[k]]), "common circle: wild tracker point"))
    full = replace(common, points_mm=points, sigma_mm=sigma, inlier=inlier)
    theta = np.empty(n_stops)
    for p in passes:
        m = np.flatnonzero(pass_name == p)
        theta[m] = unwrap_inliers(full.angle_rad[m], inlier[m])
    if len(passes) == 2:
        _same_turn(theta, pass_name, inlier, u_raw)
    pass_circles = {p: _orient_like(c, full.normal) for p, c in pass_circles.items()}
    return StopAngles(
        order, pass_name, sweep.step[order], u_raw, theta, inlier, full, pass_circles, dropped
    )
