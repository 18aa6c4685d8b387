"""The learned residual stage: a Gaussian process of what the traced model leaves.

After the named effects (:mod:`calibration.effects.closed_loop`) the remaining 3-D residual
``tracker − twin`` may still be a smooth function of the joint angles that no candidate
describes. This module models it with a Gaussian process over the joint angles:

* **kernel**: an ARD squared exponential on each joint's point on the unit circle,
  ``k(q, q') = s² exp(−2 Σ_j sin²((q_j − q'_j)/2) / l_j²)`` (a periodic kernel: a joint at
  +179° is next to one at −179°), plus white noise ``σ²``. One kernel is shared by the
  three axes (one Cholesky factor for all three);
* **hyperparameters** ``l_j`` (rad), ``s`` and ``σ`` (mm) by maximum marginal likelihood on
  the identification residuals (analytic gradient, L-BFGS-B); the prior mean is zero
  (the traced model's least-squares residual has none);
* **prediction** ``(m, 3)`` mean with one predictive standard deviation per pose and axis,
  ``sqrt(var_f + σ² + δ²)``: the spread of a tracker reading about the prediction, ``δ``
  the extra standard deviation the validation poses show (:func:`validation_extra_sd`:
  the identification residuals the hyperparameters see are in-sample residuals of the
  traced model's fit, smaller than its errors on other poses). The mean
  uses every training point; the latent variance ``var_f`` uses a Nyström projection on
  pivots chosen by a pivoted Cholesky (error in ``k(x, x)`` below :data:`PIVOT_TOL` · σ² at
  the training points, at most :data:`MAX_PIVOTS`), so 10 000 poses cost one ``(m, N)``
  kernel and ``(m, r)`` algebra;
* **reach**: a pose whose nearest training pose lies beyond :data:`REACH` in the kernel's
  metric (``d² = 4 Σ sin²(Δq_j/2)/l_j²``) is outside the data's reach: no correction, the
  traced model's standard deviation (never below the process's own prior one,
  ``sqrt(s² + σ² + δ²)``, which the sd within the reach approaches), and flagged.

Why numpy rather than scikit-learn's ``GaussianProcessRegressor``: measured by
``python -m benchmarks.bench_learned_residual`` (docs/closed-loop.md), this
implementation's likelihood gradient uses quadratic forms instead of the ``(N, N, p)``
tensor scikit-learn builds, its kernel is periodic per joint with one length per joint,
and its prediction of 10 000 poses with standard deviations takes 0.08 s of CPU (the
0.1 s target; scikit-learn's exact ``return_std`` 0.7 s), its fit 0.45 s (scikit-learn's
32 s); the benchmark and docs/closed-loop.md have the numbers.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field, replace
from weakref import WeakKeyDictionary

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import cho_factor, cho_solve, lapack, solve_triangular
from scipy.optimize import brentq, minimize
from scipy.stats import norm as normal
from threadpoolctl import threadpool_limits

from calibration.model.description import LearnedResidualDescription

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

KERNEL = "periodic_ard_se"
#: Kernel distance beyond which a pose is outside the data's reach (correlation with the
#: nearest training pose below exp(−REACH²/2) = 0.14).
REACH = 2.0
#: The Nyström pivots stop when no training pose's k(x, x) is off by more than this · σ²
#: (the variance matters beside the noise's: 1 % of it moves the sd by 0.5 %).
PIVOT_TOL = 1e-2
#: Most pivots of the variance's Nyström projection.
MAX_PIVOTS = 150
#: Starting length scales (rad) of the likelihood's search: its surface has a smooth
#: (long) and a fine (short) optimum on real arms; both are tried, the better kept.
LENGTH_STARTS = (0.1, 1.0)
#: Fewer poses are predicted without limiting the BLAS threads (its products are then too
#: small to be threaded, and the limit costs time per call: the live twin's one pose).
SMALL = 64
#: Poses predicted at once.
BLOCK = 1000
#: Bounds of the length scales (rad): below the finest pose spacing a campaign has, and
#: beyond which a joint no longer matters.
LENGTH_BOUNDS = (0.05, 100.0)


@dataclass(frozen=True)
class Hyperparameters:
    """Length scales ``(n,)`` rad per joint; signal and noise standard deviations, mm."""

    length_scales: tuple[float, ...]
    signal_sd_mm: float
    noise_sd_mm: float


def circle_features(q_rad: ArrayLike, length_scales: ArrayLike) -> FloatArray:
    """Each joint's (cos, sin) divided by its length scale: ``(m, 2n)``."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    inv = 1.0 / np.asarray(length_scales, dtype=float)
    return np.concatenate([np.cos(q) * inv, np.sin(q) * inv], axis=1)


