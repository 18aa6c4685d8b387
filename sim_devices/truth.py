"""The emulated cell's physical truth: true geometry, grating strips, laser tracker.

Everything here is seeded and reproducible. The twin (``calibration``) never imports this
module; tests compare the twin's results against it. ``TrueCell.write_truth`` writes the
truth to a TOML file that tests may read and the twin never does.

Units: mm, radians inside the code, degrees in files; counts are grating counter values.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
from numpy.typing import ArrayLike, NDArray

from calibration.model.description import BaseDescription, RobotDescription, ToolDescription
from calibration.model.kinematics import KinematicModel, nearly_parallel_joints, tcp_positions
from sim_devices.arm_masses import ArmMasses, draw_arm_masses
from sim_devices.physical_arm import PhysicalArm

FloatArray = NDArray[np.float64]

COUNTER_MODULUS = 2**32  # the reader's counters are 32-bit and wrap
#: Second seed word of the arm's own masses: a stream of their own, so adding them left
#: every earlier draw (geometry, strips, ...) of a seed as it was.
MASS_STREAM = 0x6D617373


@dataclass(frozen=True)
class GeometryDeviations:
    """Spread (1 σ) of the true geometry around the nominal description."""

    length_mm: float = 0.3  # a and d of each joint
    axis_deg: float = 0.03  # alpha, and beta of nearly parallel joints
    zero_deg: float = 0.02  # theta offsets (joint zero)
    tool_mm: float = 0.5
    base_mm: float = 20.0  # the base guess in the description is this far off
    base_deg: float = 0.5


def true_description(
    nominal: RobotDescription, rng: np.random.Generator, dev: GeometryDeviations
) -> RobotDescription:
    """Draw a true robot around ``nominal``, exactly representable by the twin's model.

    ``beta`` deviates only on nearly parallel joints and ``d`` is kept there, so the truth
    lies inside the identifiable parameter space (no unmodelled geometry by accident).
    """
    model = KinematicModel.from_description(nominal)
    parallel = nearly_parallel_joints(model)
    joints = []
    for i, j in enumerate(nominal.joints):
        joints.append(
            replace(
                j,
                a_mm=j.a_mm + rng.normal(0, dev.length_mm),
                alpha_deg=j.alpha_deg + rng.normal(0, dev.axis_deg),
                d_mm=j.d_mm if parallel[i] else j.d_mm + rng.normal(0, dev.length_mm),
                theta_offset_deg=j.theta_offset_deg + rng.normal(0, dev.zero_deg),
                beta_deg=j.beta_deg + (rng.normal(0, dev.axis_deg) if parallel[i] else 0.0),
            )
        )
    guess = nominal.base or BaseDescription()
    base = BaseDescription(
        **{k: getattr(guess, k) + rng.normal(0, dev.base_mm) for k in ("x_mm", "y_mm", "z_mm")},
        **{
            k: getattr(guess, k) + rng.normal(0, dev.base_deg)
            for k in ("rx_deg", "ry_deg", "rz_deg")
        },
        gravity=guess.gravity,
    )
    t = nominal.tool
    tool = ToolDescription(
        t.x_mm + rng.normal(0, dev.tool_mm),
        t.y_mm + rng.normal(0, dev.tool_mm),
        t.z_mm + rng.normal(0, dev.tool_mm),
        t.mass_kg,
    )
    return replace(
        nominal, name=f"{nominal.name} (truth)", joints=tuple(joints), base=base, tool=tool
    )


@dataclass(frozen=True)
class GratingStrip:
    """A linear grating strip glued around a joint's outer ring, read by a fixed head.

    Counts follow arc length: ``R·(1 + scale_error)·q`` plus a first-harmonic cyclic error
    from mounting eccentricity, at ``counts_per_mm`` (1000 = 1 µm per count), offset by an
    unknown ``zero_counts`` (the counter value at q = 0), with Gaussian read noise, rounded to
    whole counts and wrapped to the 32-bit counter.
    """

    radius_mm: float
    counts_per_mm: float = 1000.0
    scale_error_ppm: float = 0.0
    eccentricity_mm: float = 0.0
    eccentricity_phase_rad: float = 0.0
    zero_counts: int = 0
    noise_counts: float = 0.5
    direction: int = 1

    def arc_mm(self, q_rad: ArrayLike) -> FloatArray:
        """True arc length read by the head relative to q = 0 (mm), no noise."""
        q = np.asarray(q_rad, dtype=float)
        scale = self.radius_mm * (1.0 + 1e-6 * self.scale_error_ppm)
        cyclic = self.eccentricity_mm * (
            np.sin(q + self.eccentricity_phase_rad) - math.sin(self.eccentricity_phase_rad)
        )
        return self.direction * (scale * q + cyclic)

    def ideal_counts(self, q_rad: ArrayLike) -> FloatArray:
        """Unwrapped, noise-free, unquantized counter value at joint angle ``q_rad``."""
        return self.zero_counts + self.arc_mm(q_rad) * self.counts_per_mm

    def read(self, q_rad: ArrayLike, rng: np.random.Generator) -> NDArray[np.int64]:
        """Counter values as the reader latches them: noisy, whole counts, 32-bit wrapped."""
        ideal = self.ideal_counts(q_rad)
        noisy = ideal + rng.normal(0.0, self.noise_counts, np.shape(ideal))
        return np.mod(np.rint(noisy).astype(np.int64), COUNTER_MODULUS)


def default_strip_radii_mm(nominal: RobotDescription) -> list[float]:
    """Ring radii for the strips, scaled from a KR500-class arm by the arm's reach."""
    reach = sum(abs(j.a_mm) + abs(j.d_mm) for j in nominal.joints[1:4])
    scale = reach / 2880.0
    base_radii = [600.0, 450.0, 350.0, 220.0, 160.0, 110.0]
    return [base_radii[min(i, len(base_radii) - 1)] * scale for i in range(nominal.n_joints)]


