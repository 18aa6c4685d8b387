"""Joint stiffness: the TCP's deflection under a process force, and a load test to find it.

A joint of torsional stiffness ``K_j`` (N·mm/rad) after its grating ring turns by
``τ_j / K_j`` under the torque ``τ = Jᵀ·w`` a wrench ``w`` at the TCP exerts on it; the
TCP moves by ``J·K⁻¹·Jᵀ·w``: the Cartesian compliance ``C = J K⁻¹ Jᵀ`` (method.md §4),
``J`` the geometric Jacobian of the calibrated geometry at the TCP in the tracker frame
(rows mm/rad then rad/rad). The gratings read the ring, so a deflection after it is not
seen by them: the TCP is off by ``C·w`` at the joints the gratings report.

Stiffnesses come from the description (``[[joint]] stiffness_nmm_per_rad``: stated, or
written by :func:`fit_joint_compliance` from a load test). The closed loop's gravity term
gives compliances only up to a common scale (the moments it multiplies are unknown
without masses: docs/closed-loop.md), so a force needs them stated or measured.

Load test: at each pose, the TCP measured unloaded and under a known force ``F`` (N, tool
point, tracker frame); the deflection ``d = Σ_j c_j·J_j·(J_jᵀ·F)`` is linear in the joint
compliances ``c_j = 1/K_j``, fitted by bounded linear least squares (``c ≥ 0``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import lsq_linear

from calibration.errors import StiffnessError
from calibration.model.description import RobotDescription
from calibration.model.kinematics import KinematicModel, geometric_jacobian

FloatArray = NDArray[np.float64]

#: A joint whose load-test column is below this share of the largest is not excited by
#: the test (no torque on it: a force through its axis) and is left out of the fit.
EXCITATION_FLOOR = 1e-9
#: A fitted compliance is taken as determined by the test when its standard error is
#: below this share of its value (a joint the forces hardly load stays as stated).
DETERMINED_REL_ERROR = 0.5
#: A singular value of the load test's column-scaled design matrix below this share of
#: the largest is a direction of compliances the test does not see.
RANK_TOLERANCE = 1e-6
#: Deflections whose mean component along their forces is below minus this many standard
#: errors point against the forces (physically impossible).
SIGN_SIGMAS = 3.0


def joint_compliance(description: RobotDescription) -> FloatArray:
    """Compliances ``(n,)`` rad/(N·mm) from the description's stated stiffnesses (0 where
    none is stated: rigid)."""
    k = np.array([j.stiffness_nmm_per_rad or np.inf for j in description.joints], dtype=float)
    return 1.0 / k


def states_stiffness(description: RobotDescription) -> bool:
    """Whether any joint of the description states a stiffness."""
    return any(j.stiffness_nmm_per_rad is not None for j in description.joints)


def cartesian_compliance(description: RobotDescription, q_rad: ArrayLike) -> FloatArray:
    """``C = J K⁻¹ Jᵀ`` ``(m, 6, 6)`` at joints ``(m, n)`` rad: a wrench (N, N·mm) at the
    TCP in the tracker frame to the TCP's twist (mm, rad). ``C[:, :3, :3]`` is mm/N."""
    model = KinematicModel.from_description(description)
    jac = geometric_jacobian(model, np.atleast_2d(q_rad), point="tcp", frame="world")
    c = joint_compliance(description)
    return (jac * c) @ np.swapaxes(jac, 1, 2)


def force_deflection_mm(
    description: RobotDescription, q_rad: ArrayLike, force_n: ArrayLike
) -> FloatArray:
    """The TCP's deflection ``(m, 3)`` mm under forces ``(m, 3)`` N at the TCP (tracker
    frame) at joints ``(m, n)`` rad: ``C[:3, :3]·F``."""
    c = cartesian_compliance(description, q_rad)[:, :3, :3]
    f = np.asarray(force_n, dtype=float).reshape(len(c), 3)
    deflection: FloatArray = np.einsum("mij,mj->mi", c, f)
    return deflection


@dataclass(frozen=True)
class ComplianceFit:
    """A load test's result: per joint ``(n,)`` the compliance (rad/(N·mm); 0: rigid or
    not excited), its standard error, whether the test loaded the joint (``excited``) and
    whether it determined the compliance (``determined``: standard error below
    :data:`DETERMINED_REL_ERROR` of the value); the rms of the deflection residuals (mm)
    and the number of loaded measurements."""

    compliance: FloatArray
    std_error: FloatArray
    excited: NDArray[np.bool_]
    rms_residual_mm: float
    n_loads: int

    @property
    def determined(self) -> NDArray[np.bool_]:
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = self.std_error / self.compliance
        return self.excited & (self.compliance > 0) & (rel < DETERMINED_REL_ERROR)

    @property
    def stiffness_nmm_per_rad(self) -> FloatArray:
        """``1 / compliance`` ``(n,)`` (inf where the compliance is 0)."""
        with np.errstate(divide="ignore"):
            return 1.0 / self.compliance

    def applied_to(self, description: RobotDescription) -> RobotDescription:
        """``description`` with the stiffness of every joint the test determined (the
        others keep what they stated)."""
        k, determined = self.stiffness_nmm_per_rad, self.determined
        joints = tuple(
            replace(j, stiffness_nmm_per_rad=float(k[i])) if determined[i] else j
            for i, j in enumerate(description.joints)
        )
        return replace(description, joints=joints)