def _cross_exponent(fa: FloatArray, fb: FloatArray, c: float) -> FloatArray:
    """``−d²/2`` between feature rows: |φ|² is the same c for every pose (cos² + sin² = 1),
    so ``d² = 2c − 2 φ_a·φ_b`` is one matrix product."""
    g = fa @ fb.T
    g -= c
    return g


def kernel_matrix(fa: FloatArray, fb: FloatArray, hyper: Hyperparameters) -> FloatArray:
    """Signal covariance ``(ma, mb)`` mm² between poses given as :func:`circle_features`."""
    c = float(np.sum(1.0 / np.asarray(hyper.length_scales) ** 2))
    k = _cross_exponent(fa, fb, c)
    np.exp(k, out=k)
    k *= hyper.signal_sd_mm**2
    return k


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS on one thread: on a shared 2-core host a multithreaded OpenBLAS made the fit
    50x slower (``python -m benchmarks.bench_learned_residual``)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


# -- marginal likelihood --------------------------------------------------------------------
def _neg_log_likelihood(
    theta: FloatArray, q: FloatArray, y: FloatArray
) -> tuple[float, FloatArray]:
    """Negative log marginal likelihood of ``y`` ``(N, 3)`` (shared kernel, independent
    axes) and its gradient in ``theta = (log l_1..l_n, log s, log σ)``."""
    n = q.shape[1]
    length = np.exp(theta[:n])
    s2, n2 = math.exp(2 * theta[n]), math.exp(2 * theta[n + 1])
    cos, sin = np.cos(q), np.sin(q)
    f = np.concatenate([cos, sin], axis=1) / np.concatenate([length, length])
    kf = np.exp(_cross_exponent(f, f, float(np.sum(1.0 / length**2)))) * s2
    k = kf.copy()
    k[np.diag_indices_from(k)] += n2
    chol, info = lapack.dpotrf(k, lower=1, clean=1)
    if info != 0:
        return 1e25, np.zeros_like(theta)
    alpha = cho_solve((chol, True), y)
    m, d = y.shape
    value = 0.5 * float(np.sum(y * alpha)) + d * float(np.sum(np.log(np.diag(chol))))
    value += 0.5 * m * d * math.log(2 * math.pi)
    kinv, info = lapack.dpotri(chol, lower=1)
    kinv = np.tril(kinv) + np.tril(kinv, -1).T
    w = alpha @ alpha.T - d * kinv  # dL/dK = W/2
    wk = w * kf
    grad = np.empty_like(theta)
    total = float(wk.sum())
    # dK/dlog l_j = Kf ∘ D_j, D_j = (2 − 2 cos Δq_j)/l_j²: quadratic forms of W∘Kf only
    wc, ws = wk @ cos, wk @ sin
    quad = np.sum(cos * wc, axis=0) + np.sum(sin * ws, axis=0)
    grad[:n] = 0.5 * (2.0 / length**2) * (total - quad)
    grad[n] = total
    grad[n + 1] = n2 * float(np.trace(w))
    return value, -grad


