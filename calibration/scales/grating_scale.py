"""Grating-scale calibration of one joint (method §2): counts → angle relative to Home.

Inputs per joint: the raw counter values at the Home returns and, for the two 2° sweeps,
the counter value and the tracker point at every stop. Steps:

1. **Unwrap** every counter value against one reference modulo 2³² (signed offset).
2. **Home zero**: mean of the Home returns (spread reported). A joint without Home rows
   takes its zero from the sweep stops next to the nominal Home angle, using the
   commanded angles of those stops (positive limit − 2°·step), and says so.
3. **Stop angles**: one 3-D circle per sweep (reported, and compared), and one common
   circle through both sweeps (the same physical circle) whose angles start the relation;
   with two or more reflectors the rigid rotation of the target set instead
   (:mod:`calibration.scales.target_set_fit`). One angle origin for both sweeps is what makes a
   direction-dependent offset observable.
4. **Relation**::

       θ_k = θ₀ + g·u_k + [a·sin ψ_k + b·(cos ψ_k − 1)] + [η·s_k] + [c₂·ΔP₂ + c₃·ΔP₃]

   with ``u`` the counts from the Home zero, ``ψ = g₀·u`` the angle from Home (rad, g₀
   from the zero-and-scale fit), ``s = ±½`` for the backward/forward sweep,
   ``ΔPₙ = Pₙ(x) − Pₙ(x(0))`` Legendre polynomials of the counts scaled to [−1, 1] over
   the sweep. θ₀ is the frame's arbitrary origin and is not part of the relation, which is
   zero at the zero. Fitted **straight to the tracker points** together with the circle
   or target-set structure, by maximum likelihood (:mod:`calibration.scales.relation_to_points`),
   each stop's angle also carrying the grating's read noise. The start is the generalized
   least squares fit to the stop angles with their full covariance (tangential noise
   plus the part shared through the axis), which agrees to first order; on short arcs
   not to second: its scale on a 4° arc with one target came out long by 0.6 of its
   standard deviation, and with three targets its F-tests kept twice the false terms.
   Should the joint fit not converge, the two-step fit is used and a note says so.
5. **Model selection** with nested-model F-tests on the joint fit's residuals (3
   coordinates per point; exact for a linear Gaussian model with unknown noise level),
   each at ``alpha / m`` (Bonferroni over the ``m`` candidate terms, so a strip with none
   of the effects gets any extra term with probability ≤ ``alpha``): forward in the
   physical order cyclic → hysteresis → non-linearity, each tested against the terms
   already kept, then a backward check of every kept term against the final model. The
   order matters on short arcs, where a first harmonic and a cubic are nearly the same
   curve: the physically expected eccentricity goes first.
6. **Uncertainty**: the covariance of the relation (noise level from the joint fit's
   residuals), the zero's standard deviation, and for every candidate term *not* kept the
   change the term would have made to the relation (a correction not applied enters the
   uncertainty with its estimated size, GUM F.2.4.5). The last part matters on short
   arcs, where an eccentricity just below the detection limit still bends the relation:
   the strip's first harmonic is confounded with the circle centre, so only the
   centre's radial information separates them. It is conservative where nothing is
   there (error / uncertainty 0.80–0.84 RMS on 470° arcs of 10 stops, 1.0 without it).

Angles: "angle relative to Home" ``a(c)`` is the joint rotation (deg) from where the
joint sits at the Home zero, positive in the joint's positive direction (the forward sweep
runs from the positive limit to the negative one, so angles decrease along it). The twin
forms the joint angle of its description as ``q_deg = home_deg + a(c)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import CircleFitError, ScaleError
from calibration.scales.circle_fit import CircleFit, fit_circle_3d
from calibration.scales.relation_to_points import RelationToPoints, StopPoints
from calibration.scales.target_set_fit import TargetSetFit, crb_covariance_targets, fit_target_set

FloatArray = NDArray[np.float64]
#: a circle fit or a target-set fit (both can be oriented)
_Fit = TypeVar("_Fit", CircleFit, TargetSetFit)
#: a number or an array (the Legendre polynomials take both)
_X = TypeVar("_X", float, FloatArray)
IntArray = NDArray[np.int64]

COUNTER_MODULUS = 2**32
ARCSEC_PER_DEG = 3600.0
PASSES: tuple[str, str] = ("forward", "backward")
MIN_STOPS_PER_PASS = 6
RESOLUTION_STD_COUNTS = 1.0 / math.sqrt(12.0)  # whole counts: rectangular ±½ count

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


@dataclass(frozen=True)
class TrackerSpec:
    """Data-sheet MPE of the tracker: ``±(mpe_um + mpe_um_per_m · distance)`` at ``mpe_sigmas``.

    Gives the *relative* weights of the points (the tracker sits at the origin of its
    frame); the noise level itself is estimated from the residuals.
    """

    mpe_um: float = 15.0
    mpe_um_per_m: float = 6.0
    mpe_sigmas: float = 2.0

    def sigma_mm(self, points_mm: ArrayLike) -> FloatArray:
        """Per-axis standard deviation (mm) of a measurement of each point, ``(N,)``."""
        dist_m = np.linalg.norm(np.atleast_2d(points_mm), axis=-1) / 1000.0
        sigma: FloatArray = 1e-3 * (self.mpe_um + self.mpe_um_per_m * dist_m) / self.mpe_sigmas
        return sigma


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


# -- input and result types ----------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class JointSweep:
    """The sweep stops of one joint, in any order. Arrays ``(S,)`` / ``(S, 3)``.

    ``rows`` are the source-file row numbers (for messages), or -1. ``chain_counts``
    ``(S, n)`` holds every joint's raw grating reading at the stop (None: not recorded),
    for taking the other joints' motion out (:mod:`calibration.scales.chain_scale`).
    """

    joint: int
    pass_name: NDArray[np.str_]
    step: IntArray
    counts: IntArray
    points_mm: FloatArray
    rows: IntArray | None = None
    chain_counts: IntArray | None = None
    target: IntArray | None = None  # (S,) reflector of each row: T targets per stop

    @property
    def n_stops(self) -> int:
        """Stops (one per pass and step, whatever the number of targets)."""
        if self.target is None:
            return int(self.step.shape[0])
        return len({(p, int(k)) for p, k in zip(self.pass_name, self.step, strict=True)})

    @property
    def n_targets(self) -> int:
        return 1 if self.target is None else len(set(self.target.tolist()))


@dataclass(frozen=True)
class HomeZero:
    """The counter value taken as Home and how it was obtained."""

    counts: float  # raw counter value in [0, 2³²)
    spread_counts: float  # standard deviation of the individual readings/estimates
    n: int
    source: str  # "home" (mean of the returns) or "sweep-crossing"

    @property
    def std_counts(self) -> float:
        """Standard deviation of the zero (the mean).

        The spread is floored at the counter's resolution (1/√12 count): identical whole
        readings do not make the zero exact.
        """
        return max(self.spread_counts, RESOLUTION_STD_COUNTS) / math.sqrt(max(self.n, 1))


@dataclass(frozen=True)
class TermTest:
    """Nested-model F-test of one candidate term."""

    term: str
    kept: bool
    f_statistic: float
    dof_term: int
    dof_residual: int
    p_value: float
    threshold: float  # the p-value below which the term is kept


@dataclass(frozen=True)
class ScaleOptions:
    """Options of :func:`calibrate_joint`."""

    alpha: float = 0.01  # family-wise false-term rate per joint
    candidate_terms: tuple[str, ...] = tuple(TERMS)
    tracker: TrackerSpec = TrackerSpec()
    counts_per_mm: float = 1000.0  # strip resolution, for the effective radius
    step_deg: float = 2.0  # commanded step, for the zero from the sweep crossing
    outlier_alpha: float = 1e-3  # per-joint false wild-point rate (circle and relation)
    # 1σ read noise of the grating head at a stop before rounding to whole counts (the
    # rounding adds 1/12 count²): each stop's angle about the relation carries it
    read_noise_counts: float = 0.5
    min_stops_per_pass: int = MIN_STOPS_PER_PASS


@dataclass(frozen=True, eq=False)
class JointScaleResult:
    """Everything the calibration of one joint found. Arrays are over the S stops."""

    joint: int
    scale: GratingScale
    home: HomeZero
    # common circle of both sweeps (or the common fit of a target set), oriented with the
    # joint's + direction; one per sweep below, same orientation
    circle: CircleFit | TargetSetFit
    pass_circles: Mapping[str, CircleFit | TargetSetFit]
    tests: tuple[TermTest, ...]
    pass_name: NDArray[np.str_]  # (S,)
    step: IntArray  # (S,)
    offset_counts: FloatArray  # (S,) u: counts from the zero, unwrapped
    stop_angle_deg: FloatArray  # (S,) angle from the circle, relative to Home
    stop_angle_std_deg: FloatArray  # (S,) its standard deviation (common offset excluded)
    residual_deg: FloatArray  # (S,) circle angle minus relation (NaN for dropped stops)
    used: NDArray[np.bool_]  # (S,) stops used in the relation
    dropped: tuple[tuple[int, str], ...]  # (index in the JointSweep, reason with pass/step/row)
    variance_factor: float  # s² of the published relation (tracker noise relative to its model)
    crb_covariance_rad2: FloatArray  # (p, p) bound on the relation coefficients (rad units)
    notes: tuple[str, ...] = ()

    @property
    def residual_rms_deg(self) -> float:
        return float(np.sqrt(np.mean(self.residual_deg[self.used] ** 2)))

    @property
    def residual_rms_arcsec(self) -> float:
        return ARCSEC_PER_DEG * self.residual_rms_deg

    @property
    def strip_direction(self) -> int:
        """+1 when the counts rise with the joint angle, −1 otherwise."""
        return 1 if self.scale.scale_deg_per_count > 0 else -1

    @property
    def kept_terms(self) -> tuple[str, ...]:
        return self.scale.terms

    @property
    def tracker_sigma_um(self) -> float:
        """Tracker per-axis noise estimated from the common circle's residuals (median)."""
        return 1e3 * float(np.median(self.circle.point_sigma_mm))

    @property
    def stop_counts(self) -> FloatArray:
        """Raw counter value of every stop (float, wrapped), ``(S,)``."""
        return np.mod(self.offset_counts + self.scale.zero_counts, COUNTER_MODULUS)

    @property
    def stop_direction(self) -> FloatArray:
        """Direction of motion at every stop: −1 forward sweep, +1 backward, ``(S,)``."""
        return np.where(self.pass_name == "backward", 1.0, -1.0)

    def test(self, term: str) -> TermTest | None:
        """The selection test of ``term``, if it was a candidate."""
        return next((t for t in self.tests if t.term == term), None)

    @property
    def crb_angle_std_deg(self) -> FloatArray:
        """Cramér-Rao bound on the relation at every stop (zero excluded), ``(S,)`` deg."""
        s = np.zeros_like(self.offset_counts)  # direction average
        _, x = self.scale.basis.columns(self.offset_counts, s, self.scale.terms)
        cov = self.crb_covariance_rad2[1:, 1:]
        std: FloatArray = np.degrees(np.sqrt(np.einsum("ij,jk,ik->i", x, cov, x)))
        return std


