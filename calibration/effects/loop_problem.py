"""The closed loop's settings and its problem: the identification poses, how they are
weighted, the validation sets, and the model's linearisation at a fit
(:mod:`calibration.effects.closed_loop` runs the search on it)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.candidate_scoring import LinearizedModel
from calibration.effects.effect_base import EffectContext, EffectData, EffectSpec, ModelAtPoses
from calibration.effects.effect_coupling import coupling_moment_columns
from calibration.effects.effect_kinds import (
    KINDS,
    effect_terms,
    predict_points,
    regressor_matrix,
)
from calibration.effects.loop_settings import LoopSettings as LoopSettings
from calibration.errors import IdentificationError
from calibration.identify.campaign_files import Campaign
from calibration.identify.identification import IdentificationResult, identify
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel

FloatArray = NDArray[np.float64]


def campaign_effect_data(
    description: RobotDescription,
    campaign: Campaign,
    *,
    sweep_referenced: bool = False,
    sweep_configurations: ArrayLike | None = None,
) -> EffectData:
    """Effect data of a whole campaign: directions from its pose sequence (from Home),
    the temperatures of its ``temp_c`` column when it has one.

    ``sweep_referenced``: the joint readings come from scale maps fitted on sweeps, which
    absorbed each swept link's deflection in its sweep configuration: the other joints at
    Home, or per joint ``sweep_configurations`` ``(n, n)`` rad when given (row j: joint
    j+1's sweep configuration, :attr:`EffectData.sweep_reference`).
    """
    home = np.radians(description.home)
    data = EffectData.from_sequence(campaign.q_rad, campaign.t_s, home, temp_c=campaign.temp_c)
    if not sweep_referenced:
        return data
    if sweep_configurations is None:
        return replace(data, sweep_reference=home)
    n = description.n_joints
    configs = np.array(sweep_configurations, dtype=float)
    if configs.shape != (n, n):
        raise ValueError(f"sweep_configurations: shape {configs.shape}, expected {(n, n)}")
    return replace(data, sweep_reference=configs)


@dataclass(frozen=True, eq=False)
class LoopProblem:
    """The identification poses and how they are weighted; the validation sets."""

    nominal: KinematicModel
    ctx: EffectContext  # identification poses
    meas: FloatArray  # (m, 3)
    prior: FloatArray  # (m,) relative weights of the points
    contexts: dict[str, EffectContext]
    points: dict[str, FloatArray]
    identify_kwargs: dict[str, Any]

    @property
    def m(self) -> int:
        return len(self.meas)

    def started_at(self, model: KinematicModel) -> LoopProblem:
        """The same problem, its identifications started from ``model`` (a stage's solved
        geometry) instead of the nominal one."""
        return replace(self, nominal=model)

    @classmethod
    def of_campaign(
        cls,
        description: RobotDescription,
        campaign: Campaign,
        identify_kwargs: dict[str, Any],
        point_sigma_mm: ArrayLike | None,
        *,
        sweep_referenced: bool,
        sweep_configurations: ArrayLike | None,
    ) -> LoopProblem:
        """The campaign's identification poses (weighted by ``point_sigma_mm`` ``(m,)`` as
        :func:`~calibration.identify.identification.identify` does) and its validation poses."""
        nominal = KinematicModel.from_description(description)
        data = campaign_effect_data(
            description, campaign, sweep_referenced=sweep_referenced,
            sweep_configurations=sweep_configurations,
        )  # fmt: skip
        masks = {s: campaign.mask(s) for s in ("identify", "validate")}
        masks = {s: m for s, m in masks.items() if m.any()}
        if "identify" not in masks:
            raise IdentificationError("the campaign has no identification poses")
        contexts = {s: EffectContext(description, data.subset(m)) for s, m in masks.items()}
        points = {s: campaign.xyz_mm[m] for s, m in masks.items()}
        ctx_id = contexts["identify"]
        m = len(ctx_id.data)
        prior = np.ones(m)
        if point_sigma_mm is not None:
            ps = np.broadcast_to(np.asarray(point_sigma_mm, dtype=float), (m,))
            prior = (1.0 / np.sqrt(np.mean(1.0 / ps**2)) / ps) ** 2
        return cls(nominal, ctx_id, points["identify"], prior, contexts, points, identify_kwargs)

    def identify(
        self, specs: tuple[EffectSpec, ...], start: FloatArray | None
    ) -> IdentificationResult:
        terms = effect_terms(specs, self.ctx, start=start) if specs else None
        q = self.ctx.data.q_rad
        return identify(self.nominal, q, self.meas, effects=terms, **self.identify_kwargs)

    def errors(
        self, model: KinematicModel, specs: tuple[EffectSpec, ...], values: FloatArray
    ) -> dict[str, FloatArray]:
        return {
            s: self.points[s] - predict_points(model, specs, values, self.contexts[s])
            for s in self.contexts
        }

    def linearized(
        self, result: IdentificationResult, specs: tuple[EffectSpec, ...], settings: LoopSettings
    ) -> tuple[LinearizedModel, FloatArray, ModelAtPoses]:
        """The model at its solution, weighted like the fit; the weights ``(m,)``."""
        model, values = result.model, result.effect_values
        kin = ModelAtPoses.of(model, self.ctx.data.q_rad)
        sw = np.sqrt(self.prior * result.pose_weights)
        pred = predict_points(model, specs, values, self.ctx)
        residual = ((pred - self.meas) * sw[:, None]).ravel()
        effects = regressor_matrix(specs, self.ctx, slice(0, self.m), kin)
        jac = np.concatenate([kin.jacobian, effects], axis=2)[:, :, result.free]
        jac = jac * sw[:, None, None]
        lin = LinearizedModel.build(
            residual,
            jac.reshape(-1, jac.shape[-1]),
            self.m,
            settings.folds,
            settings.fold_seed,
            leave_one_out=settings.leave_one_out,
            deviance=settings.loo_deviance,
        )
        return lin, sw, kin

    def columns(self, spec: EffectSpec, sw: FloatArray, kin: ModelAtPoses) -> FloatArray:
        """A candidate's weighted regressor ``(3m, k)``."""
        sel = slice(0, self.m)
        r = KINDS[spec.kind].regressor(spec, self.ctx, sel, kin) * sw[:, None, None]
        return r.reshape(3 * self.m, -1)

    def coupling_columns(
        self, sw: FloatArray, kin: ModelAtPoses
    ) -> Callable[[tuple[str, ...]], FloatArray]:
        """The shoulder pair's coupling ``(3m, b)`` per unit of each of the base moments
        named (:func:`coupling_moment_columns`), weighted as :meth:`columns`."""
        return partial(coupling_moment_columns, columns_of=partial(self.columns, sw=sw, kin=kin))


def validation_set_name(contexts: dict[str, EffectContext]) -> str:
    return "validate" if "validate" in contexts else "identify"