def fit_hyperparameters(q_rad: ArrayLike, residual_mm: ArrayLike) -> Hyperparameters:
    """Maximum marginal likelihood hyperparameters for residuals ``(N, 3)`` mm at joint
    angles ``(N, n)`` rad: L-BFGS-B from each of :data:`LENGTH_STARTS` (every joint's
    length the same, half the variance as signal), the best likelihood kept."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    y = np.asarray(residual_mm, dtype=float)
    scale = float(np.sqrt(np.mean(y**2))) or 1.0
    yn = y / scale  # unit scale: the bounds and start need no units
    n = q.shape[1]
    lo, hi = (math.log(b) for b in LENGTH_BOUNDS)
    bounds = [(lo, hi)] * n + [(math.log(1e-3), math.log(10.0)), (math.log(1e-3), math.log(2.0))]
    best = None
    for start in LENGTH_STARTS:
        theta0 = np.concatenate([np.full(n, math.log(start)), [math.log(math.sqrt(0.5))] * 2])
        res = minimize(
            _neg_log_likelihood,
            theta0,
            args=(q, yn),
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            options={"maxiter": 200},
        )
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    theta = best.x
    return Hyperparameters(
        length_scales=tuple(float(v) for v in np.exp(theta[:n])),
        signal_sd_mm=float(math.exp(theta[n]) * scale),
        noise_sd_mm=float(math.exp(theta[n + 1]) * scale),
    )


# -- the fitted model -----------------------------------------------------------------------
@dataclass(frozen=True)
class ResidualPrediction:
    """The learned correction ``mean_mm`` ``(m, 3)`` (zero outside the reach), the
    predictive standard deviation ``sd_mm`` ``(m,)`` per axis of a tracker reading about the
    corrected point, and ``within_reach`` ``(m,)``."""

    mean_mm: FloatArray
    sd_mm: FloatArray
    within_reach: BoolArray


@dataclass(frozen=True, eq=False)
class LearnedResidual:
    """A Gaussian process of the residual: training poses ``q_rad`` ``(N, n)``, residuals
    ``residual_mm`` ``(N, 3)`` (``tracker − traced model``), its hyperparameters, the
    traced model's own per-axis standard deviation (used outside the reach), and the extra
    standard deviation ``extra_sd_mm`` (mm) added in quadrature to every prediction's."""

    q_rad: FloatArray
    residual_mm: FloatArray
    hyper: Hyperparameters
    traced_sd_mm: float
    reach: float = REACH
    extra_sd_mm: float = 0.0
    _f: FloatArray = field(init=False, repr=False)
    _chol: FloatArray = field(init=False, repr=False)
    _alpha: FloatArray = field(init=False, repr=False)
    _pivots: NDArray[np.intp] = field(init=False, repr=False)
    _proj: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        """Factor once: the Cholesky of K + σ²I, the weights K⁻¹y and the variance's
        Nyström matrix (``O(N³)``)."""
        with one_blas_thread():
            self._factor()

    def _factor(self) -> None:
        h = self.hyper
        f = circle_features(self.q_rad, h.length_scales)
        kf = kernel_matrix(f, f, h)
        k = kf.copy()
        k[np.diag_indices_from(k)] += h.noise_sd_mm**2
        chol = cho_factor(k, lower=True)
        alpha = cho_solve(chol, self.residual_mm)
        pivots, lp = _pivoted_cholesky(kf, PIVOT_TOL * h.noise_sd_mm**2, MAX_PIVOTS)
        # k*ᵀ K⁻¹ k* with k(x, X) ≈ k(x, P) K_PP⁻¹ K_PX: a quadratic form in k(x, P)
        g = solve_triangular(lp, kf[pivots], lower=True)  # (r, N) = L_P⁻¹ K_PX
        c = g @ cho_solve(chol, g.T)  # (r, r)
        left = solve_triangular(lp, c, lower=True, trans="T")  # L_P⁻ᵀ c
        proj = solve_triangular(lp, left.T, lower=True, trans="T").T  # L_P⁻ᵀ c L_P⁻¹
        object.__setattr__(self, "_f", f)
        object.__setattr__(self, "_chol", chol[0])
        object.__setattr__(self, "_alpha", alpha)
        object.__setattr__(self, "_pivots", pivots)
        object.__setattr__(self, "_proj", 0.5 * (proj + proj.T))

    @property
    def n_points(self) -> int:
        return len(self.q_rad)

    @property
    def prior_sd_mm(self) -> float:
        """The predictive sd far from every training pose, ``sqrt(s² + σ² + δ²)`` (mm)."""
        h = self.hyper
        return math.sqrt(h.signal_sd_mm**2 + h.noise_sd_mm**2 + self.extra_sd_mm**2)

    @property
    def beyond_reach_sd_mm(self) -> float:
        """The sd outside the reach: the traced model's, never below :attr:`prior_sd_mm`
        (else the sd would drop where the process stops)."""
        return max(self.traced_sd_mm, self.prior_sd_mm)

    def predict(self, q_rad: ArrayLike) -> ResidualPrediction:
        """The correction and predictive standard deviation at joint angles ``(m, n)`` rad
        (in blocks of :data:`BLOCK` poses: the ``(block, N)`` kernel stays in cache)."""
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))
        with one_blas_thread() if len(q) > SMALL else nullcontext():
            parts = [self._predict_block(q[i : i + BLOCK]) for i in range(0, len(q), BLOCK)]
        if not parts:
            return ResidualPrediction(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=bool))
        return ResidualPrediction(
            mean_mm=np.concatenate([p.mean_mm for p in parts]),
            sd_mm=np.concatenate([p.sd_mm for p in parts]),
            within_reach=np.concatenate([p.within_reach for p in parts]),
        )

    def _predict_block(self, q_rad: FloatArray) -> ResidualPrediction:
        h = self.hyper
        fx = circle_features(q_rad, h.length_scales)
        c = float(np.sum(1.0 / np.asarray(h.length_scales) ** 2))
        expo = _cross_exponent(fx, self._f, c)  # −d²/2 to every training pose
        nearest_d2 = -2.0 * expo.max(axis=1)
        within = nearest_d2 <= self.reach**2
        np.exp(expo, out=expo)
        expo *= h.signal_sd_mm**2  # now k(x, X)
        mean = expo @ self._alpha
        kp = expo[:, self._pivots]
        explained = np.sum((kp @ self._proj) * kp, axis=1)
        var_f = np.clip(h.signal_sd_mm**2 - explained, 0.0, h.signal_sd_mm**2)
        sd = np.sqrt(var_f + (h.noise_sd_mm**2 + self.extra_sd_mm**2))
        mean[~within] = 0.0
        sd[~within] = self.beyond_reach_sd_mm
        return ResidualPrediction(mean_mm=mean, sd_mm=sd, within_reach=within)

    def exact_latent_variance(self, q_rad: ArrayLike) -> FloatArray:
        """``var_f`` ``(m,)`` mm² without the Nyström projection (``O(m N²)``: for checks)."""
        fx = circle_features(q_rad, self.hyper.length_scales)
        ks = kernel_matrix(fx, self._f, self.hyper)
        v = solve_triangular(self._chol, ks.T, lower=True)
        return np.asarray(self.hyper.signal_sd_mm**2 - np.sum(v * v, axis=0))

    def loo_residuals(self) -> FloatArray:
        """Leave-one-out errors ``(N, 3)`` mm of the training residuals (hyperparameters
        held): ``[K⁻¹y]_i / [K⁻¹]_ii``, exact for a Gaussian process."""
        kinv, _ = lapack.dpotri(self._chol, lower=1)
        return np.asarray(self._alpha / np.diag(kinv)[:, None])

    def loo_operator(self) -> FloatArray:
        """``C`` ``(N, N)``: the leave-one-out errors are ``C y`` (row i of ``K⁻¹`` over
        ``[K⁻¹]_ii``), linear in the training residuals."""
        kinv, _ = lapack.dpotri(self._chol, lower=1)
        kinv = np.tril(kinv) + np.tril(kinv, -1).T
        return np.asarray(kinv / np.diag(kinv)[:, None])