# -- the fit --------------------------------------------------------------------------------
# -- the fit --------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class _Whitener:
    """``W`` with ``WᵀW = V⁻¹`` for ``V = diag(d) + B·Bᵀ`` (B of low rank), in O(N)."""

    d: FloatArray  # (n,)
    b: FloatArray  # (n, r)
    basis: FloatArray  # (n, r) left singular vectors of D^-1/2 B
    shrink: FloatArray  # (r,)

    @classmethod
    def build(cls, d: FloatArray, b: FloatArray) -> _Whitener:
        bd = b / np.sqrt(d)[:, None]
        basis, sv, _ = np.linalg.svd(bd, full_matrices=False)
        return cls(d, b, basis, 1.0 - 1.0 / np.sqrt(1.0 + sv**2))

    def apply(self, x: FloatArray) -> FloatArray:
        """``W·x`` for ``x`` of shape ``(n,)`` or ``(n, p)``."""
        z = x.reshape(len(self.d), -1) / np.sqrt(self.d)[:, None]
        z = z - self.basis @ (self.shrink[:, None] * (self.basis.T @ z))
        return z.reshape(x.shape)

    @property
    def diag(self) -> FloatArray:
        total: FloatArray = self.d + np.einsum("ij,ij->i", self.b, self.b)
        return total


