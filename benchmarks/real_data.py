"""Real laser-tracker data of real robots (``../shared/data/real/``) as the twin's inputs.

Each data set becomes a nominal :class:`~calibration.model.description.RobotDescription` (the
data README's D-H table in the project's modified D-H, no base: it is fitted) and its
poses ``q_deg`` ``(m, 6)`` with the measured points ``xyz_mm`` ``(m, 3)``; a split of the
rows into identification, validation and held-out poses becomes a
:class:`~calibration.identify.campaign_files.Campaign`. Beside it, an independent geometric fit
(:func:`geometric_fit`: MDH + base + tool, 27 parameters, ``scipy.optimize.least_squares``,
its own forward kinematics) is the reference every benchmark compares with.

The data stay where they are (their licences ask for attribution; nothing is copied).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calibration.identify.campaign_files import Campaign
from calibration.model.description import JointDescription, RobotDescription, ToolDescription

FloatArray = NDArray[np.float64]

DATA_ROOT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"
UR10_FILE = DATA_ROOT / "ur10_series_c" / "measurements_random_poses.csv"
UR5_GRID_FILE = DATA_ROOT / "ur5" / "3D_UR5_uncalibrated_grid_cleaned.csv"
UR5_TEST_FILE = DATA_ROOT / "ur5" / "3D_UR5_uncalibrated_random_cleaned.csv"
UR10_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


@dataclass(frozen=True)
class RealData:
    """One data set: its nominal description, joint angles ``(m, 6)`` deg, points ``(m, 3)``
    mm in the instrument's frame, rows in measurement order."""

    name: str
    description: RobotDescription
    q_deg: FloatArray
    xyz_mm: FloatArray

    def __len__(self) -> int:
        return len(self.q_deg)

    def campaign(self, identify: NDArray[np.intp], validate: NDArray[np.intp]) -> Campaign:
        """The rows ``identify`` and ``validate`` as a campaign (times: the row number in
        seconds, keeping the measurement order; the files have no usable clock)."""
        rows = np.concatenate([identify, validate])
        order = np.argsort(rows, kind="stable")
        rows = rows[order]
        sets = np.array(["identify"] * len(identify) + ["validate"] * len(validate))[order]
        return Campaign(
            source=self.name,
            pose=tuple(str(int(r) + 1) for r in rows),
            set=tuple(str(s) for s in sets),
            t_s=rows.astype(float),
            q_deg=self.q_deg[rows],
            xyz_mm=self.xyz_mm[rows],
        )


def _ur_description(name: str, d1: float, a2: float, a3: float, d4: float, d5: float,
                    d6: float, tool_z_mm: float) -> RobotDescription:  # fmt: skip
    """A Universal Robots arm's D-H (the data README's table) in modified D-H; limits
    ±360° and the tracker target ``tool_z_mm`` along the flange axis."""
    rows = ((0.0, 0.0, d1), (0.0, 90.0, 0.0), (a2, 0.0, 0.0), (a3, 0.0, d4), (0.0, 90.0, d5))
    rows = (*rows, (0.0, -90.0, d6))
    joints = tuple(
        JointDescription(
            a_mm=a, alpha_deg=al, d_mm=d, theta_offset_deg=0.0, lower_deg=-360.0, upper_deg=360.0
        )
        for a, al, d in rows
    )
    return RobotDescription(name=name, joints=joints, tool=ToolDescription(0.0, 0.0, tool_z_mm))


def read_ur10(path: Path = UR10_FILE) -> RealData:
    """UR10 series C: ``;``-separated, decimal commas, joint angles in radians."""
    with open(path, encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh, delimiter=";"))

    def col(name: str) -> FloatArray:
        return np.array([float(r[name].replace(",", ".")) for r in rows])

    q = np.degrees(np.column_stack([col(j) for j in UR10_JOINTS]))
    xyz = np.column_stack([col(f"measurement_{a}") for a in "xyz"])
    desc = _ur_description("UR10 (nominal D-H)", 127.3, -612.0, -572.3, 163.941, 115.7, 92.2, 93.0)
    return RealData("ur10_series_c", desc, q, xyz)