def _pivoted_cholesky(
    k: FloatArray, tol: float, max_rank: int
) -> tuple[NDArray[np.intp], FloatArray]:
    """Greedy pivots of a PSD matrix ``(N, N)`` until no diagonal residual exceeds ``tol``;
    the pivots ``(r,)`` and the lower Cholesky factor ``(r, r)`` of ``k[P][:, P]``."""
    n = len(k)
    diag = np.diag(k).copy()
    g = np.zeros((min(max_rank, n), n))
    pivots: list[int] = []
    for i in range(min(max_rank, n)):
        p = int(np.argmax(diag))
        if diag[p] <= tol:
            break
        row = (k[p] - g[:i, p] @ g[:i]) / math.sqrt(diag[p])
        g[i] = row
        diag -= row**2
        diag[p] = 0.0
        pivots.append(p)
    piv = np.asarray(pivots, dtype=np.intp)
    lp = g[: len(piv)][:, piv].T  # rows of G at the pivots: K_PP = lp lpᵀ
    return piv, np.ascontiguousarray(lp)


def fit_learned_residual(
    q_rad: ArrayLike, residual_mm: ArrayLike, traced_sd_mm: float | None = None, seed: int = 0
) -> LearnedResidual:
    """Hyperparameters by marginal likelihood (on :data:`HYPER_POSES` of the poses drawn
    with ``seed``, beyond that many), then the model factored on every pose."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    y = np.asarray(residual_mm, dtype=float)
    sub = np.random.default_rng(seed).permutation(len(q))[:HYPER_POSES]
    with one_blas_thread():
        hyper = fit_hyperparameters(q[sub], y[sub])
    sd = float(np.sqrt(np.mean(y**2))) if traced_sd_mm is None else traced_sd_mm
    return LearnedResidual(q_rad=q, residual_mm=y, hyper=hyper, traced_sd_mm=sd)


# -- stored with the model ------------------------------------------------------------------
#: Poses the hyperparameters are fitted on (a random subset beyond it: the likelihood's
#: O(N³) per evaluation would exceed the 3 s budget of 1000 poses; the final model uses all).
HYPER_POSES = 400

_MODELS: WeakKeyDictionary[LearnedResidualDescription, LearnedResidual] = WeakKeyDictionary()


def model_of(learned: LearnedResidualDescription, traced_sd_mm: float) -> LearnedResidual:
    """The factored model of a stored stage (factored once per description object and
    traced standard deviation: the live twin predicts one pose at a time)."""
    model = _MODELS.get(learned)
    if model is None or model.traced_sd_mm != traced_sd_mm:
        model = _factored(learned, traced_sd_mm)
        _MODELS[learned] = model
    return model


def _factored(learned: LearnedResidualDescription, traced_sd_mm: float) -> LearnedResidual:
    """The model from exactly the stored numbers (so a file read back predicts the same)."""
    return LearnedResidual(
        q_rad=np.radians(np.array(learned.q_deg, dtype=float)),
        residual_mm=np.array(learned.residual_mm, dtype=float),
        hyper=Hyperparameters(learned.length_scales_rad, learned.signal_sd_mm, learned.noise_sd_mm),
        traced_sd_mm=traced_sd_mm,
        reach=learned.reach,
        extra_sd_mm=learned.extra_sd_mm,
    )


def stored(
    q_rad: ArrayLike,
    residual_mm: ArrayLike,
    hyper: Hyperparameters,
    reach: float = REACH,
    extra_sd_mm: float = 0.0,
) -> LearnedResidualDescription:
    """The stage as a description stores it (angles in degrees, as every file has them)."""
    q = np.degrees(np.atleast_2d(np.asarray(q_rad, dtype=float)))
    r = np.asarray(residual_mm, dtype=float)
    return LearnedResidualDescription(
        kernel=KERNEL,
        length_scales_rad=hyper.length_scales,
        signal_sd_mm=hyper.signal_sd_mm,
        noise_sd_mm=hyper.noise_sd_mm,
        reach=reach,
        q_deg=tuple(tuple(float(v) for v in row) for row in q),
        residual_mm=tuple(tuple(float(v) for v in row) for row in r),
        extra_sd_mm=extra_sd_mm,
    )


def validation_extra_sd(model: LearnedResidual, q_rad: ArrayLike, residual_mm: ArrayLike) -> float:
    """The extra standard deviation ``δ`` (mm) that makes the RMS z-score of the validation
    residuals ``(m, 3)`` (tracker − traced model, at joint angles ``(m, n)`` rad) about the
    model's prediction 1: ``mean_i,axes e²/(v_i + δ²) = 1`` over the poses within the
    reach, ``v_i`` the fitted predictive variance. 0 when they already score at most 1:
    the fitted sd is never shrunk.

    Why: the hyperparameters see in-sample residuals of the traced model's fit (geometry
    and the effects the loop chose among many candidates on the same poses), which are
    smaller than its errors elsewhere; the validation poses are outside that fit. On the
    UR10 with 100 poses the identification residuals' RMS was 0.64–1.01× the validation
    poses' (docs/closed-loop.md). The mean is not touched."""
    pred = model.predict(q_rad)
    e = np.asarray(residual_mm, dtype=float) - pred.mean_mm
    within = pred.within_reach
    e2 = np.mean(e[within] ** 2, axis=1)
    var = pred.sd_mm[within] ** 2 - model.extra_sd_mm**2
    if len(e2) == 0 or float(np.mean(e2 / var)) <= 1.0:
        return 0.0

    def excess(d2: float) -> float:
        return float(np.mean(e2 / (var + d2))) - 1.0

    # decreasing in δ²; at δ² = max e² every term is below 1
    return math.sqrt(brentq(excess, 0.0, float(np.max(e2)), xtol=1e-12 * float(np.max(e2))))


