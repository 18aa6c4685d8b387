"""Fitting a target set's geometry to the points (:mod:`calibration.scales.target_set_fit`'s
steps): the start (plane by SVD, rotations by 2-D Procrustes), the damped Gauss-Newton
with the stop angles profiled out (Schur complement), and the rejection of wild points by
their deleted residuals. Units: mm and radians."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.errors import TargetSetFitError
from calibration.scales.circle_fit import (
    MIN_POINTS,
)
from calibration.scales.target_set_model import (
    TargetSetGeometry,
    in_plane_axis,
    local_coordinates,
    point_jacobians,
    profile_theta,
)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


MIN_STOPS = MIN_POINTS  # as the circle fit: 3 stops fix a circle, one more for the noise


MAX_ITERATIONS = 100


# in-plane spread of the target set (RMS about its centroid) below this many times the
# noise: the set is collinear with the axis and turns like a single target
MIN_SPREAD_NOISE = 10.0


def _cost(
    geo: TargetSetGeometry, points: FloatArray, weight: FloatArray, theta: FloatArray
) -> tuple[float, FloatArray]:
    e = points - geo.positions_mm(np.nan_to_num(theta))
    return float(np.sum(weight * np.einsum("kta,kta->kt", e, e))), e


def _normal_blocks(
    geo: TargetSetGeometry, theta: FloatArray, weight: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Blocks of the weighted normal matrix: ``N_ss`` ``(P, P)``, ``N_θs`` ``(K, P)``, ``N_θθ``."""
    js, j_theta = point_jacobians(geo, np.nan_to_num(theta))
    sw = np.sqrt(weight)[..., None, None]
    a = (sw * js).reshape(-1, js.shape[-1])
    n_ss = a.T @ a
    n_ts = np.einsum("kta,kt,ktap->kp", j_theta, weight, js)
    n_tt = np.sum(weight * geo.radii_mm**2, axis=1)
    return n_ss, n_ts, n_tt, js


def _update(geo: TargetSetGeometry, step: FloatArray) -> TargetSetGeometry:
    """The structure moved by ``step`` ``(P,)`` (tilts applied as a finite rotation)."""
    t = geo.n_targets
    u, v, n = geo.axis_u, geo.axis_v, geo.normal
    centre = geo.centre_mm + step[0] * u + step[1] * v
    n_new = n + step[2] * u + step[3] * v
    n_new /= np.linalg.norm(n_new)
    u_new = u - (u @ n_new) * n_new
    u_new /= np.linalg.norm(u_new)
    phase = geo.phase_rad.copy()
    phase[1:] += step[4 + 2 * t :]
    return TargetSetGeometry(
        centre,
        n_new,
        u_new,
        geo.height_mm + step[4 : 4 + t],
        geo.radii_mm + step[4 + t : 4 + 2 * t],
        phase,
    )


def solve_geometry(
    geo: TargetSetGeometry, points: FloatArray, weight: FloatArray
) -> tuple[TargetSetGeometry, FloatArray, float, int]:
    """Levenberg-Marquardt on the structure with the angles profiled out (Schur complement).

    ``points`` with zeros where unused, ``weight`` ``(K, T)`` = 1/σ² or 0. Returns the
    structure, the profiled angles, the weighted RSS and the number of iterations.
    """
    theta = profile_theta(geo, local_coordinates(geo, points)[0], weight)
    cost, e = _cost(geo, points, weight, theta)
    mu = 1e-3
    iterations = 0
    for iterations in range(1, MAX_ITERATIONS + 1):  # noqa: B007 (reported)
        n_ss, n_ts, n_tt, js = _normal_blocks(geo, theta, weight)
        inv_tt = np.where(n_tt > 0, 1.0 / np.where(n_tt > 0, n_tt, 1.0), 0.0)
        reduced = n_ss - n_ts.T @ (n_ts * inv_tt[:, None])
        # θ is profiled exactly, so the θ-gradient is zero and the reduced gradient is g_s
        grad = np.einsum("ktap,kt,kta->p", js, weight, e)
        scale = np.sqrt(np.maximum(np.diag(reduced), 1e-300))
        a = reduced / np.outer(scale, scale)
        g = grad / scale
        improved = False
        while mu < 1e12:
            try:
                step = np.linalg.solve(a + mu * np.eye(a.shape[0]), g) / scale
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            trial = _update(geo, step)
            trial_theta = profile_theta(trial, local_coordinates(trial, points)[0], weight)
            trial_cost, trial_e = _cost(trial, points, weight, trial_theta)
            if trial_cost <= cost:
                decrease = cost - trial_cost
                geo, theta, cost, e = trial, trial_theta, trial_cost, trial_e
                mu = max(mu / 10.0, 1e-12)
                improved = True
                break
            mu *= 10.0
        # stop once a step no longer changes the cost by a measurable fraction of it
        if not improved or decrease <= 1e-13 * cost + 1e-300:
            break
    return geo, theta, cost, iterations