class _NoJointFit(Exception):
    """The relation's fit to the points did not converge (the caller falls back)."""


@dataclass(frozen=True, eq=False)
class _Gls:
    beta: FloatArray
    cov_unit: FloatArray  # (XᵀV⁻¹X)⁻¹
    rss: float  # rᵀV⁻¹r
    rank: int
    n: int

    @property
    def s2(self) -> float:
        return self.rss / max(self.n - self.rank, 1)


def _gls(y: FloatArray, x: FloatArray, white: _Whitener) -> _Gls:
    """Generalized least squares of ``y`` on ``x`` (columns scaled for conditioning)."""
    x_w = white.apply(x)
    y_w = white.apply(y)
    norms = np.linalg.norm(x_w, axis=0)
    norms[norms == 0] = 1.0
    a = x_w / norms
    left, sv, vt = np.linalg.svd(a, full_matrices=False)
    keep = sv > 1e-10 * sv[0]
    coef = (vt[keep].T / sv[keep]) @ (left[:, keep].T @ y_w)
    resid_w = y_w - a @ coef
    cov = ((vt[keep].T / sv[keep] ** 2) @ vt[keep]) / np.outer(norms, norms)
    return _Gls(coef / norms, cov, float(resid_w @ resid_w), int(keep.sum()), len(y))


