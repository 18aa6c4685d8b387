"""The loop's gravity deflection at the sweep stops, with its statistics: what the joint fit
takes out of the sweeps before refitting the scale maps (:mod:`calibration.twin.fit_rounds`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from calibration.identify.campaign_files import Campaign
from calibration.model.description import RobotDescription
from calibration.scales.chain_scale import ScaleCampaignResult
from calibration.scales.grating_scale import JointSweep
from calibration.twin.campaign_measurement import CampaignMeasurements
from calibration.twin.sweep_configuration import stop_angles_rad, sweep_configurations

if TYPE_CHECKING:
    from calibration.effects.closed_loop import ClosedLoopResult
    from calibration.effects.effect_base import EffectSpec
    from calibration.effects.effect_gravity import GravityDeflection
    from calibration.identify.identification import IdentificationResult
    from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]


def sweep_deflections(
    meas: CampaignMeasurements,
    scales: ScaleCampaignResult,
    campaign: Campaign,
    loop: ClosedLoopResult | None,
) -> tuple[dict[int, FloatArray], FloatArray] | None:
    """A round's gravity deflection of every link ``(S, n)`` rad at each joint's sweep
    stops, and per joint its variance summed over all sweeps' stops ``(n,)`` (None when
    the round's loop found no gravity deflection). ``scales``, ``campaign``, ``loop``: the
    round's (:class:`~calibration.twin.fit_rounds.TwinRound`) maps, the poses read through
    them and its closed loop.

    Only what the poses can tell from the maps goes back into them: a moment whose effect
    on joint j depends on q_j alone (it vanishes relative to j's sweep configuration, e.g.
    link 2's own moment about joint 2 when joint 1 is vertical) is left in j's map, and
    each joint's deflection is shrunk by its signal-to-noise ratio over the sweeps, by the
    factor ``max(0, 1 − 1/SNR²)`` (positive-part James-Stein): a deflection within its own
    standard error (a rigid joint's estimate is noise) is not taken out, a well determined
    one nearly all of it, and nothing switches on and off between rounds.
    """
    term = None if loop is None else gravity_term(loop)
    if loop is None or term is None:
        return None
    robot = meas.robot
    reference = sweep_configurations(robot, meas.sweeps, scales)
    acting = acting_moments(robot, campaign, term, reference)
    sweeps = {
        j: sweep_deflection(robot, scales, sweep, term, acting) for j, sweep in meas.sweeps.items()
    }
    n = meas.n_joints
    ratio_var = compliance_ratio_variance(term.spec, loop, n)
    signal = np.zeros(n)
    noise = np.zeros(n)
    for value, var in sweeps.values():
        signal += np.sum(value**2, axis=0)
        noise += np.sum(var, axis=0) + np.sum(value**2, axis=0) * ratio_var
    # positive-part shrinkage by the joint's signal-to-noise ratio over the sweeps
    shrink = np.clip(1.0 - noise / np.maximum(signal, 1e-300), 0.0, 1.0)
    return {j: value * shrink[None, :] for j, (value, _) in sweeps.items()}, noise


@dataclass(frozen=True, eq=False)
class GravityTerm:
    """A loop's fitted gravity deflection: its spec, values ``(k,)`` and their covariance
    ``(k, k)``, the kind that evaluates it and the loop's final model."""

    spec: EffectSpec
    values: FloatArray
    covariance: FloatArray
    kind: GravityDeflection
    model: KinematicModel


def gravity_term(loop: ClosedLoopResult) -> GravityTerm | None:
    """The loop's gravity deflection term (None: it found none)."""
    from calibration.effects.effect_gravity import GravityDeflection
    from calibration.effects.effect_kinds import KINDS, split_values

    final = loop.final
    gravity = [s for s in final.specs if s.kind == "gravity_deflection"]
    if not gravity:
        return None
    spec = gravity[0]
    index = list(final.specs).index(spec)
    assert final.result is not None  # a loop's final stage has its fit
    values = split_values(final.specs, final.result.effect_values)[index]
    cov = _effect_covariance(final.result, index, final.specs)
    kind = KINDS["gravity_deflection"]
    assert isinstance(kind, GravityDeflection)
    return GravityTerm(spec, values, cov, kind, final.model)


def acting_moments(
    robot: RobotDescription, campaign: Campaign, term: GravityTerm, reference: FloatArray
) -> NDArray[np.bool_]:
    """Which moments' share of each joint ``(n, P)`` the identification poses see apart
    from that joint's own angle (relative to its sweep configuration, ``reference``
    ``(n, n)`` rad): what the maps cannot hold."""
    from calibration.effects.effect_base import EffectContext, EffectData, ModelAtPoses

    q_poses = campaign.q_rad[campaign.mask("identify")]
    ref_ctx = EffectContext(robot, EffectData(q_poses, sweep_reference=reference))
    d_ref = term.kind.deflection_jacobian(term.spec, ref_ctx, ModelAtPoses.of(term.model, q_poses))
    rms = np.sqrt(np.mean(d_ref**2, axis=0))  # (n, P): what the poses see apart from maps
    acting: NDArray[np.bool_] = rms > 1e-9 * max(float(rms.max(initial=0.0)), 1e-300)
    return acting


def sweep_deflection(
    robot: RobotDescription,
    scales: ScaleCampaignResult,
    sweep: JointSweep,
    term: GravityTerm,
    acting: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray]:
    """The term's deflection of every link ``(S, n)`` rad at one sweep's stops (the stops
    read through ``scales``, the ``acting`` moments only) and its variance ``(S, n)``."""
    from calibration.effects.effect_base import EffectContext, EffectData, ModelAtPoses

    q = stop_angles_rad(robot, scales, sweep)
    ctx = EffectContext(robot, EffectData(q))
    kin = ModelAtPoses.of(term.model, q)
    unit = np.eye(len(term.values))
    jac = np.stack(
        [term.kind.joint_deflections_rad(term.spec, u, ctx, kin, acting) for u in unit], axis=2
    )
    value: FloatArray = jac @ term.values
    variance: FloatArray = np.einsum("sjk,kl,sjl->sj", jac, term.covariance, jac)
    return value, variance


def compliance_ratio_variance(spec: EffectSpec, loop: ClosedLoopResult, n: int) -> FloatArray:
    """Per joint ``(n,)``, the relative variance of its compliance ratio: the physical
    form's ratios are held fixed in the fit, and their own uncertainty (from the loop's
    profile of them) adds ``(d_j / ρ_j)²·var(ρ_j)`` to a deflection's variance."""
    ratio_var = np.zeros(n)
    if spec.parameter == "physical":
        form = next(  # the last record: a later step may have refitted the ratios
            (
                st.shape["gravity_form"]
                for st in reversed(loop.stages)
                if "gravity_form" in st.shape
            ),
            None,
        )
        if form is not None:
            for j, r, se in zip(
                form["joints"], form["compliance_ratio"], form["compliance_ratio_se"], strict=True
            ):
                ratio_var[j - 1] = (se / r) ** 2 if r != 0 else np.inf
    return ratio_var


def _effect_covariance(
    result: IdentificationResult, index: int, specs: Sequence[EffectSpec]
) -> FloatArray:
    """Covariance ``(k, k)`` of one effect's parameters (zero rows for held ones)."""
    sizes = [len(s.parameter_names()) for s in specs]
    start = result.n_geometric + sum(sizes[:index])
    k = sizes[index]
    full = np.zeros((len(result.free), len(result.free)))
    idx = np.flatnonzero(result.free)
    full[np.ix_(idx, idx)] = result.covariance
    return full[start : start + k, start : start + k]