def start_geometry(
    points: FloatArray, measured: BoolArray, weight: FloatArray
) -> TargetSetGeometry:
    """Plane by SVD, rotations by 2-D Procrustes against a template stop, then linear LS."""
    t_n = measured.shape[1]
    rows = []
    for t in range(t_n):
        p = points[measured[:, t], t]
        rows.append(p - p.mean(axis=0))
    vt = np.linalg.svd(np.concatenate(rows), full_matrices=False)[2]
    normal = vt[2]
    u = in_plane_axis(normal)
    v = np.cross(normal, u)
    centroid = points[measured].mean(axis=0)
    w = points - centroid
    z = np.where(measured, (w @ u) + 1j * (w @ v), 0.0)
    axial = np.where(measured, w @ normal, 0.0)
    # robust noise level from the scatter of each target about its plane
    median = np.array([np.median(axial[measured[:, t], t]) for t in range(t_n)])
    noise = 1.4826 * float(np.median(np.abs(axial - median)[measured]))

    count = measured.sum(axis=1)
    template = int(np.argmax(count))
    common = measured & measured[template]
    n_common = common.sum(axis=1)
    zc = np.where(common, z, 0.0)
    mean_k = zc.sum(axis=1) / np.maximum(n_common, 1)
    mean_ref = np.where(common, z[template], 0.0).sum(axis=1) / np.maximum(n_common, 1)
    a = np.where(common, z - mean_k[:, None], 0.0)
    b = np.where(common, z[template][None, :] - mean_ref[:, None], 0.0)
    ref_set = z[template, measured[template]]
    spread = float(np.sqrt(np.mean(np.abs(ref_set - ref_set.mean()) ** 2)))
    if measured[template].sum() < 2 or spread <= MIN_SPREAD_NOISE * noise:
        raise TargetSetFitError(
            f"the targets lie on one line parallel to the joint axis (their in-plane spread "
            f"{spread:.4g} mm is within {MIN_SPREAD_NOISE:g}× the noise {noise:.2g} mm): the "
            "set turns like a single target; fit one target alone (T = 1, the circle fit)"
        )
    usable = n_common >= 2
    if usable.sum() < 3:
        raise TargetSetFitError(
            "fewer than 3 stops share two measured targets with the best-measured stop: "
            "their rotation cannot be started"
        )
    theta = np.angle(np.sum(a * np.conj(b), axis=1))
    # z_tk = c + w_t e^{iθ_k}: linear in the complex unknowns (c, w_0 .. w_{T-1})
    sel = measured & usable[:, None]
    kk, tt = np.nonzero(sel)
    design = np.zeros((kk.size, 1 + t_n), dtype=complex)
    design[:, 0] = 1.0
    design[np.arange(kk.size), 1 + tt] = np.exp(1j * theta[kk])
    sw = np.sqrt(weight[kk, tt])
    sol = np.linalg.lstsq(design * sw[:, None], z[kk, tt] * sw, rcond=None)[0]
    c2, wt = sol[0], sol[1:]
    centre = centroid + c2.real * u + c2.imag * v
    height = np.sum(weight * axial, axis=0) / np.sum(weight, axis=0)  # centre is in-plane
    return TargetSetGeometry(centre, normal, u, height, np.abs(wt), np.angle(wt) - np.angle(wt[0]))


@dataclass(frozen=True, eq=False)
class GeometryFit:
    geo: TargetSetGeometry
    theta: FloatArray  # (K,) profiled over the used points, NaN for stops without one
    rss: float
    dof: int
    iterations: int

    @property
    def s2(self) -> float:
        return self.rss / self.dof