def _f_test(full: _Gls, reduced: _Gls) -> tuple[float, int, int, float]:
    """Nested-model F-test: statistic, term dof, residual dof, p-value."""
    from scipy import stats  # loads when a fit runs: a refused input is said at once

    d1 = full.rank - reduced.rank
    d2 = full.n - full.rank
    if d1 <= 0 or d2 <= 0 or full.rss <= 0:
        return 0.0, max(d1, 0), d2, 1.0
    f = ((reduced.rss - full.rss) / d1) / (full.rss / d2)
    return float(f), d1, d2, float(stats.f.sf(max(f, 0.0), d1, d2))


def crb_covariance(
    circle: CircleFit, angle_rad: ArrayLike, design: ArrayLike, sigma_mm: ArrayLike
) -> FloatArray:
    """Cramér-Rao bound on the coefficients of ``θ_k = design_k · β`` (rad units).

    The bound of the direct 3-D model ``p_k = c + ρ(cos θ_k·u + sin θ_k·v) + noise``,
    isotropic per-axis noise ``sigma_mm`` ``(S,)``, with the circle (centre, normal,
    radius) unknown. ``circle`` supplies the geometry, ``angle_rad`` ``(S,)`` the stop
    angles in its frame, ``design`` ``(S, p)`` the relation's columns (the first should be
    the intercept θ₀). Returns the ``(p, p)`` block of the inverse Fisher information.
    """
    th = np.asarray(angle_rad, dtype=float)
    x = np.asarray(design, dtype=float)
    sig = np.broadcast_to(np.asarray(sigma_mm, dtype=float), th.shape)
    u, v = circle.axis_u, circle.axis_v
    radial = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v  # (S, 3)
    tangent = -np.sin(th)[:, None] * u + np.cos(th)[:, None] * v
    rel = circle.radius_mm * radial
    cols = [np.broadcast_to(np.eye(3)[i], rel.shape) for i in range(3)]
    cols += [np.cross(v, rel), -np.cross(u, rel), radial]  # tilts and radius
    cols += [circle.radius_mm * tangent * x[:, j : j + 1] for j in range(x.shape[1])]
    jac = np.stack(cols, axis=-1) / sig[:, None, None]  # (S, 3, 6 + p)
    info = np.einsum("kai,kaj->ij", jac, jac)
    scale = np.sqrt(np.diag(info))
    scale[scale == 0] = 1.0
    cov = np.linalg.pinv(info / np.outer(scale, scale), rcond=1e-12, hermitian=True)
    cov_angles: FloatArray = (cov / np.outer(scale, scale))[6:, 6:]
    return cov_angles


def _commanded_deg(
    pass_name: NDArray[np.str_], step: IntArray, lower: float, upper: float, step_deg: float
) -> FloatArray:
    """Commanded angle of every stop: forward from the positive limit, backward the reverse."""
    n_fwd = math.floor((upper - lower) / step_deg + 1e-9) + 1
    last = upper - step_deg * (n_fwd - 1)
    return np.where(pass_name == "forward", upper - step_deg * step, last + step_deg * step)


def _orient_like(fit: _Fit, normal: FloatArray) -> _Fit:
    return fit if fit.normal @ normal >= 0 else fit.flipped()


def _unwrap_inliers(angle: FloatArray, inlier: NDArray[np.bool_]) -> FloatArray:
    """Unwrap along the order using inliers only; outliers take their nearest inlier's turn."""
    out = angle.copy()
    idx = np.flatnonzero(inlier)
    out[idx] = np.unwrap(angle[idx])
    for k in np.flatnonzero(~inlier):
        j = idx[np.argmin(np.abs(idx - k))]
        out[k] = out[j] + np.angle(np.exp(1j * (angle[k] - angle[j])))
    return out


@dataclass(frozen=True, eq=False)
class _Angles:
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