# -- the decision ---------------------------------------------------------------------------
#: One-sided significance of the cross-validated error reduction the stage must reach.
ALPHA = 0.01

CRITERION = (
    "a Gaussian process of the traced model's identification residuals over the joint "
    "angles (periodic ARD kernel, hyperparameters by marginal likelihood) is accepted when "
    "its leave-one-out squared error summed over the poses is lower than the traced "
    f"model's residual with one-sided p < {ALPHA} (the gain's spread that of white "
    "residuals of the same variance and kurtosis: the gain is a quadratic form in them), "
    "and it does not make the validation mean error worse"
)


@dataclass(frozen=True)
class LooGain:
    """The leave-one-out gain ``G = Σ_i |y_i|² − |e_i|²`` (mm², all poses and axes) and its
    mean and standard deviation were the residuals white (:func:`loo_gain`)."""

    gain: float
    null_mean: float
    null_sd: float

    @property
    def p_value(self) -> float:
        """One-sided p of ``G > 0``: the normal tail of ``G`` over the white residuals' sd.
        Centred on 0, not on ``null_mean`` (below 0: white residuals' leave-one-out errors
        are larger than they are), so it tests what the stage claims, a lower error."""
        return float(normal.sf(self.gain / self.null_sd)) if self.null_sd > 0 else 1.0


