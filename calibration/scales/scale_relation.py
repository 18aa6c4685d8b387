"""The published counts → angle relation of one joint's grating (:class:`GratingScale`):
its candidate terms and basis columns, its uncertainty, and the counter's modulo-2³²
unwrapping. Angles in degrees, counts as raw counter values."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import ScaleError

FloatArray = NDArray[np.float64]


#: a number or an array (the Legendre polynomials take both)
_X = TypeVar("_X", float, FloatArray)


COUNTER_MODULUS = 2**32


ARCSEC_PER_DEG = 3600.0


# candidate term -> (coefficient names, meaning); the order is the selection order
TERMS: dict[str, tuple[tuple[str, ...], str]] = {
    "cyclic": (
        ("cyclic_sin_deg", "cyclic_cos_deg"),
        "first harmonic of the joint angle (strip eccentricity)",
    ),
    "hysteresis": (("hysteresis_deg",), "angle offset backward minus forward sweep"),
    "nonlinear": (
        ("nonlinear_p2_deg", "nonlinear_p3_deg"),
        "smooth non-linearity (Legendre P2, P3 over the sweep)",
    ),
}


SCALE_NAME = "scale_deg_per_count"


# direction of motion: +1 towards the positive limit (as the backward sweep), -1 towards
# the negative one (as the forward sweep), 0 unknown
DIRECTIONS: dict[str, int] = {
    "positive": 1,
    "backward": 1,
    "negative": -1,
    "forward": -1,
    "unknown": 0,
    "": 0,
}


def check_terms(terms: Sequence[str]) -> tuple[str, ...]:
    """Validate term names against :data:`TERMS`; returns them in selection order."""
    for t in terms:
        if t not in TERMS:
            raise ScaleError(f"unknown term {t!r} (known: {', '.join(TERMS)})")
    return tuple(t for t in TERMS if t in terms)


def signed_offset_counts(counts: ArrayLike, reference: float) -> FloatArray:
    """``counts − reference`` reduced modulo 2³² to [−2³¹, 2³¹): undoes counter wraps."""
    c = np.asarray(counts, dtype=np.float64)
    half = COUNTER_MODULUS / 2
    return np.mod(c - reference + half, COUNTER_MODULUS) - half


def _p2(x: _X) -> _X:
    return 0.5 * (3.0 * x * x - 1.0)


def _p3(x: _X) -> _X:
    return 0.5 * (5.0 * x**3 - 3.0 * x)


@dataclass(frozen=True)
class RelationBasis:
    """The functions the relation is built from (fixed when the joint is calibrated).

    ``ψ = phase_rad_per_count · u``; ``x = (u − nonlinear_centre_counts) /
    nonlinear_half_span_counts``.
    """

    phase_rad_per_count: float
    nonlinear_centre_counts: float = 0.0
    nonlinear_half_span_counts: float = 1.0

    def columns(
        self, u: FloatArray, s: FloatArray, terms: Sequence[str]
    ) -> tuple[tuple[str, ...], FloatArray]:
        """Coefficient names and columns ``(N, p)``: ``u`` first, then the terms' columns.

        All columns vanish at ``u = 0, s = 0``, so the relation is zero at the zero.
        """
        names, cols = [SCALE_NAME], [u]
        for t in terms:
            names += TERMS[t][0]
            if t == "cyclic":
                psi = self.phase_rad_per_count * u
                cols += [np.sin(psi), np.cos(psi) - 1.0]
            elif t == "hysteresis":
                cols += [s]
            else:
                x = (u - self.nonlinear_centre_counts) / self.nonlinear_half_span_counts
                x0 = -self.nonlinear_centre_counts / self.nonlinear_half_span_counts
                cols += [_p2(x) - _p2(x0), _p3(x) - _p3(x0)]
        return tuple(names), np.column_stack(cols)


# -- the relation -------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class UnmodelledTerm:
    """A candidate term that was tested and not kept: what adding it would have changed.

    ``delta`` is the change of the coefficients (deg) over the kept names plus the
    term's own; ``delta_covariance_deg2`` its covariance (wider minus kept model, same
    noise level), so that ``δ(c)² − var δ(c)`` estimates the squared bias of leaving the
    term out.
    """

    p_value: float
    delta: Mapping[str, float]
    delta_covariance_deg2: FloatArray


@dataclass(frozen=True, eq=False)
class GratingScale:
    """Counts → angle relative to Home for one joint, with its uncertainty.

    ``a(c) = Σ coefficient · column(u, s)`` in degrees over :class:`RelationBasis` columns,
    with ``u`` the counter value minus ``zero_counts`` modulo 2³² and ``s`` half the
    direction of motion (±½, 0 when unknown: the direction average).

    ``covariance_deg2`` is over ``coefficients`` (same order). ``unmodelled`` holds each
    candidate term that was tested and *not* kept (:class:`UnmodelledTerm`); its
    estimated bias enters :meth:`angle_std_deg`.
    """

    joint: int  # 1-based
    zero_counts: float  # raw counter value at Home, in [0, 2³²)
    zero_std_counts: float  # standard deviation of the zero (of the mean)
    terms: tuple[str, ...]
    coefficients: Mapping[str, float]  # deg per unit column, SCALE_NAME first
    basis: RelationBasis
    covariance_deg2: FloatArray  # (p, p)
    unmodelled: Mapping[str, UnmodelledTerm] = field(default_factory=dict)
    home_deg: float | None = None  # this joint's Home in the robot description, if known

    @property
    def scale_deg_per_count(self) -> float:
        return float(self.coefficients[SCALE_NAME])

    @property
    def counts_per_deg(self) -> float:
        return 1.0 / self.scale_deg_per_count

    @property
    def hysteresis_deg(self) -> float:
        """Angle read moving positive minus moving negative at the same counts (0: not kept)."""
        return float(self.coefficients.get("hysteresis_deg", 0.0))

    @property
    def hysteresis_counts(self) -> float:
        """The same as a reading difference: counts moving positive minus moving negative."""
        return -self.hysteresis_deg / self.scale_deg_per_count

    def effective_radius_mm(self, counts_per_mm: float = 1000.0) -> float:
        """The strip radius the scale implies for a strip of ``counts_per_mm``."""
        return 1.0 / (abs(math.radians(self.scale_deg_per_count)) * counts_per_mm)

    def offset_counts(self, counts: ArrayLike) -> FloatArray:
        """Counts from the zero, unwrapped modulo 2³²."""
        return signed_offset_counts(counts, self.zero_counts)

    def _uvs(self, counts: ArrayLike, direction: ArrayLike | None) -> tuple[FloatArray, ...]:
        u = np.atleast_1d(self.offset_counts(counts))
        d = 0.0 if direction is None else np.asarray(direction, dtype=float)
        s = np.broadcast_to(0.5 * d, u.shape).astype(float)
        return u, s

    def _evaluate(
        self,
        coefficients: Mapping[str, float],
        terms: Sequence[str],
        u: FloatArray,
        s: FloatArray,
    ) -> FloatArray:
        names, x = self.basis.columns(u, s, terms)
        value: FloatArray = x @ np.array([coefficients.get(n, 0.0) for n in names])
        return value

    def counts_to_angle_deg(
        self, counts: ArrayLike, direction: ArrayLike | None = None
    ) -> FloatArray:
        """Angle relative to Home (deg) of raw counter values, shaped like ``counts``.

        ``direction`` (optional, scalar or like ``counts``): +1 while moving towards the
        positive limit, −1 towards the negative one, 0 unknown (the direction average).
        It matters only when the hysteresis term was kept.
        """
        u, s = self._uvs(counts, direction)
        return self._evaluate(self.coefficients, self.terms, u, s).reshape(np.shape(counts))

    def counts_to_joint_deg(
        self, counts: ArrayLike, direction: ArrayLike | None = None
    ) -> FloatArray:
        """The description's joint angle: ``q_deg = home_deg + counts_to_angle_deg(counts)``."""
        if self.home_deg is None:
            raise ScaleError(f"joint {self.joint}: Home angle unknown (no robot description)")
        return self.home_deg + self.counts_to_angle_deg(counts, direction)

    def angle_std_deg(
        self,
        counts: ArrayLike,
        direction: ArrayLike | None = None,
        *,
        include_unmodelled: bool = True,
    ) -> FloatArray:
        """Standard uncertainty (deg) of :meth:`counts_to_angle_deg`, shaped like ``counts``.

        The fit's covariance, the zero's, and (by default) for each term tested but not
        kept its estimated squared bias ``max(0, δ(c)² − var δ(c))``: a correction not
        applied enters the uncertainty with its estimated size (GUM F.2.4.5), less the
        part of it that is only noise.
        """
        u, s = self._uvs(counts, direction)
        _, x = self.basis.columns(u, s, self.terms)
        var = np.einsum("ij,jk,ik->i", x, self.covariance_deg2, x)
        var = var + (self.scale_deg_per_count * self.zero_std_counts) ** 2
        if include_unmodelled:
            for term, un in self.unmodelled.items():
                names, xw = self.basis.columns(u, s, (*self.terms, term))
                delta = xw @ np.array([un.delta.get(n, 0.0) for n in names])
                noise = np.einsum("ij,jk,ik->i", xw, un.delta_covariance_deg2, xw)
                var = var + np.maximum(delta**2 - noise, 0.0)
        std: FloatArray = np.sqrt(var).reshape(np.shape(counts))
        return std