def fit_joint_compliance(
    description: RobotDescription,
    q_rad: ArrayLike,
    force_n: ArrayLike,
    deflection_mm: ArrayLike,
) -> ComplianceFit:
    """Joint compliances from a load test: poses ``(m, n)`` rad, forces ``(m, 3)`` N and
    the measured deflections (loaded − unloaded TCP) ``(m, 3)`` mm, tracker frame."""
    model = KinematicModel.from_description(description)
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    m, n = q.shape
    f = np.asarray(force_n, dtype=float).reshape(m, 3)
    d = np.asarray(deflection_mm, dtype=float).reshape(m, 3)
    jp = geometric_jacobian(model, q, point="tcp", frame="world")[:, :3, :]  # (m, 3, n)
    torque = np.einsum("min,mi->mn", jp, f)  # τ_j = J_jᵀ F, N·mm
    a = (jp * torque[:, None, :]).reshape(3 * m, n)  # column j: J_j τ_j, mm per (rad/N·mm)
    norms = np.linalg.norm(a, axis=0)
    excited = norms > EXCITATION_FLOOR * max(float(norms.max()), 1e-300)
    if m < 2 or not excited.any():
        raise StiffnessError("the load test excites no joint (forces zero or too few loads)")
    _check_deflection_signs(f, d)
    scale = norms[excited]
    _check_rank(a[:, excited] / scale, np.flatnonzero(excited), q, f)
    sol = lsq_linear(a[:, excited] / scale, d.ravel(), bounds=(0.0, np.inf), method="bvls")
    c = np.zeros(n)
    c[excited] = sol.x / scale
    residual = d.ravel() - a @ c
    dof = max(3 * m - int(excited.sum()), 1)
    sigma2 = float(residual @ residual) / dof
    se = np.full(n, np.nan)
    an = a[:, excited] / scale
    cov = np.linalg.pinv(an.T @ an) * sigma2
    se[excited] = np.sqrt(np.clip(np.diag(cov), 0.0, None)) / scale
    return ComplianceFit(c, se, excited, float(np.sqrt(np.mean(residual**2))), m)


def _check_deflection_signs(force_n: FloatArray, deflection_mm: FloatArray) -> None:
    """Refuse deflections ``(m, 3)`` mm that point against their forces ``(m, 3)`` N on the
    whole: ``F·C·F ≥ 0`` for every compliance ``C = J K⁻¹ Jᵀ``, so their mean component
    along the force cannot be negative beyond its noise (more than
    :data:`SIGN_SIGMAS` standard errors: loaded and unloaded points swapped, a force's
    sign flipped; a stiff robot's deflections lost in the tracker's noise are not)."""
    magnitude = np.linalg.norm(force_n, axis=1)
    loaded = magnitude > 0
    along = np.einsum("mi,mi->m", deflection_mm[loaded], force_n[loaded]) / magnitude[loaded]
    if along.size < 2:
        return
    mean = float(along.mean())
    if mean < -SIGN_SIGMAS * float(along.std(ddof=1)) / np.sqrt(along.size):
        against = int(np.sum(along < 0))
        raise StiffnessError(
            f"the deflections (loaded - unloaded) point against their forces in {against} of "
            f"{along.size} loads (mean {1e3 * mean:.1f} µm along the force); "
            "a joint compliance cannot do that: are the loaded and unloaded points swapped, "
            "or the force's sign?"
        )


def _check_rank(
    design: FloatArray, joints: NDArray[np.intp], q_rad: FloatArray, force_n: FloatArray
) -> None:
    """Refuse a load test whose design ``(3m, k)`` (columns scaled to unit length, the
    ``k`` loaded ``joints``) does not determine every loaded joint's compliance, or leaves
    no redundant equation to judge them (the fit would report ± 0 %)."""
    k = design.shape[1]
    sv = np.linalg.svd(design, compute_uv=False)
    rank = int(np.sum(sv > RANK_TOLERANCE * sv[0]))
    poses = len(np.unique(np.round(q_rad, 9), axis=0))
    unit = force_n / np.maximum(np.linalg.norm(force_n, axis=1, keepdims=True), 1e-300)
    directions = len(np.unique(np.round(np.abs(unit), 6), axis=0))
    given = (
        f"{len(q_rad)} loads at {poses} distinct pose(s) along {directions} distinct "
        f"axis/axes give {design.shape[0]} equations"
    )
    if rank < k:
        _, _, vt = np.linalg.svd(design)
        null = vt[rank:]
        unseen = [int(joints[i]) + 1 for i in np.flatnonzero(np.linalg.norm(null, axis=0) > 0.1)]
        raise StiffnessError(
            f"the load test cannot determine the stiffnesses: rank {rank} for the {k} "
            f"compliances of the loaded joints ({given}); joint(s) "
            f"{', '.join(map(str, unseen))} cannot be told apart: add loads along other "
            "axes and at other poses"
        )
    if design.shape[0] <= k:
        raise StiffnessError(
            f"the load test leaves no redundant equation: {given} for {k} compliances, so "
            "their uncertainty is unknown: add loads along other axes or at other poses"
        )
