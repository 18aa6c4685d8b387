"""The identification's pure residual functions: the points a model predicts (geometry
plus linear effect terms, :class:`EffectTerms`), the position residuals against the
measured points and their Jacobian, stacked over the poses in chunks. Units: mm, rad;
shapes ``(m, n)`` joints, ``(m, 3)`` points."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.model.kinematics import (
    KinematicModel,
    identification_jacobian,
    tcp_positions,
)

FloatArray = NDArray[np.float64]


#: An effect regressor: (geometric model, slice of the poses) -> ∂TCP/∂c ``(rows, 3, k)``,
#: mm per unit of each effect parameter, for the poses the terms were built on.
EffectRegressor = Callable[[KinematicModel, slice], NDArray[np.float64]]


@dataclass(frozen=True, eq=False)
class EffectTerms:
    """Non-geometric terms linear in k parameters appended to the geometric vector.

    The twin predicts ``tcp(model, q) + regressor(model, poses) · c``. ``names`` carry the
    parameters' units (they are reported as they are); ``start`` defaults to zeros.
    """

    names: tuple[str, ...]
    regressor: EffectRegressor
    start: tuple[float, ...] | None = None

    @property
    def n_parameters(self) -> int:
        return len(self.names)

    def start_vector(self) -> NDArray[np.float64]:
        return np.zeros(len(self.names)) if self.start is None else np.asarray(self.start, float)


# -- pure residual functions --------------------------------------------------------------
def full_vector(x_free: FloatArray, x_full: FloatArray, free_idx: NDArray[np.intp]) -> FloatArray:
    x = np.array(x_full, dtype=float)
    x[free_idx] = x_free
    return x


#: Poses per block when evaluating residuals and Jacobians: keeps temporaries small so the
#: cost stays linear in the number of poses.
CHUNK_POSES = 8192


def _split(x: FloatArray, template: KinematicModel) -> tuple[KinematicModel, FloatArray]:
    """Geometry and effect parameters of a full vector ``(5n + 9 + k,)``."""
    p = template.n_parameters
    return template.with_parameters(x[:p]), x[p:]


def position_residuals(
    x_free: ArrayLike,
    x_full: FloatArray,
    free_idx: NDArray[np.intp],
    template: KinematicModel,
    q_rad: FloatArray,
    measured_mm: FloatArray,
    sqrt_weights: FloatArray,
    effects: EffectTerms | None = None,
) -> FloatArray:
    """Weighted residuals ``(3m,)``: (predicted point − tracker point), mm times √weight.

    ``x_free`` replaces the entries ``free_idx`` of the full parameter vector ``x_full``,
    which is ``(5n + 9,)``, or ``(5n + 9 + k,)`` with ``effects`` appended.
    """
    model, c = _split(full_vector(np.asarray(x_free), x_full, free_idx), template)
    pred = predicted_points(model, q_rad, effects, c)
    return ((pred - measured_mm) * sqrt_weights[:, None]).ravel()


def position_residual_jacobian(
    x_free: ArrayLike,
    x_full: FloatArray,
    free_idx: NDArray[np.intp],
    template: KinematicModel,
    q_rad: FloatArray,
    measured_mm: FloatArray,
    sqrt_weights: FloatArray,
    effects: EffectTerms | None = None,
) -> FloatArray:
    """Jacobian ``(3m, k_free)`` of :func:`position_residuals` with respect to ``x_free``.

    The effect regressors' own dependence on the geometry (second order in sub-mm
    effects) is left out.
    """
    model, _ = _split(full_vector(np.asarray(x_free), x_full, free_idx), template)
    jac = stacked_jacobian(model, q_rad, effects)
    return (jac[:, :, free_idx] * sqrt_weights[:, None, None]).reshape(-1, len(free_idx))


def stacked_jacobian(
    model: KinematicModel, q_rad: FloatArray, effects: EffectTerms | None = None
) -> FloatArray:
    """∂TCP/∂(geometry, effect parameters) ``(m, 3, 5n + 9 + k)``, in blocks of poses."""
    k = 0 if effects is None else effects.n_parameters
    p = model.n_parameters
    out = np.empty((len(q_rad), 3, p + k))
    for s in range(0, len(q_rad), CHUNK_POSES):
        e = slice(s, min(s + CHUNK_POSES, len(q_rad)))
        out[e, :, :p] = identification_jacobian(model, q_rad[e])[1]
        if effects is not None:
            out[e, :, p:] = effects.regressor(model, e)
    return out


def predicted_points(
    model: KinematicModel,
    q_rad: FloatArray,
    effects: EffectTerms | None = None,
    effect_values: ArrayLike | None = None,
) -> FloatArray:
    """Predicted tracker points ``(m, 3)`` mm: geometric TCP plus the effect terms."""
    tcp = tcp_positions(model, q_rad)
    if effects is None or effects.n_parameters == 0:
        return tcp
    c = np.asarray(effect_values, dtype=float)
    out = np.empty_like(tcp)
    for s in range(0, len(q_rad), CHUNK_POSES):
        e = slice(s, min(s + CHUNK_POSES, len(q_rad)))
        out[e] = tcp[e] + effects.regressor(model, e) @ c
    return out