def _target_set_angles(sweep: JointSweep, reference: float, opt: ScaleOptions) -> _Angles:
    """As :func:`_circle_angles` for T ≥ 2 reflectors: each stop's angle from the rigid
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
        theta[m] = _unwrap_inliers(common.angle_rad[m], inlier[m])
    u_raw = signed_offset_counts(sweep.counts[first[stops]], reference)
    if len(passes) == 2:
        _same_turn(theta, pass_name, inlier, u_raw)
    pass_fits = {p: _orient_like(c, common.normal) for p, c in pass_fits.items()}
    return _Angles(
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


def _circle_angles(sweep: JointSweep, reference: float, opt: ScaleOptions) -> _Angles:
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
        theta[m] = _unwrap_inliers(full.angle_rad[m], inlier[m])
    if len(passes) == 2:
        _same_turn(theta, pass_name, inlier, u_raw)
    pass_circles = {p: _orient_like(c, full.normal) for p, c in pass_circles.items()}
    return _Angles(
        order, pass_name, sweep.step[order], u_raw, theta, inlier, full, pass_circles, dropped
    )


def _home_zero(
    home: IntArray,
    reference: float,
    ang: _Angles,
    white_all: tuple[FloatArray, FloatArray],
    *,
    joint: int,
    home_deg: float | None,
    limits_deg: tuple[float, float] | None,
    opt: ScaleOptions,
) -> tuple[HomeZero, float, list[str]]:
    """The zero as a raw counter value, and as an offset from ``reference``."""
    if home.size:
        u_home = signed_offset_counts(home, reference)
        zero_u = float(u_home.mean())
        spread = float(u_home.std(ddof=1)) if home.size > 1 else 0.0
        zero = HomeZero(
            float(np.mod(reference + zero_u, COUNTER_MODULUS)), spread, home.size, "home"
        )
        return zero, zero_u, []
    if home_deg is None or limits_deg is None:
        raise ScaleError(
            f"joint {joint}: no Home returns, and no robot description to find the nominal "
            "Home on the sweep"
        )
    idx = np.flatnonzero(ang.inlier)
    white = _Whitener.build(white_all[0][idx], white_all[1][idx])
    x = np.column_stack([np.ones(idx.size), ang.u_raw[idx]])
    g0 = _gls(ang.theta[idx], x, white).beta[1]
    cmd = _commanded_deg(ang.pass_name, ang.step, *limits_deg, opt.step_deg)
    near = ang.inlier & (np.abs(cmd - home_deg) <= opt.step_deg + 1e-9)
    if not near.any():
        raise ScaleError(f"joint {joint}: no sweep stop within {opt.step_deg}° of Home")
    est = ang.u_raw[near] + np.radians(home_deg - cmd[near]) / g0
    zero_u = float(est.mean())
    spread = float(est.std(ddof=1)) if est.size > 1 else 0.0
    zero = HomeZero(
        float(np.mod(reference + zero_u, COUNTER_MODULUS)), spread, est.size, "sweep-crossing"
    )
    note = (
        f"no Home returns: zero from {est.size} sweep stops within {opt.step_deg}° of the "
        f"nominal Home {home_deg}° (their commanded angles; robot positioning error applies)"
    )
    return zero, zero_u, [note]


def _worst_residual(
    theta: FloatArray, x: FloatArray, white: _Whitener, outlier_alpha: float
) -> tuple[int, float, float]:
    """Index of the largest studentized residual (robust scale), its z, and the limit."""
    from scipy import stats  # loads when a fit runs: a refused input is said at once

    fit = _gls(theta, x, white)
    resid = theta - x @ fit.beta
    var = white.diag - np.einsum("ij,jk,ik->i", x, fit.cov_unit, x)
    z = resid / np.sqrt(np.maximum(var, 1e-300))
    z = z / max(1.4826 * float(np.median(np.abs(z))), 1e-300)
    k = int(np.argmax(np.abs(z)))
    return k, float(z[k]), float(stats.norm.isf(outlier_alpha / (2 * len(theta))))


def calibrate_joint(
    sweep: JointSweep,
    home_counts: ArrayLike | None,
    *,
    home_deg: float | None = None,
    limits_deg: tuple[float, float] | None = None,
    options: ScaleOptions | None = None,
) -> JointScaleResult:
    """Calibrate one joint's grating from its sweeps and Home returns.

    ``home_counts``: raw counter values at the Home returns (``None`` or empty: the zero
    comes from the sweep stops at the nominal Home, which needs ``home_deg`` and
    ``limits_deg`` of the joint). Raises :class:`ScaleError` when the data cannot give a
    calibration.

    Long for the result's many fields; each step is a function (or a :class:`_Relation`
    method) of its own.
    """
    opt = options or ScaleOptions()
    candidates = check_terms(opt.candidate_terms)
    j = sweep.joint
    home = np.asarray(home_counts if home_counts is not None else [], dtype=np.int64)
    if sweep.n_stops == 0:
        raise ScaleError(f"joint {j}: no sweep stops")
    reference = float(home[0]) if home.size else float(sweep.counts[0])

    ang = _circle_angles(sweep, reference, opt)
    circle, theta, inlier, dropped = ang.circle, ang.theta, ang.inlier, ang.dropped
    d_all, b_all = circle.angle_covariance_factors()  # unit-variance V = diag(d) + B·Bᵀ
    d_all, b_all = d_all / circle.variance_factor, b_all / math.sqrt(circle.variance_factor)
    zero, zero_u, notes = _home_zero(
        home,
        reference,
        ang,
        (d_all, b_all),
        joint=j,
        home_deg=home_deg,
        limits_deg=limits_deg,
        opt=opt,
    )
    u = ang.u_raw - zero_u
    s = np.where(ang.pass_name == "backward", 0.5, -0.5)
    two_passes = len(set(ang.pass_name.tolist())) == 2
    g0 = _first_order_gain(theta, u, _whitened(d_all, b_all, inlier), j)
    # each stop's angle about the relation also carries the read noise of its counts
    read_noise_rad = abs(g0) * math.sqrt(opt.read_noise_counts**2 + 1.0 / 12.0)
    d_circle = d_all
    d_all = d_all + read_noise_rad**2
    basis = _basis_over(g0, u[inlier])
    usable = [t for t in candidates if t != "hysteresis" or two_passes]
    wild = _WildAngles(theta, _design(basis, u, s, usable), d_all, b_all, ang.order)
    white, idx = wild.drop(inlier, dropped, opt.outlier_alpha)
    relation = _Relation(
        basis, u, s, theta, idx, white, StopPoints.of(circle, inlier), read_noise_rad
    )
    kept, tests, published, scale = _selected_scale(j, relation, usable, opt, zero, home_deg, notes)
    final = relation.fit_angles(kept)
    x_all = relation.design(kept)
    theta_pub = relation.refined_angles(kept, circle)
    resid = theta_pub - x_all @ published.beta
    var_stop = relation.stop_angle_variance(final, x_all, b_all, d_circle)
    crb, stored = _crb(circle, theta[idx], x_all[idx], idx, inlier)
    return JointScaleResult(
        joint=j,
        scale=scale,
        home=zero,
        circle=stored,
        pass_circles=ang.pass_circles,
        tests=tuple(tests),
        pass_name=ang.pass_name,
        step=ang.step,
        offset_counts=u,
        stop_angle_deg=np.degrees(theta_pub - published.beta[0]),
        stop_angle_std_deg=np.degrees(np.sqrt(final.s2 * np.maximum(var_stop, 0.0))),
        residual_deg=np.where(inlier, np.degrees(resid), np.nan),
        used=inlier.copy(),
        dropped=tuple((i, why + _stop_label(sweep, i)) for i, why in dropped),
        variance_factor=published.s2,
        crb_covariance_rad2=crb,
        notes=tuple(notes),
    )


def _whitened(
    d: FloatArray, b: FloatArray, inlier: NDArray[np.bool_]
) -> tuple[_Whitener, IntArray]:
    """The whitener of the inlier stops' angle covariance ``diag(d) + B·Bᵀ``, and their indices."""
    idx = np.flatnonzero(inlier)
    return _Whitener.build(d[idx], b[idx]), idx


