"""What an identification found (:class:`IdentificationResult`): the identified model,
its covariance, the parameters dropped and why, the poses' weights and outliers, and
the effect parameters with their units."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:  # scipy loads when a fit runs: a command that only reads a model is quick
    from scipy.optimize import OptimizeResult
from calibration.identify.identifiability import (
    IdentifiabilityAnalysis,
)
from calibration.identify.position_residuals import EffectTerms
from calibration.model.kinematics import (
    KinematicModel,
    identification_jacobian,
    tcp_positions,
)

FloatArray = NDArray[np.float64]


# -- the problem and its result ----------------------------------------------------------
@dataclass(frozen=True)
class IdentificationResult:
    """Identified model, its uncertainty, what was dropped, and the solver's own result."""

    model: KinematicModel  # identified geometry, base and tool
    start_model: KinematicModel  # nominal geometry with the start base pose
    start_method: str  # one of START_METHODS
    identifiability: IdentifiabilityAnalysis
    covariance: FloatArray  # (k, k) of the identified parameters, model units (mm, rad)
    sigma_mm: float  # per-axis noise estimated from the residuals (of a reference pose)
    pose_weights: FloatArray  # (m,) final robust-loss weights (1 with the linear loss)
    outliers: NDArray[np.bool_]  # (m,) poses whose residual is improbably large
    loss: str
    f_scale_mm: float | None
    optimize_result: OptimizeResult  # of the last LM run (x: free parameters)
    elapsed_s: float
    irls_iterations: int = 1
    history: list[tuple[int, float, float]] = field(default_factory=list)
    #: with per-point σ: the σ the weights are relative to (their harmonic RMS); sigma_mm
    #: over it is how the data compare with the stated σ (1: as stated). None: unweighted.
    reference_sigma_mm: float | None = None
    #: effect terms identified with the geometry (None: the geometric model alone)
    effects: EffectTerms | None = None
    effect_values: FloatArray = field(default_factory=lambda: np.zeros(0))  # (k,)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Geometric parameter names, then the effect parameters' (with their units)."""
        return self.identifiability.parameter_names

    @property
    def free(self) -> NDArray[np.bool_]:
        return self.identifiability.free

    @property
    def success(self) -> bool:
        return bool(self.optimize_result.success)

    @property
    def n_geometric(self) -> int:
        return self.model.n_parameters

    def parameter_vector(self) -> FloatArray:
        """Identified geometry then effect parameters ``(5n + 9 + k,)``."""
        return np.concatenate([self.model.parameter_vector(), self.effect_values])

    def start_vector(self) -> FloatArray:
        start = np.zeros(0) if self.effects is None else self.effects.start_vector()
        return np.concatenate([self.start_model.parameter_vector(), start])

    def deviations(self) -> FloatArray:
        """Identified minus start parameters, full vector ``(5n + 9 [+ k],)`` (mm, rad)."""
        return self.parameter_vector() - self.start_vector()

    def standard_errors(self) -> FloatArray:
        """Standard errors, full vector (mm, rad, effect units); NaN exactly for the dropped
        parameters (held at their start value), finite for every identified one."""
        se = np.full(len(self.parameter_names), np.nan)
        se[self.free] = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return se

    def residuals_mm(self, q_rad: ArrayLike, measured_mm: ArrayLike) -> FloatArray:
        """Errors ``tracker − twin`` ``(N, 3)`` mm of the identified *geometric* model
        (effect terms need their own per-pose data: see :mod:`calibration.effects.closed_loop`)."""
        return np.asarray(measured_mm, dtype=float) - tcp_positions(self.model, q_rad)

    def prediction_covariance(self, q_rad: ArrayLike) -> FloatArray:
        """Covariance ``(N, 3, 3)`` mm² of the predicted geometric TCP at ``q`` from the
        geometric parameters."""
        _, jac = identification_jacobian(self.model, np.atleast_2d(q_rad))
        p = self.n_geometric
        geo = self.free[:p]
        n_geo = int(np.count_nonzero(geo))
        jf = jac[:, :, geo]
        cov = self.covariance[:n_geo, :n_geo]
        return jf @ cov @ jf.transpose(0, 2, 1)

    def parameter_table(self) -> list[dict[str, object]]:
        """One row per parameter, in human units (mm and degrees; effect parameters in the
        units their names carry)."""
        start = self.start_vector()
        final = self.parameter_vector()
        se = self.standard_errors()
        dropped = {d.name: d.reason for d in self.identifiability.dropped}
        rows = []
        for i, name in enumerate(self.parameter_names):
            if i >= self.n_geometric:
                rows.append(
                    {
                        "name": name,
                        "unit": effect_unit(name),
                        "start": float(start[i]),
                        "identified": float(final[i]),
                        "deviation": float(final[i] - start[i]),
                        "standard_error": None if np.isnan(se[i]) else float(se[i]),
                        "identified_from_data": bool(self.free[i]),
                        "dropped_reason": dropped.get(name),
                    }
                )
                continue
            to_deg = name.endswith("_rad")
            k = math.degrees(1.0) if to_deg else 1.0
            unit = "deg" if to_deg else "mm"
            rows.append(
                {
                    "name": name.removesuffix("_rad").removesuffix("_mm") + f"_{unit}",
                    "unit": unit,
                    "start": float(start[i] * k),
                    "identified": float(final[i] * k),
                    "deviation": float((final[i] - start[i]) * k),
                    "standard_error": None if np.isnan(se[i]) else float(se[i] * k),
                    "identified_from_data": bool(self.free[i]),
                    "dropped_reason": dropped.get(name),
                }
            )
        return rows


#: Unit suffixes of effect parameter names (longest first) -> unit for people.
EFFECT_UNITS = (
    ("_urad_per_knm", "µrad/(kN·m)"),
    ("_mm_per_h2", "mm/h²"),
    ("_ppm_per_h", "ppm/h"),
    ("_mm_per_h", "mm/h"),
    ("_ppm", "ppm"),
    ("_deg", "deg"),
    ("_mm", "mm"),
)


def effect_unit(name: str) -> str:
    """The unit an effect parameter's name ends with (``''`` when none is known)."""
    return next((u for suffix, u in EFFECT_UNITS if name.endswith(suffix)), "")
