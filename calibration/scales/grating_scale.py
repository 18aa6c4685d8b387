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

This module runs the steps for one joint (:func:`calibrate_joint`) and finds its zero;
each step lives in a module of its own: the inputs (:mod:`~calibration.scales.sweep_inputs`),
the stop angles (:mod:`~calibration.scales.stop_angles`), the relation's fits
(:mod:`~calibration.scales.relation_fit`, over :mod:`~calibration.scales.whitened_gls`), the
term selection (:mod:`~calibration.scales.term_selection`), the published relation
(:mod:`~calibration.scales.scale_relation`) and the result
(:mod:`~calibration.scales.joint_scale_result`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.errors import ScaleError
from calibration.scales.joint_scale_result import HomeZero, JointScaleResult
from calibration.scales.relation_fit import (
    RelationFits,
    WildAngles,
    basis_over,
    first_order_gain,
    relation_crb,
    relation_design,
)
from calibration.scales.relation_to_points import StopPoints
from calibration.scales.scale_relation import (
    COUNTER_MODULUS,
    TERMS,
    check_terms,
    signed_offset_counts,
)
from calibration.scales.stop_angles import StopAngles, stop_angles
from calibration.scales.sweep_inputs import JointSweep, ScaleOptions, TrackerSpec
from calibration.scales.term_selection import selected_scale
from calibration.scales.whitened_gls import Whitener, gls_fit, whitened

#: The joint's inputs and the relation's vocabulary, where ``twin scale`` and ``twin run``
#: import them from (re-exported: those modules are being edited on another branch).
__all__ = [
    "COUNTER_MODULUS",
    "TERMS",
    "JointScaleResult",
    "JointSweep",
    "ScaleOptions",
    "TrackerSpec",
    "calibrate_joint",
    "check_terms",
]

FloatArray = NDArray[np.float64]


IntArray = NDArray[np.int64]


def _commanded_deg(
    pass_name: NDArray[np.str_], step: IntArray, lower: float, upper: float, step_deg: float
) -> FloatArray:
    """Commanded angle of every stop: forward from the positive limit, backward the reverse."""
    n_fwd = math.floor((upper - lower) / step_deg + 1e-9) + 1
    last = upper - step_deg * (n_fwd - 1)
    return np.where(pass_name == "forward", upper - step_deg * step, last + step_deg * step)


def _home_zero(
    home: IntArray,
    reference: float,
    ang: StopAngles,
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
    white = Whitener.build(white_all[0][idx], white_all[1][idx])
    x = np.column_stack([np.ones(idx.size), ang.u_raw[idx]])
    g0 = gls_fit(ang.theta[idx], x, white).beta[1]
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

    Long for the result's many fields; each step is a function (or a :class:`RelationFits`
    method) of its own.
    """
    opt = options or ScaleOptions()
    candidates = check_terms(opt.candidate_terms)
    j = sweep.joint
    home = np.asarray(home_counts if home_counts is not None else [], dtype=np.int64)
    if sweep.n_stops == 0:
        raise ScaleError(f"joint {j}: no sweep stops")
    reference = float(home[0]) if home.size else float(sweep.counts[0])

    ang = stop_angles(sweep, reference, opt)
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
    g0 = first_order_gain(theta, u, whitened(d_all, b_all, inlier), j)
    # each stop's angle about the relation also carries the read noise of its counts
    read_noise_rad = abs(g0) * math.sqrt(opt.read_noise_counts**2 + 1.0 / 12.0)
    d_circle = d_all
    d_all = d_all + read_noise_rad**2
    basis = basis_over(g0, u[inlier])
    usable = [t for t in candidates if t != "hysteresis" or two_passes]
    wild = WildAngles(theta, relation_design(basis, u, s, usable), d_all, b_all, ang.order)
    white, idx = wild.drop(inlier, dropped, opt.outlier_alpha)
    relation = RelationFits(
        basis, u, s, theta, idx, white, StopPoints.of(circle, inlier), read_noise_rad
    )
    kept, tests, published, scale = selected_scale(j, relation, usable, opt, zero, home_deg, notes)
    final = relation.fit_angles(kept)
    x_all = relation.design(kept)
    theta_pub = relation.refined_angles(kept, circle)
    resid = theta_pub - x_all @ published.beta
    var_stop = relation.stop_angle_variance(final, x_all, b_all, d_circle)
    crb, stored = relation_crb(circle, theta[idx], x_all[idx], idx, inlier)
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


def _stop_label(sweep: JointSweep, i: int) -> str:
    row = f", row {sweep.rows[i]}" if sweep.rows is not None else ""
    return f" ({sweep.pass_name[i]} step {sweep.step[i]}{row})"
