"""Joint 2's counterbalance of a heavy arm: a spring between link 1 and link 2.

Heavy arms carry a spring (KUKA: hydro-pneumatic cylinder) from a point fixed on the
rotating column (link 1) to a point fixed on the upper arm (link 2), so that the joint-2
gear does not hold the whole weight of the arm. Model, in the plane perpendicular to axis
2 (angles about axis 2, from the x axis of frame 2):

* anchor on link 1 at distance ``e`` from the axis, angle ``φ_a`` (frame 2 at θ2 = 0);
* attachment on link 2 at radius ``r``, angle ``φ_b`` in frame 2 (turns with θ2);
* spring length ``l(θ) = sqrt(e² + r² − 2·e·r·cos ψ)``, ``ψ = θ + φ_b − φ_a``,
  θ = q2 + θ-offset2 (the D-H angle);
* force ``k·(l − l_free)`` along the spring (tension pulls the attachment to the anchor),
  moment arm ``e·r·sin ψ / l`` (the axis's distance from the spring's line), torque on link
  2 about axis 2 ``τ = −k·(l − l_free)·e·r·sin ψ / l = −dV/dθ`` with ``V = ½k(l − l_free)²``.

A real free length (``l_free > 0``) makes the torque a distorted first harmonic of θ2, not
the pure sinusoid a zero-free-length spring (or a mass) gives. Units: mm, N/mm, N·mm.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Arms whose links weigh at least this carry a counterbalance on joint 2. Descriptions do
#: not state the rated payload; arms rated 100 kg and more weigh well over 500 kg (KR500
#: and KR210 R3100 presets: 1907 kg, 956 kg), a 20 kg arm about 200 kg (HP20D: 210 kg).
HEAVY_ARM_KG = 500.0
#: Share of joint 2's RMS gravity torque the spring is sized to take (residual 30 %).
DEFAULT_SHARE = 0.7


@dataclass(frozen=True)
class Counterbalance:
    """A spring counterbalance on ``joint`` (1-based, 2 on the presets)."""

    anchor_radius_mm: float  # e
    anchor_angle_deg: float  # φ_a, fixed to link 1
    attachment_radius_mm: float  # r
    attachment_angle_deg: float  # φ_b, fixed to link 2
    stiffness_n_per_mm: float  # k
    free_length_mm: float  # l_free
    joint: int = 2

    def spring_angle_rad(self, theta_rad: ArrayLike) -> FloatArray:
        """ψ = θ + φ_b − φ_a: the angle at the axis between attachment and anchor."""
        d = math.radians(self.attachment_angle_deg - self.anchor_angle_deg)
        return np.asarray(theta_rad, dtype=float) + d

    def length_mm(self, theta_rad: ArrayLike) -> FloatArray:
        e, r = self.anchor_radius_mm, self.attachment_radius_mm
        psi = self.spring_angle_rad(theta_rad)
        return np.sqrt(e * e + r * r - 2.0 * e * r * np.cos(psi))

    def force_n(self, theta_rad: ArrayLike) -> FloatArray:
        """Spring tension (N, > 0 pulls) at D-H angles ``theta_rad``."""
        return self.stiffness_n_per_mm * (self.length_mm(theta_rad) - self.free_length_mm)

    def moment_arm_mm(self, theta_rad: ArrayLike) -> FloatArray:
        """Signed distance of axis 2 from the spring's line (mm): ``e·r·sin ψ / l``."""
        e, r = self.anchor_radius_mm, self.attachment_radius_mm
        return e * r * np.sin(self.spring_angle_rad(theta_rad)) / self.length_mm(theta_rad)

    def torque_nmm(self, theta_rad: ArrayLike) -> FloatArray:
        """Torque (N·mm) the spring exerts on link 2 about axis 2, positive sense of θ."""
        return -self.force_n(theta_rad) * self.moment_arm_mm(theta_rad)

    def potential_nmm(self, theta_rad: ArrayLike) -> FloatArray:
        """Elastic energy ``½k(l − l_free)²`` (N·mm)."""
        stretch = self.length_mm(theta_rad) - self.free_length_mm
        return 0.5 * self.stiffness_n_per_mm * stretch**2

    def document(self) -> dict[str, float | int]:
        return asdict(self)


def size_counterbalance(
    theta_rad: ArrayLike,
    weight_torque_nmm: ArrayLike,
    link_length_mm: float,
    *,
    share: float = DEFAULT_SHARE,
    joint: int = 2,
) -> tuple[Counterbalance, float]:
    """A spring oriented and sized to cancel ``share`` of the RMS gravity torque.

    ``theta_rad`` ``(N,)`` are joint 2's D-H angles and ``weight_torque_nmm`` ``(N,)`` the
    weights' torque on joint 2 at poses spread over the joint ranges. Geometry from the
    upper arm's length L (``link_length_mm``): attachment radius r = 0.2·L behind the axis
    (φ_b = 180°), anchor e = 2.5·r, free length 0.5·(e − r) (the spring stays in tension,
    l ≥ e − r). The anchor's angle puts the spring's zero where the torque's first
    harmonic in θ2 (least squares over the poses) has its zero, opposing it; the stiffness
    makes the RMS of the sum ``(1 − share)`` of the weights' RMS, or the least-squares
    optimum when that is out of reach (the other joints' part cannot be cancelled by a
    function of θ2). Returns the spring and the share actually cancelled.
    """
    theta = np.asarray(theta_rad, dtype=float)
    tau = np.asarray(weight_torque_nmm, dtype=float)
    r = 0.2 * link_length_mm
    e = 2.5 * r
    basis = np.column_stack([np.sin(theta), np.cos(theta)])
    (a, b), *_ = np.linalg.lstsq(basis, tau, rcond=None)
    phase_deg = math.degrees(math.atan2(b, a))  # tau ≈ C·sin(θ + phase), C > 0
    unit = Counterbalance(e, 180.0 - phase_deg, r, 180.0, 1.0, 0.5 * (e - r), joint)
    f = unit.torque_nmm(theta)
    g2, ff, tf = np.mean(tau**2), np.mean(f**2), np.mean(tau * f)
    # RMS(tau + k f)² = g2 + 2k·tf + k²·ff = (1 − share)²·g2: the smaller root
    disc = tf * tf - ff * g2 * (1.0 - (1.0 - share) ** 2)
    k = (-tf - math.sqrt(disc)) / ff if disc >= 0 else -tf / ff
    spring = replace(unit, stiffness_n_per_mm=float(k))
    achieved = 1.0 - math.sqrt(np.mean((tau + spring.torque_nmm(theta)) ** 2) / g2)
    return spring, float(achieved)