def _first_order_gain(
    theta: FloatArray, u: FloatArray, whitened: tuple[_Whitener, IntArray], joint: int
) -> float:
    """The straight line's slope (rad per count) of the stop angles ``theta`` ``(K,)`` on
    the count offsets ``u`` ``(K,)``, over the stops ``whitened`` holds."""
    white, idx = whitened
    base = _gls(theta[idx], np.column_stack([np.ones(idx.size), u[idx]]), white)
    g0 = float(base.beta[1])
    if g0 == 0 or not np.isfinite(g0):
        raise ScaleError(f"joint {joint}: counts do not change with the joint angle")
    return g0


def _basis_over(g0: float, span: FloatArray) -> RelationBasis:
    """The basis for the count offsets ``span`` ``(K,)`` the relation is fitted on: the cyclic
    phase from the first-order gain ``g0`` rad per count, the polynomials over their range."""
    return RelationBasis(
        phase_rad_per_count=g0,
        nonlinear_centre_counts=0.5 * float(span.max() + span.min()),
        nonlinear_half_span_counts=max(0.5 * float(span.max() - span.min()), 1.0),
    )


def _design(basis: RelationBasis, u: FloatArray, s: FloatArray, terms: Sequence[str]) -> FloatArray:
    """The relation's design ``(K, 2 + …)``: the intercept θ₀, then the basis columns."""
    _, x = basis.columns(u, s, terms)
    return np.column_stack([np.ones_like(u), x])