def loo_gain(loo_op: ArrayLike, residual_mm: ArrayLike) -> LooGain:
    """The leave-one-out gain of residuals ``y`` ``(N, 3)`` mm with errors ``e = C y``
    (``C`` ``(N, N)`` from :meth:`LearnedResidual.loo_operator`), and its moments under
    white residuals: independent, zero mean, the observed variance ``σ²`` and fourth
    moment ``μ₄``, the axes alike.

    Per axis ``G = yᵀ A y`` with ``A = I − CᵀC``: mean ``σ² tr A``, variance
    ``2σ⁴ tr A² + (μ₄ − 3σ⁴) Σ A_ii²``. Not a paired t-test on the per-pose gains: pose i's
    gain holds ``2 y_i·f_i`` with ``f_i`` a weighted sum of the other poses' residuals, so
    each pair (i, j) enters two poses' gains and the t-test's variance is half the true one
    (its t-scores spread by √2 on white residuals: a nominal 1 % rejected about 5 %)."""
    c = np.asarray(loo_op, dtype=float)
    y = np.asarray(residual_mm, dtype=float)
    e = c @ y
    n_axes = y.shape[1]
    sigma2 = float(np.mean(y**2))
    mu4 = float(np.mean(y**4))
    ctc_diag = np.sum(c**2, axis=0)  # diag(CᵀC)
    frob2 = float(np.sum(ctc_diag))  # ‖C‖²_F = tr CᵀC
    tr_a = len(c) - frob2
    tr_a2 = len(c) - 2.0 * frob2 + float(np.sum((c @ c.T) ** 2))  # tr (CᵀC)² = ‖CCᵀ‖²_F
    a_diag = 1.0 - ctc_diag
    var = n_axes * (2 * sigma2**2 * tr_a2 + (mu4 - 3 * sigma2**2) * float(np.sum(a_diag**2)))
    return LooGain(
        gain=float(np.sum(y**2) - np.sum(e**2)),
        null_mean=n_axes * sigma2 * tr_a,
        null_sd=math.sqrt(var) if var > 0 else 0.0,
    )