#: The shortest distance of a link's reflector from its joint axis (mm): a wrist joint's
#: is mounted on an extension bar, since each stop's angle noise is the tracker's noise
#: over this radius (15-20 µm over 265 mm would be 3-4″ per stop on a KR500's flange).
MIN_TARGET_RADIUS_MM = 500.0


def link_target_mm(strip_radius_mm: float) -> tuple[float, float, float]:
    """Where the scale campaign's reflector sits on a link, in the link's frame (mm): past
    the ring, on a bar at least :data:`MIN_TARGET_RADIUS_MM` long."""
    r = strip_radius_mm
    return (max(1.5 * r + 100.0, MIN_TARGET_RADIUS_MM), 0.3 * r, 80.0)


@dataclass(frozen=True)
class TrackerModel:
    """A laser tracker at the origin of the world frame, measuring a spherical target.

    Noise follows a data-sheet MPE ``±(mpe_um + mpe_um_per_m · distance)``, taken as
    ``mpe_sigmas`` standard deviations, isotropic. ``scale_error_ppm`` is an instrument
    error (off by default). A broken beam yields NaN and status ``"beam_broken"``.
    """

    mpe_um: float = 15.0
    mpe_um_per_m: float = 6.0
    mpe_sigmas: float = 2.0
    scale_error_ppm: float = 0.0
    beam_break_probability: float = 0.0

    def sigma_mm(self, points_mm: ArrayLike) -> FloatArray:
        """Per-axis standard deviation (mm) of a measurement of each point, shape ``(N,)``."""
        dist_m = np.linalg.norm(np.atleast_2d(points_mm), axis=-1) / 1000.0
        sigma: FloatArray = 1e-3 * (self.mpe_um + self.mpe_um_per_m * dist_m) / self.mpe_sigmas
        return sigma

    def measure(
        self, points_mm: ArrayLike, rng: np.random.Generator
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Measured points ``(N, 3)`` mm and an ``ok`` mask ``(N,)`` (False: beam broken)."""
        pts = np.atleast_2d(np.asarray(points_mm, dtype=float))
        sigma = self.sigma_mm(pts)[:, None]
        measured = (
            pts * (1.0 + 1e-6 * self.scale_error_ppm) + rng.normal(0.0, 1.0, pts.shape) * sigma
        )
        ok = rng.random(len(pts)) >= self.beam_break_probability
        measured[~ok] = np.nan
        return measured, ok


def with_masses(desc: RobotDescription, masses: ArmMasses) -> RobotDescription:
    """``desc`` carrying ``masses`` (links and payload mass; the payload's centre of mass
    has no place in a description and goes to the truth document)."""
    joints = tuple(
        replace(j, mass_kg=float(m), com_mm=(float(c[0]), float(c[1]), float(c[2])))
        for j, m, c in zip(desc.joints, masses.mass_kg, masses.com_mm, strict=True)
    )
    return replace(desc, joints=joints, tool=replace(desc.tool, mass_kg=masses.payload_kg))


@dataclass(frozen=True)
class TrueCell:
    """The whole emulated truth of one cell: robot, strips, tracker, link targets, and the
    physical arm (its own masses and counterbalance; ``truth`` carries the same masses)."""

    nominal: RobotDescription
    truth: RobotDescription
    strips: tuple[GratingStrip, ...]
    tracker: TrackerModel
    link_targets_mm: tuple[tuple[float, float, float], ...]  # per joint, in that joint's frame
    arm: PhysicalArm
    seed: int = 0
    deviations: GeometryDeviations = field(default_factory=GeometryDeviations)

    @classmethod
    def create(
        cls,
        nominal: RobotDescription,
        seed: int,
        *,
        deviations: GeometryDeviations | None = None,
        tracker: TrackerModel | None = None,
        eccentricity_mm: float = 0.0,
        scale_error_ppm_sigma: float = 50.0,
        counterbalance: bool | None = None,
    ) -> TrueCell:
        """Draw a reproducible true cell around ``nominal`` from ``seed``.

        ``eccentricity_mm`` is the amplitude of each strip's cyclic error (0: none). The
        arm's masses are drawn from their own stream ``[seed, MASS_STREAM]``
        (:func:`sim_devices.arm_masses.draw_arm_masses`); ``counterbalance`` None gives
        heavy arms one on joint 2 (:meth:`PhysicalArm.of`).
        """
        rng = np.random.default_rng(seed)
        dev = deviations or GeometryDeviations()
        truth = true_description(nominal, rng, dev)
        strips = tuple(
            GratingStrip(
                radius_mm=r,
                scale_error_ppm=float(rng.normal(0.0, scale_error_ppm_sigma)),
                eccentricity_mm=eccentricity_mm,
                eccentricity_phase_rad=float(rng.uniform(-math.pi, math.pi)),
                zero_counts=int(rng.integers(0, COUNTER_MODULUS)),
                direction=1,
            )
            for r in default_strip_radii_mm(nominal)
        )
        radii = default_strip_radii_mm(nominal)
        targets = tuple(link_target_mm(r) for r in radii)
        tool = (truth.tool.x_mm, truth.tool.y_mm, truth.tool.z_mm)
        masses = draw_arm_masses(nominal, tool, np.random.default_rng([seed, MASS_STREAM]))
        truth = with_masses(truth, masses)
        return cls(
            nominal=nominal,
            truth=truth,
            strips=strips,
            tracker=tracker or TrackerModel(),
            link_targets_mm=targets,
            arm=PhysicalArm.of(truth, masses, counterbalance=counterbalance),
            seed=seed,
            deviations=dev,
        )

    @cached_property
    def model(self) -> KinematicModel:
        """The true kinematic model (built once: tcp_mm and link_target_mm use it per call)."""
        return KinematicModel.from_description(self.truth)

    def tcp_mm(self, q_rad: ArrayLike) -> FloatArray:
        """True TCP target positions in the tracker frame ``(N, 3)`` mm."""
        return tcp_positions(self.model, q_rad)

    def link_target_mm(self, joint: int, q_rad: ArrayLike) -> FloatArray:
        """True position of the target fixed on link ``joint`` (0-based) ``(N, 3)`` mm."""
        sub = self.model.truncated(joint + 1, tool_mm=self.link_targets_mm[joint])
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))[:, : joint + 1]
        return tcp_positions(sub, q)

    def truth_document(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "robot": tomllib.loads(self.truth.dumps()),
            "strip": [asdict(s) for s in self.strips],
            "tracker": asdict(self.tracker),
            "link_targets_mm": [list(t) for t in self.link_targets_mm],
            "deviations": asdict(self.deviations),
            "physical_arm": self.arm.document(),
        }

    def write_truth(self, path: str | Path) -> None:
        """Write the truth for tests (the twin never reads this file); atomic: the file
        appears whole or not at all (:class:`edges.outputs.OutputSet`)."""
        from edges.outputs import OutputSet
        from sim_devices.errors import SimError

        text = tomli_w.dumps(self.truth_document())
        with OutputSet(error=SimError) as outputs:
            outputs.file(path, "truth").write_text(text, encoding="utf-8")
