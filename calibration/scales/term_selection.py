"""Which candidate terms the relation keeps (method §2, step 5: forward F-tests, then a
backward check) and the relation in degrees with what each term left out would have
changed (step 6)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from calibration.scales.joint_scale_result import HomeZero, TermTest
from calibration.scales.relation_fit import NoJointFit, RelationFits
from calibration.scales.scale_relation import GratingScale, RelationBasis, UnmodelledTerm
from calibration.scales.sweep_inputs import ScaleOptions
from calibration.scales.whitened_gls import GlsFit, f_test


def selected_scale(
    joint: int,
    relation: RelationFits,
    usable: Sequence[str],
    opt: ScaleOptions,
    zero: HomeZero,
    home_deg: float | None,
    notes: list[str],
) -> tuple[list[str], list[TermTest], GlsFit, GratingScale]:
    """The terms kept, their tests, the published fit and the scale: fitted to the points,
    or to the stop angles when that fit does not converge (said in ``notes``, in place)."""
    threshold = opt.alpha / max(len(usable), 1)
    for fit_terms in (relation.fit_points, relation.fit_angles):
        try:
            kept, tests = _select_terms(usable, fit_terms, threshold)
            published = fit_terms(kept)
            scale = _grating_scale_of(
                joint, zero, published, kept, tests, relation.basis, fit_terms, home_deg
            )
            break
        except NoJointFit:
            notes.append(
                "the fit of the relation to the tracker points did not converge: relation "
                "fitted to the stop angles (two-step, first order)"
            )
    return kept, tests, published, scale


def _select_terms(
    usable: Sequence[str], fit_terms: Callable[[Sequence[str]], GlsFit], threshold: float
) -> tuple[list[str], list[TermTest]]:
    """Forward selection in :data:`TERMS` order, then a backward check; F-tests at ``threshold``."""
    kept: list[str] = []
    for t in usable:
        if f_test(fit_terms([*kept, t]), fit_terms(kept))[3] <= threshold:
            kept.append(t)
    while kept:  # a later term may make an earlier one redundant
        final = fit_terms(kept)
        p = {t: f_test(final, fit_terms([c for c in kept if c != t]))[3] for t in kept}
        weakest = max(kept, key=lambda t: p[t])
        if p[weakest] <= threshold:
            break
        kept.remove(weakest)
    final = fit_terms(kept)
    tests = []
    for t in usable:
        if t in kept:  # drop-one test against the final model
            f, d1, d2, p_value = f_test(final, fit_terms([c for c in kept if c != t]))
        else:  # add-one test
            f, d1, d2, p_value = f_test(fit_terms([*kept, t]), final)
        tests.append(TermTest(t, t in kept, f, d1, d2, p_value, threshold))
    return kept, tests


def _grating_scale_of(
    joint: int,
    zero: HomeZero,
    fit: GlsFit,
    kept: Sequence[str],
    tests: Sequence[TermTest],
    basis: RelationBasis,
    fit_terms: Callable[[Sequence[str]], GlsFit],
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