@dataclass(frozen=True)
class LearnedStage:
    """The learned stage's decision. ``share``: the fraction of the traced model's mean
    squared identification residual the stage explains, cross-validated (leave-one-out);
    ``p_value`` of the leave-one-out gain's test (:class:`LooGain`); validation
    mean AP (mm) before and after (NaN without validation poses); ``description``: the
    stored stage when accepted."""

    accepted: bool
    reason: str
    share: float
    p_value: float
    identify_mean_mm: float
    loo_mean_mm: float
    validate_before_mm: float
    validate_after_mm: float
    hyper: Hyperparameters
    fit_s: float
    description: LearnedResidualDescription | None = field(default=None, repr=False)
    #: δ of :func:`validation_extra_sd` (mm), and the validation poses' RMS z-score with
    #: the fitted sd before it (NaN without validation poses)
    extra_sd_mm: float = 0.0
    validate_z_rms: float = float("nan")


def learned_stage(
    q_identify_rad: ArrayLike,
    residual_identify_mm: ArrayLike,
    q_validate_rad: ArrayLike | None = None,
    residual_validate_mm: ArrayLike | None = None,
    *,
    seed: int = 0,
) -> LearnedStage:
    """Fit the stage on the identification residuals ``(m, 3)`` mm (tracker − traced model)
    and decide whether it stays (see :data:`CRITERION`)."""
    started = time.perf_counter()
    q = np.atleast_2d(np.asarray(q_identify_rad, dtype=float))
    r = np.asarray(residual_identify_mm, dtype=float)
    sub = np.random.default_rng(seed).permutation(len(q))[:HYPER_POSES]
    with one_blas_thread():
        hyper = fit_hyperparameters(q[sub], r[sub])
    desc = stored(q, r, hyper)
    model = _factored(desc, float(np.sqrt(np.mean(r**2))))
    with one_blas_thread():
        loo_op = model.loo_operator()
        p = loo_gain(loo_op, r).p_value
    loo = loo_op @ r
    share = 1.0 - float(np.mean(np.sum(loo**2, axis=1)) / np.mean(np.sum(r**2, axis=1)))
    before = after = z_rms = float("nan")
    extra = 0.0
    if q_validate_rad is not None and residual_validate_mm is not None:
        rv = np.asarray(residual_validate_mm, dtype=float)
        pred = model.predict(q_validate_rad)
        before = float(np.linalg.norm(rv, axis=1).mean())
        after = float(np.linalg.norm(rv - pred.mean_mm, axis=1).mean())
        z_rms = float(np.sqrt(np.mean(((rv - pred.mean_mm) / pred.sd_mm[:, None]) ** 2)))
        extra = validation_extra_sd(model, q_validate_rad, rv)
        desc = replace(desc, extra_sd_mm=extra)
    if p >= ALPHA:
        accepted, reason = False, f"not significant (p = {p:.2g} ≥ {ALPHA})"
    elif after > before:
        accepted = False
        reason = f"undone: validation mean AP {before:.4f} -> {after:.4f} mm"
    else:
        accepted, reason = True, f"significant (p = {p:.2g} < {ALPHA})"
    return LearnedStage(
        accepted=accepted,
        reason=reason,
        share=share,
        p_value=p,
        identify_mean_mm=float(np.linalg.norm(r, axis=1).mean()),
        loo_mean_mm=float(np.linalg.norm(loo, axis=1).mean()),
        validate_before_mm=before,
        validate_after_mm=after,
        hyper=hyper,
        fit_s=time.perf_counter() - started,
        description=desc if accepted else None,
        extra_sd_mm=extra,
        validate_z_rms=z_rms,
    )