def fit_geometry(
    points: FloatArray, weight: FloatArray, used: BoolArray, geo: TargetSetGeometry
) -> GeometryFit:
    w = np.where(used, weight, 0.0)
    geo, theta, rss, iterations = solve_geometry(geo, points, w)
    dof = 3 * int(used.sum()) - (3 * geo.n_targets + 3) - int(used.any(axis=1).sum())
    if dof <= 0:
        raise TargetSetFitError(
            f"{int(used.sum())} points at {int(used.any(axis=1).sum())} stops leave no residual "
            f"degrees of freedom for {3 * geo.n_targets + 3} structure parameters"
        )
    return GeometryFit(geo, theta, rss, dof, iterations)


def deleted_chi2(
    geo: TargetSetGeometry, points: FloatArray, weight: FloatArray, used: BoolArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Each used point against θ_k from the *other* used points of its stop (structure fixed).

    Returns ``(K, T)`` arrays: the normalized squared deleted residual (relative units,
    divide by s²), its degrees of freedom (3, or 2 for a stop's only point), and the
    radial-plus-axial part alone (χ²₂). Zero where unused.
    """
    z, axial = local_coordinates(geo, points)
    w = np.where(used, weight, 0.0)
    r, phi = geo.radii_mm, geo.phase_rad
    terms = w * r * np.exp(-1j * phi) * z
    others = terms.sum(axis=1)[:, None] - terms
    n_other = used.sum(axis=1)[:, None] - used
    info_other = np.sum(w * r**2, axis=1)[:, None] - w * r**2
    theta = np.angle(np.where(n_other > 0, others, terms))
    direction = np.exp(1j * (theta + phi))
    e = np.conj(direction) * z - r
    sigma2 = 1.0 / np.where(used, weight, 1.0)
    radax = (axial**2 + e.real**2) / sigma2
    tangential_var = sigma2 + r**2 / np.where(info_other > 0, info_other, np.inf)
    chi2 = radax + np.where(n_other > 0, e.imag**2 / tangential_var, 0.0)
    df = np.where(n_other > 0, 3.0, 2.0)
    return np.where(used, chi2, 0.0), df, np.where(used, radax, 0.0)


def reject_wild(
    points: FloatArray,
    weight: FloatArray,
    used: BoolArray,
    fit: GeometryFit,
    outlier_alpha: float,
    max_outliers: int,
) -> tuple[BoolArray, GeometryFit]:
    """Drop wild points one at a time (screen, refit without, test the deleted residual)."""
    from scipy import stats  # loads when a fit runs: a refused input is said at once

    n_par = 3 * fit.geo.n_targets + 3
    dropped = 0
    while dropped < max_outliers and used.any(axis=1).sum() > MIN_STOPS + 1:
        chi2, df, _ = deleted_chi2(fit.geo, points, weight, used)
        n_used = int(used.sum())
        limit = stats.chi2.isf(outlier_alpha / n_used, df)
        med = stats.chi2.median(df)
        robust_s2 = max(float(np.median((chi2 / med)[used])), 1e-300)
        screen = np.where(used, chi2 / robust_s2 / limit, 0.0)
        k, t = np.unravel_index(int(np.argmax(screen)), screen.shape)
        if screen[k, t] <= 1.0:
            break
        trial = used.copy()
        trial[k, t] = False
        try:
            candidate = fit_geometry(points, weight, trial, fit.geo)
        except TargetSetFitError:
            break
        # the point against the refit (θ_k from the stop's remaining points)
        probe = trial.copy()
        probe[k, t] = True
        chi2_c, df_c, radax_c = deleted_chi2(candidate.geo, points, weight, probe)
        inflation = 1.0 + n_par / trial.sum()
        s2 = candidate.s2 * inflation
        if chi2_c[k, t] / s2 <= stats.chi2.isf(outlier_alpha / n_used, df_c[k, t]):
            break
        if trial[k].sum() == 1 and radax_c[k, t] / s2 <= stats.chi2.isf(outlier_alpha / n_used, 2):
            # two points disagreeing only tangentially: either may be wrong; drop the stop
            trial[k] = False
            try:
                candidate = fit_geometry(points, weight, trial, candidate.geo)
            except TargetSetFitError:
                break
        dropped += int(used.sum() - trial.sum())
        used, fit = trial, candidate
    return used, fit
