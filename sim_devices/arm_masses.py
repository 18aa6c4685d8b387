"""The emulated arm's own masses: drawn around the nominal description, never copied from it.

A robot description's mass model is a catalogue estimate; the real arm differs from it
(castings, cables, motors, the dress pack) and its payload's centre of mass is not where
the tracker target sits. The emulator therefore draws its own (:func:`draw_arm_masses`)
from a generator of its own, so the twin's description never holds the truth.

Conventions (the same as :mod:`calibration.model.statics`, so the two can be compared): link i
(frame i of the modified D-H chain, after joint i's rotation and its ``d``) carries
``mass_kg[i]`` at ``com_mm[i]`` in frame i; the payload carries ``payload_kg`` at
``payload_com_mm`` in the flange frame (frame n).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.model.description import RobotDescription, load_robot

FloatArray = NDArray[np.float64]

#: The preset whose mass model, scaled by reach, stands in when a description has none.
GENERIC_PRESET = "kr500"


@dataclass(frozen=True)
class MassSpread:
    """How far the real arm's masses lie from the description's (1 σ)."""

    link_mass_rel: float = 0.25  # link mass × (1 + N(0, 0.25))
    link_mass_min_rel: float = 0.4  # ... clipped to at least 0.4 × nominal
    com_rel: float = 0.15  # centre of mass moved by N(0, 0.15·extent + 30 mm) per axis
    com_mm: float = 30.0
    payload_rel: float = 0.1  # payload mass × (1 + N(0, 0.1))
    payload_com_mm: float = 40.0  # payload centre of mass: tool point + N(0, 40 mm) per axis


@dataclass(frozen=True, eq=False)
class ArmMasses:
    """Link masses ``(n,)`` kg, centres of mass ``(n, 3)`` mm in each link's frame, and the
    payload: ``payload_kg`` at ``payload_com_mm`` ``(3,)`` in the flange frame."""

    mass_kg: FloatArray
    com_mm: FloatArray
    payload_kg: float
    payload_com_mm: FloatArray

    @property
    def n_links(self) -> int:
        return int(self.mass_kg.shape[0])

    @property
    def arm_kg(self) -> float:
        """The links' mass without the payload (kg)."""
        return float(self.mass_kg.sum())

    @classmethod
    def of_description(cls, desc: RobotDescription) -> ArmMasses:
        """A description's own mass model (missing entries: the generic one; the payload
        at the tool point). For checks against the twin's mass-model terms only."""
        generic = generic_masses(desc)
        pairs = list(zip(desc.joints, generic.mass_kg, generic.com_mm, strict=True))
        mass = np.array([m if j.mass_kg is None else j.mass_kg for j, m, _ in pairs])
        com = np.array([c if j.com_mm is None else j.com_mm for j, _, c in pairs], dtype=float)
        payload = generic.payload_kg if desc.tool.mass_kg is None else desc.tool.mass_kg
        tool = np.array([desc.tool.x_mm, desc.tool.y_mm, desc.tool.z_mm])
        return cls(mass.astype(float), com, float(payload), tool)

    def document(self) -> dict[str, object]:
        return {
            "mass_kg": self.mass_kg.tolist(),
            "com_mm": self.com_mm.tolist(),
            "payload_kg": self.payload_kg,
            "payload_com_mm": self.payload_com_mm.tolist(),
        }


def reach_mm(desc: RobotDescription) -> float:
    """Shoulder-to-wrist reach ``Σ |a| + |d|`` of joints 2-4 (mm), the arm's size."""
    return float(sum(abs(j.a_mm) + abs(j.d_mm) for j in desc.joints[1:4]))


def generic_masses(desc: RobotDescription) -> ArmMasses:
    """The :data:`GENERIC_PRESET` mass model scaled to ``desc`` by reach: lengths × s,
    masses × s³ (geometric similarity), s = reach / the preset's reach."""
    ref = load_robot(GENERIC_PRESET)
    s = reach_mm(desc) / reach_mm(ref)
    n = desc.n_joints
    mass = np.resize([j.mass_kg or 0.0 for j in ref.joints], n) * s**3
    com = np.resize(np.array([j.com_mm or (0.0, 0.0, 0.0) for j in ref.joints]), (n, 3)) * s
    tool = np.array([desc.tool.x_mm, desc.tool.y_mm, desc.tool.z_mm])
    return ArmMasses(mass, com, float((ref.tool.mass_kg or 0.0) * s**3), tool)


def link_extent_mm(desc: RobotDescription) -> FloatArray:
    """Each link's size ``(n,)`` mm: ``|a| + |d|`` of the D-H row that leads to the next
    frame (link i spans frame i to frame i+1); the last link its own row's."""
    rows = [*desc.joints[1:], desc.joints[-1]]
    return np.array([abs(j.a_mm) + abs(j.d_mm) for j in rows])


def draw_arm_masses(
    nominal: RobotDescription,
    tool_point_mm: tuple[float, float, float],
    rng: np.random.Generator,
    spread: MassSpread = MassSpread(),
) -> ArmMasses:
    """The real arm's masses around ``nominal``'s (or the generic model's where it has none).

    ``tool_point_mm`` is the true tracker target in the flange frame; the payload's centre
    of mass is drawn around it. Draw order (fixed, for reproducibility): link mass factors
    ``(n,)``, centre-of-mass offsets ``(n, 3)``, payload factor, payload offset ``(3,)``.
    """
    base = ArmMasses.of_description(nominal)
    n = base.n_links
    factor = np.maximum(1.0 + rng.normal(0.0, spread.link_mass_rel, n), spread.link_mass_min_rel)
    sigma = spread.com_rel * link_extent_mm(nominal) + spread.com_mm
    com = base.com_mm + rng.normal(0.0, 1.0, (n, 3)) * sigma[:, None]
    payload = base.payload_kg * max(
        1.0 + rng.normal(0.0, spread.payload_rel), spread.link_mass_min_rel
    )
    payload_com = np.asarray(tool_point_mm, float) + rng.normal(0.0, spread.payload_com_mm, 3)
    return ArmMasses(base.mass_kg * factor, com, float(payload), payload_com)