@dataclass(frozen=True, eq=False)
class _WildAngles:
    """The test for wild stop angles (a tangential wild point is invisible to the circle):
    the angles ``theta`` ``(K,)`` on the full model ``design`` ``(K, p)``, their covariance
    factors ``d`` ``(K,)``, ``b`` ``(K, r)``, the stops' rows ``order`` ``(K,)``."""

    theta: FloatArray
    design: FloatArray
    d: FloatArray
    b: FloatArray
    order: IntArray

    def drop(
        self, inlier: NDArray[np.bool_], dropped: list[tuple[int, str]], outlier_alpha: float
    ) -> tuple[_Whitener, IntArray]:
        """Drop the worst stop while its studentized residual is beyond the limit, at most
        one stop in 25 (``inlier`` and ``dropped`` in place); the whitener of the stops left
        and their indices."""
        white, idx = _whitened(self.d, self.b, inlier)
        for _ in range(max(1, int(inlier.sum()) // 25)):
            k, z, limit = _worst_residual(self.theta[idx], self.design[idx], white, outlier_alpha)
            if abs(z) <= limit:
                break
            inlier[idx[k]] = False
            dropped.append((int(self.order[idx[k]]), f"relation: angle residual {z:+.1f}σ"))
            white, idx = _whitened(self.d, self.b, inlier)
        return white, idx


@dataclass(frozen=True, eq=False)
class _Relation:
    """The relation's fits over one joint's stops (K of them): their count offsets from the
    zero ``u`` and pass signs ``s`` ``(K,)``, their angles ``theta`` ``(K,)`` rad, the stops
    used ``idx`` and the whitener of their angles' covariance."""

    basis: RelationBasis
    u: FloatArray
    s: FloatArray
    theta: FloatArray
    idx: IntArray
    white: _Whitener
    points: StopPoints
    read_noise_rad: float
    joint_fits: dict[tuple[str, ...], RelationToPoints] = field(default_factory=dict)

    def design(self, terms: Sequence[str]) -> FloatArray:
        return _design(self.basis, self.u, self.s, terms)

    def fit_angles(self, terms: Sequence[str]) -> _Gls:
        """Two-step: the relation fitted to the stop angles."""
        return _gls(self.theta[self.idx], self.design(terms)[self.idx], self.white)

    def fit_points(self, terms: Sequence[str]) -> _Gls:
        """The relation and the structure fitted to the tracker points (kept per terms)."""
        key = tuple(terms)
        if key not in self.joint_fits:
            fit = self.points.fit(
                self.design(terms), self.fit_angles(terms).beta, self.read_noise_rad
            )
            if fit is None:
                raise _NoJointFit
            self.joint_fits[key] = fit
        fit = self.joint_fits[key]
        return _Gls(fit.beta, fit.cov_unit, fit.rss, fit.rank, fit.n)

    def refined_angles(self, kept: Sequence[str], circle: CircleFit | TargetSetFit) -> FloatArray:
        """The stops' angles ``(K,)`` rad under the structure refined with the relation
        ``kept`` (the circle's when the joint fit did not run)."""
        if tuple(kept) not in self.joint_fits:
            return self.theta
        refined = self.joint_fits[tuple(kept)].angle_rad
        theta: FloatArray = self.theta + np.angle(np.exp(1j * (refined - circle.angle_rad)))
        return theta

    def stop_angle_variance(
        self, final: _Gls, x_all: FloatArray, b_all: FloatArray, d_circle: FloatArray
    ) -> FloatArray:
        """Unit variance ``(K,)`` of each stop's angle from Home by the circle, θ_k − θ̂₀:
        var = V_kk + var(θ̂₀) − 2 cov(θ̂₀, θ_k), cov(θ̂₀, θ_k) = [Cov·Xᵀ·V⁻¹·V]₀ₖ."""
        idx = self.idx
        wb = self.white.apply(b_all[idx])
        cov_theta0 = (final.cov_unit @ (self.white.apply(x_all[idx]).T @ wb))[0] @ b_all.T
        cov_theta0[idx] = (final.cov_unit @ x_all[idx].T)[0]  # used stops: V⁻¹·V = I
        var_stop = d_circle + np.einsum("ij,ij->i", b_all, b_all)
        var: FloatArray = var_stop + final.cov_unit[0, 0] - 2 * cov_theta0
        return var


def _selected_scale(
    joint: int,
    relation: _Relation,
    usable: Sequence[str],
    opt: ScaleOptions,
    zero: HomeZero,
    home_deg: float | None,
    notes: list[str],
) -> tuple[list[str], list[TermTest], _Gls, GratingScale]:
    """The terms kept, their tests, the published fit and the scale: fitted to the points,
    or to the stop angles when that fit does not converge (said in ``notes``, in place)."""
    threshold = opt.alpha / max(len(usable), 1)
    for fit_terms in (relation.fit_points, relation.fit_angles):
        try:
            kept, tests = _select_terms(usable, fit_terms, threshold)
            published = fit_terms(kept)
            scale = _publish(
                joint, zero, published, kept, tests, relation.basis, fit_terms, home_deg
            )
            break
        except _NoJointFit:
            notes.append(
                "the fit of the relation to the tracker points did not converge: relation "
                "fitted to the stop angles (two-step, first order)"
            )
    return kept, tests, published, scale


def _crb(
    circle: CircleFit | TargetSetFit,
    theta_used: FloatArray,
    x_used: FloatArray,
    idx: IntArray,
    inlier: NDArray[np.bool_],
) -> tuple[FloatArray, CircleFit | TargetSetFit]:
    """The Cramér-Rao bound of the relation's coefficients over the stops used (their angles
    and design rows), and the angle fit as stored (a circle with the relation's inliers)."""
    if isinstance(circle, CircleFit):
        crb = crb_covariance(circle, theta_used, x_used, circle.point_sigma_mm[idx])
        return crb, replace(circle, inlier=inlier.copy())
    # a target set: its own bound; stops dropped by the relation are in `used`
    crb = crb_covariance_targets(
        circle, theta_used, x_used, circle.target_sigma_mm[idx], circle.point_inlier[idx]
    )
    return crb, circle


def _stop_label(sweep: JointSweep, i: int) -> str:
    row = f", row {sweep.rows[i]}" if sweep.rows is not None else ""
    return f" ({sweep.pass_name[i]} step {sweep.step[i]}{row})"


def _select_terms(
    usable: Sequence[str], fit_terms: Callable[[Sequence[str]], _Gls], threshold: float
) -> tuple[list[str], list[TermTest]]:
    """Forward selection in :data:`TERMS` order, then a backward check; F-tests at ``threshold``."""
    kept: list[str] = []
    for t in usable:
        if _f_test(fit_terms([*kept, t]), fit_terms(kept))[3] <= threshold:
            kept.append(t)
    while kept:  # a later term may make an earlier one redundant
        final = fit_terms(kept)
        p = {t: _f_test(final, fit_terms([c for c in kept if c != t]))[3] for t in kept}
        weakest = max(kept, key=lambda t: p[t])
        if p[weakest] <= threshold:
            break
        kept.remove(weakest)
    final = fit_terms(kept)
    tests = []
    for t in usable:
        if t in kept:  # drop-one test against the final model
            f, d1, d2, p_value = _f_test(final, fit_terms([c for c in kept if c != t]))
        else:  # add-one test
            f, d1, d2, p_value = _f_test(fit_terms([*kept, t]), final)
        tests.append(TermTest(t, t in kept, f, d1, d2, p_value, threshold))
    return kept, tests


def _publish(
    joint: int,
    zero: HomeZero,
    fit: _Gls,
    kept: Sequence[str],
    tests: Sequence[TermTest],
    basis: RelationBasis,
    fit_terms: Callable[[Sequence[str]], _Gls],
    home_deg: float | None,
) -> GratingScale:
    """The relation in degrees (all columns are angle per unit, so rad → deg throughout)."""
    deg2 = math.degrees(1.0) ** 2
    names, _ = basis.columns(np.zeros(1), np.zeros(1), kept)
    coefficients = {n: math.degrees(b) for n, b in zip(names, fit.beta[1:], strict=True)}
    unmodelled = {}
    for test in tests:
        if test.kept:
            continue
        wide = fit_terms([*kept, test.term])
        wide_names, _ = basis.columns(np.zeros(1), np.zeros(1), [*kept, test.term])
        narrow_cov = np.zeros_like(wide.cov_unit)
        narrow_cov[: fit.cov_unit.shape[0], : fit.cov_unit.shape[0]] = fit.cov_unit
        unmodelled[test.term] = UnmodelledTerm(
            p_value=test.p_value,
            delta={
                n: math.degrees(b) - coefficients.get(n, 0.0)
                for n, b in zip(wide_names, wide.beta[1:], strict=True)
            },
            delta_covariance_deg2=wide.s2 * (wide.cov_unit - narrow_cov)[1:, 1:] * deg2,
        )
    return GratingScale(
        joint=joint,
        zero_counts=zero.counts,
        zero_std_counts=zero.std_counts,
        terms=tuple(kept),
        coefficients=coefficients,
        basis=basis,
        covariance_deg2=fit.s2 * fit.cov_unit[1:, 1:] * deg2,
        unmodelled=unmodelled,
        home_deg=home_deg,
    )