def read_ur5(path: Path = UR5_GRID_FILE) -> RealData:
    """UR5 grid or test poses: degrees; the measured point is ``target − dif``."""
    with open(path, encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows.sort(key=lambda r: int(r["step_order"]))

    def col(name: str) -> FloatArray:
        return np.array([float(r[name]) for r in rows])

    q = np.column_stack([col(f"joint_{i}") for i in range(1, 7)])
    xyz = np.column_stack([col(f"{a}_t") - col(f"{a}_dif") for a in "xyz"])
    desc = _ur_description("UR5 (nominal D-H)", 89.159, -425.0, -392.25, 109.15, 94.65, 82.3, 31.0)
    return RealData("ur5", desc, q, xyz)


# -- the independent geometric fit ------------------------------------------------------------
#: The 27 parameters: (joint index 0-5, field) of the MDH rows, then base (6) and the
#: tool's x, y (2). Joint 1 is the base's; of the parallel joints 2-4 only one d (joint 4's)
#: is identifiable, and their misalignment is an α and a β; θ6 and the tool's z are the
#: tool's (the data README's 25 parameters put the point on the joint-6 axis).
FREE_JOINT_PARAMETERS = (
    (1, "a"), (1, "alpha"), (1, "theta"),
    (2, "a"), (2, "alpha"), (2, "theta"), (2, "beta"),
    (3, "a"), (3, "alpha"), (3, "d"), (3, "theta"), (3, "beta"),
    (4, "a"), (4, "alpha"), (4, "d"), (4, "theta"),
    (5, "a"), (5, "alpha"), (5, "d"),
)  # fmt: skip
_FIELDS = {"a": 0, "alpha": 1, "d": 2, "theta": 3, "beta": 4}


def _rot(axis: int, angle: FloatArray) -> FloatArray:
    """Rotations ``(..., 3, 3)`` about x (0), y (1) or z (2) by ``angle`` rad."""
    c, s = np.cos(angle), np.sin(angle)
    r = np.zeros((*np.shape(angle), 3, 3))
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    r[..., axis, axis] = 1.0
    r[..., i, i] = c
    r[..., j, j] = c
    sign = -1.0 if axis == 1 else 1.0
    r[..., i, j] = -s * sign
    r[..., j, i] = s * sign
    return r


def mdh_points(
    rows: FloatArray, base: FloatArray, tool: FloatArray, q_rad: FloatArray
) -> FloatArray:
    """Points ``(m, 3)``: rows ``(6, 5)`` (a mm, α rad, d mm, θ0 rad, β rad), base
    (x, y, z mm, rx, ry, rz rad fixed-axis), tool ``(3,)`` mm, joints ``(m, 6)`` rad."""
    m = len(q_rad)
    rot = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    pos = np.zeros((m, 3))
    for i, (a, al, d, th, be) in enumerate(rows):
        local = _rot(0, np.full(m, al)) @ _rot(1, np.full(m, be)) @ _rot(2, q_rad[:, i] + th)
        ax = _rot(0, np.array(al))
        pos = pos + rot @ (ax @ np.array([a, 0.0, 0.0]))
        rot = rot @ local
        pos = pos + rot[:, :, 2] * d
    p = pos + rot @ tool
    rb = _rot(2, np.array(base[5])) @ _rot(1, np.array(base[4])) @ _rot(0, np.array(base[3]))
    return np.asarray(p @ rb.T + base[:3])


def _nominal_rows(desc: RobotDescription) -> FloatArray:
    return np.array(
        [
            [j.a_mm, np.radians(j.alpha_deg), j.d_mm, np.radians(j.theta_offset_deg),
             np.radians(j.beta_deg)]
            for j in desc.joints
        ]
    )  # fmt: skip


def _registration(a: FloatArray, b: FloatArray) -> FloatArray:
    """Base ``(6,)`` of the rigid motion taking points ``a`` onto ``b`` (Kabsch)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    dd = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, dd]) @ u.T
    t = cb - r @ ca
    ry = np.arcsin(-np.clip(r[2, 0], -1, 1))
    return np.array([*t, np.arctan2(r[2, 1], r[2, 2]), ry, np.arctan2(r[1, 0], r[0, 0])])


@dataclass(frozen=True)
class GeometricFit:
    """The reference fit: MDH rows ``(6, 5)``, base ``(6,)``, tool ``(3,)``."""

    rows: FloatArray
    base: FloatArray
    tool: FloatArray

    def points(self, q_deg: FloatArray) -> FloatArray:
        return mdh_points(self.rows, self.base, self.tool, np.radians(q_deg))


def geometric_fit(desc: RobotDescription, q_deg: FloatArray, xyz_mm: FloatArray) -> GeometricFit:
    """MDH + base + tool by ``least_squares`` (trf, x_scale by the Jacobian), base started
    by a rigid registration of the nominal points."""
    q = np.radians(q_deg)
    rows0 = _nominal_rows(desc)
    tool0 = np.array([desc.tool.x_mm, desc.tool.y_mm, desc.tool.z_mm])
    base0 = _registration(mdh_points(rows0, np.zeros(6), tool0, q), xyz_mm)

    def unpack(x: FloatArray) -> GeometricFit:
        rows = rows0.copy()
        for v, (i, f) in zip(x[: len(FREE_JOINT_PARAMETERS)], FREE_JOINT_PARAMETERS, strict=True):
            rows[i, _FIELDS[f]] += v
        k = len(FREE_JOINT_PARAMETERS)
        return GeometricFit(rows, base0 + x[k : k + 6], tool0 + np.array([x[k + 6], x[k + 7], 0.0]))

    def residual(x: FloatArray) -> FloatArray:
        return (unpack(x).points(q_deg) - xyz_mm).ravel()

    # bounded: a real arm's errors are far below 20 mm and 0.1 rad, and the wrist's
    # parameters, with the point near the joint-6 axis, otherwise wander off to a worse
    # local minimum (the UR5's did)
    angle = [f in ("alpha", "theta", "beta") for _, f in FREE_JOINT_PARAMETERS]
    hi = np.array([0.1 if a else 20.0 for a in angle] + [np.inf] * 6 + [20.0, 20.0])
    x0 = np.zeros(len(FREE_JOINT_PARAMETERS) + 8)
    res = least_squares(
        residual, x0, bounds=(-hi, hi), method="trf", x_scale="jac", xtol=1e-10, ftol=1e-10
    )
    return unpack(res.x)


def split(
    m: int, n_identify: int, n_validate: int, seed: int
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """A random split of ``m`` rows: identification, validation, the rest held out."""
    perm = np.random.default_rng([seed, 29]).permutation(m)
    return (
        perm[:n_identify],
        perm[n_identify : n_identify + n_validate],
        perm[n_identify + n_validate :],
    )
