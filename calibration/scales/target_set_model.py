"""The rigid rotation of a set of T targets about one axis (:class:`TargetSetGeometry`):
its parameters, each point's local coordinates and Jacobians, the stop angles profiled
out in closed form, and its canonical form. Units: mm and radians; shapes ``(K, T, 3)``
points, ``(K, T)`` per point, ``(K,)`` per stop."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def parameter_names(n_targets: int) -> tuple[str, ...]:
    """Names of the ``P = 3T + 3`` structure parameters, in covariance order."""
    t = range(n_targets)
    return (
        "centre_u_mm",
        "centre_v_mm",
        "tilt_u_rad",
        "tilt_v_rad",
        *(f"height_{i}_mm" for i in t),
        *(f"radius_{i}_mm" for i in t),
        *(f"phase_{i}_rad" for i in t if i > 0),
    )


@dataclass(frozen=True, eq=False)
class TargetSetGeometry:
    """Where the targets sit about the axis: the structure of the model, without angles.

    ``centre_mm`` ``(3,)`` a point of the axis; ``normal`` ``(3,)`` and ``axis_u`` ``(3,)``
    unit (``axis_u ⟂ normal``: angle 0); ``height_mm``, ``radii_mm``, ``phase_rad``
    ``(T,)`` (``phase_rad[0] = 0``).
    """

    centre_mm: FloatArray
    normal: FloatArray
    axis_u: FloatArray
    height_mm: FloatArray
    radii_mm: FloatArray
    phase_rad: FloatArray

    @property
    def axis_v(self) -> FloatArray:
        return np.cross(self.normal, self.axis_u)

    @property
    def n_targets(self) -> int:
        return int(self.radii_mm.shape[0])

    def positions_mm(self, angle_rad: ArrayLike) -> FloatArray:
        """Noise-free target positions ``(K, T, 3)`` at the stop angles ``(K,)``."""
        th = np.atleast_1d(np.asarray(angle_rad, dtype=float))
        radial, _ = target_directions(self, th)
        return (
            self.centre_mm
            + self.height_mm[None, :, None] * self.normal
            + self.radii_mm[None, :, None] * radial
        )


def target_directions(geo: TargetSetGeometry, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Radial and tangential unit vectors ``(K, T, 3)`` of every target at every stop."""
    alpha = theta[:, None] + geo.phase_rad[None, :]
    c, s = np.cos(alpha)[..., None], np.sin(alpha)[..., None]
    u, v = geo.axis_u, geo.axis_v
    return c * u + s * v, -s * u + c * v


def point_jacobians(geo: TargetSetGeometry, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """∂p/∂structure ``(K, T, 3, P)`` and ∂p/∂θ_k ``(K, T, 3)`` (unweighted).

    Structure perturbations (:func:`parameter_names`): the axis point moves along ``u``,
    ``v``; the normal tilts as ``n + a·u + b·v`` about the axis point, with ``u`` following
    by projection (so ``∂u/∂a = −n``, ``∂v/∂b = −n``: no twist about ``n``).
    """
    k, t = theta.shape[0], geo.n_targets
    u, v, n = geo.axis_u, geo.axis_v, geo.normal
    alpha = theta[:, None] + geo.phase_rad[None, :]
    cos_a, sin_a = np.cos(alpha), np.sin(alpha)
    radial = cos_a[..., None] * u + sin_a[..., None] * v
    tangent = -sin_a[..., None] * u + cos_a[..., None] * v
    h, r = geo.height_mm[None, :, None], geo.radii_mm[None, :, None]
    n_par = 3 * t + 3
    js = np.zeros((k, t, 3, n_par))
    js[..., 0] = u
    js[..., 1] = v
    js[..., 2] = h * u - (r * cos_a[..., None]) * n
    js[..., 3] = h * v - (r * sin_a[..., None]) * n
    idx = np.arange(t)
    js[:, idx, :, 4 + idx] = np.broadcast_to(n, (t, k, 3))  # heights: one-hot per target
    js[:, idx, :, 4 + t + idx] = radial.transpose(1, 0, 2)  # radii
    j_theta = r * tangent
    if t > 1:  # phases of targets 1.. (φ_0 = 0)
        js[:, idx[1:], :, 4 + 2 * t + idx[1:] - 1] = j_theta[:, 1:].transpose(1, 0, 2)
    return js, j_theta


def local_coordinates(geo: TargetSetGeometry, points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """In-plane complex position about the axis ``(K, T)`` and axial residual ``(K, T)``."""
    w = points - geo.centre_mm
    z = (w @ geo.axis_u) + 1j * (w @ geo.axis_v)
    return z, w @ geo.normal - geo.height_mm


def profile_theta(geo: TargetSetGeometry, z: FloatArray, weight: FloatArray) -> FloatArray:
    """Best θ_k for fixed structure ``(K,)``: argument of ``Σ_t ω r_t e^{−iφ_t} z_tk``.

    NaN where the stop has no weighted point.
    """
    terms = weight * geo.radii_mm * np.exp(-1j * geo.phase_rad) * z
    theta = np.angle(terms.sum(axis=1))
    return np.where(weight.sum(axis=1) > 0, theta, np.nan)


def canonical(geo: TargetSetGeometry, theta: FloatArray) -> tuple[TargetSetGeometry, FloatArray]:
    """Positive radii, ``φ_0 = 0``, phases in (−π, π], axis point at the mean height."""
    radius = np.abs(geo.radii_mm)
    phase = geo.phase_rad + np.where(geo.radii_mm < 0, np.pi, 0.0)
    theta = theta + phase[0]
    phase = np.angle(np.exp(1j * (phase - phase[0])))
    mean_h = float(np.mean(geo.height_mm))
    geo = TargetSetGeometry(
        geo.centre_mm + mean_h * geo.normal,
        geo.normal,
        geo.axis_u,
        geo.height_mm - mean_h,
        radius,
        phase,
    )
    return geo, np.angle(np.exp(1j * theta))


def in_plane_axis(normal: FloatArray) -> FloatArray:
    """A unit vector ⟂ ``normal``: the world axis least aligned with it, projected."""
    ref = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = ref - (ref @ normal) * normal
    unit: FloatArray = u / np.linalg.norm(u)
    return unit
