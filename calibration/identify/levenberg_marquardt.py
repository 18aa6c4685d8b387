"""The Levenberg-Marquardt solver the identification runs (the source's: μ ×10 on
failure, ÷10 on success), its settings and its termination statuses."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:  # scipy loads when a fit runs: a command that only reads a model is quick
    from scipy.optimize import OptimizeResult

FloatArray = NDArray[np.float64]


TERMINATION_MESSAGES = {
    -2: "the residuals were not finite at any damping: the iteration ran away",
    -1: "the step could not reduce the error: damping limit reached",
    0: "the maximum number of iterations was reached",
    1: "change of the error norm <= tol_mm",
    2: "the error norm is zero",
}


ProgressCallback = Callable[[int, float, float], None]  # (iteration, error norm mm, damping)


@dataclass(frozen=True)
class LMSettings:
    """Levenberg-Marquardt settings (the source's: μ ×10 on failure, ÷10 on success)."""

    mu0: float = 1e-3
    increase: float = 10.0
    decrease: float = 0.1
    mu_max: float = 1e12
    tol_mm: float = 1e-4  # stop when successive error norms (mm) differ by at most this
    max_iterations: int = 100


#: The settings :func:`~calibration.identify.identification.identify` runs with by default.
DEFAULT_LM_SETTINGS = LMSettings()


# -- the solver ------------------------------------------------------------------------
#: A check of each accepted iterate: (iteration, x, residuals, Jacobian) -> None. It may
#: raise to end the iteration (identify() drops parameters that ran away through it).
IterateWatch = Callable[[int, FloatArray, FloatArray, FloatArray], None]


def levenberg_marquardt(
    fun: Callable[..., FloatArray],
    jac: Callable[..., FloatArray],
    x0: ArrayLike,
    *,
    args: tuple[object, ...] = (),
    x_scale: ArrayLike | None = None,
    settings: LMSettings = LMSettings(),
    progress: ProgressCallback | None = None,
    watch: IterateWatch | None = None,
) -> OptimizeResult:
    """Minimize ``½‖fun(x, *args)‖²`` by the source's Levenberg-Marquardt iteration.

    ``x_scale`` (k,) gives the characteristic size of each variable; the damping acts on
    ``x / x_scale``. ``watch`` sees the start point and every accepted iterate; what it
    raises ends the iteration and propagates. Returns a :class:`scipy.optimize.OptimizeResult`
    with x, cost, fun, jac, grad, optimality, nfev, njev, nit, status, message, success and
    ``mu``. ``success``: converged (status 1 or 2), or status −1 (no step of any damping
    lowers the error) at a finite error norm: the last accepted point has the smallest
    norm seen and no descent step is left at the solver's resolution. Status 0 (iteration
    limit) and −2 (non-finite residuals at every damping) are failures.
    """
    x = np.array(x0, dtype=float)
    scale = np.ones_like(x) if x_scale is None else np.asarray(x_scale, dtype=float)
    f = fun(x, *args)
    j = jac(x, *args)
    nfev, njev = 1, 1
    norm = float(np.linalg.norm(f))
    mu = settings.mu0
    status = 0
    nit = 0
    if watch is not None:
        watch(0, x, f, j)
    if progress is not None:
        progress(0, norm, mu)
    for nit in range(1, settings.max_iterations + 1):
        if norm == 0.0:
            status = 2
            break
        trial = _damped_step(fun, args, x, f, norm, j * scale, scale, mu, settings)
        nfev += trial.nfev
        mu = trial.mu
        if not trial.accepted:
            status = _rejected_status(norm, trial.norm, settings.tol_mm)
            break
        change = norm - trial.norm
        x, f, norm = trial.x, trial.f, trial.norm
        j = jac(x, *args)
        njev += 1
        if watch is not None:
            watch(nit, x, f, j)
        if progress is not None:
            progress(nit, norm, mu)
        if change <= settings.tol_mm:
            status = 1
            break
    return _lm_result(x, f, j, norm, mu, status, nit=nit, nfev=nfev, njev=njev)


@dataclass(frozen=True)
class _Trial:
    """One LM iteration's search over the damping: the trial point it ended on."""

    accepted: bool  # the error norm fell: x, f, norm are the new iterate
    x: FloatArray  # (k,) the accepted point (the current one when not accepted)
    f: FloatArray  # (3m,) its residuals
    norm: float  # error norm of the last trial step (inf: non-finite residuals)
    mu: float  # damping after the search
    nfev: int  # residual evaluations spent


def _damped_step(
    fun: Callable[..., FloatArray],
    args: tuple[object, ...],
    x: FloatArray,
    f: FloatArray,
    norm: float,
    js: FloatArray,
    scale: FloatArray,
    mu: float,
    settings: LMSettings,
) -> _Trial:
    """Raise the damping μ from ``mu`` until a step on the column-scaled Jacobian ``js``
    ``(3m, k)`` lowers the error norm, the step changes it by <= tol_mm (at the minimum),
    or μ passes ``mu_max``."""
    a = js.T @ js
    g = js.T @ f
    norm_new = math.inf
    nfev = 0
    while mu <= settings.mu_max:
        try:
            step = -np.linalg.solve(a + mu * np.eye(len(x)), g) * scale
        except np.linalg.LinAlgError:
            mu *= settings.increase
            continue
        x_new = x + step
        f_new = fun(x_new, *args)
        nfev += 1
        norm_new = float(np.linalg.norm(f_new)) if np.all(np.isfinite(f_new)) else math.inf
        if norm_new < norm:
            return _Trial(True, x_new, f_new, norm_new, max(mu * settings.decrease, 1e-12), nfev)
        if norm_new - norm <= settings.tol_mm:
            break  # at the minimum: a step changes the error norm by <= tol_mm
        mu *= settings.increase
    return _Trial(False, x, f, norm_new, mu, nfev)


def _lm_result(
    x: FloatArray,
    f: FloatArray,
    j: FloatArray,
    norm: float,
    mu: float,
    status: int,
    *,
    nit: int,
    nfev: int,
    njev: int,
) -> OptimizeResult:
    """The solver's end point as scipy reports it (see :func:`levenberg_marquardt`)."""
    grad = j.T @ f
    from scipy.optimize import OptimizeResult

    return OptimizeResult(
        x=x,
        cost=0.5 * norm**2,
        fun=f,
        jac=j,
        grad=grad,
        optimality=float(np.max(np.abs(grad))) if grad.size else 0.0,
        nfev=nfev,
        njev=njev,
        nit=nit,
        mu=mu,
        status=status,
        message=TERMINATION_MESSAGES[status],
        success=status > 0 or (status == -1 and math.isfinite(norm)),
    )


def _rejected_status(norm: float, norm_new: float, tol_mm: float) -> int:
    """Status when no trial step was accepted: 1 at the minimum (the last trial changed
    the norm by <= tol_mm), −2 when its residuals were not finite, else −1."""
    if norm_new - norm <= tol_mm:
        return 1
    return -1 if math.isfinite(norm_new) else -2
