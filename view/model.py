"""The twin the view draws: a model, the gratings' scale maps, and what a calibration says.

Two ways to get one:

* :func:`load_calibration` — ``--model DIR/calibrated.toml`` from ``twin run``: the
  calibrated description with its found effects, the scale maps ``scale.toml`` and the
  campaign's time origin (``phases.json``) beside it, the stage table and added effects
  (``report/report.json``), and the nominal robot the run started from, drawn as a ghost.
* :func:`provisional_twin` — no calibration: the nominal robot, its base registered onto
  the recording's poses, and scale maps fitted from the recording's own sweeps (round 1
  of the twin's joint fit, no identification): enough to watch the arm move.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.effects.model_effects import predict_tcp
from calibration.model.description import BaseDescription, RobotDescription, load_robot
from calibration.model.kinematics import KinematicModel
from calibration.scales.scale_relation import GratingScale
from view.errors import ViewError
from view.scene import ghost_model

if TYPE_CHECKING:
    from calibration.twin.campaign_measurement import CampaignMeasurements

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class TwinModel:
    """What turns grating counts into the drawn arm and its TCP.

    ``scales`` maps joint number (1-based) to its scale map; ``t0_ns`` is the campaign's
    time origin (host UTC ns) for time-dependent effects; ``ghost`` is the nominal
    geometry on the calibrated base (None without a calibration).
    """

    description: RobotDescription
    scales: Mapping[int, GratingScale] | None
    t0_ns: int
    calibrated: bool
    source: str
    ghost: KinematicModel | None = None
    stage_table: str | None = None
    effects: tuple[str, ...] = ()

    @property
    def n_joints(self) -> int:
        return self.description.n_joints

    @property
    def kinematics(self) -> KinematicModel:
        return KinematicModel.from_description(self.description)

    def joint_deg(self, counts: ArrayLike) -> FloatArray | None:
        """Joint angles ``(N, n)`` deg from grating counts ``(N, n)``: ``home + map(c)``;
        None without scale maps."""
        if self.scales is None:
            return None
        c = np.atleast_2d(np.asarray(counts))
        home = np.asarray(self.description.home, dtype=float)
        out = np.full(c.shape, np.nan)
        for j, scale in self.scales.items():
            if 1 <= j <= c.shape[1]:
                out[:, j - 1] = home[j - 1] + scale.counts_to_angle_deg(c[:, j - 1])
        return out

    def tcp_mm(self, q_deg: ArrayLike, t_ns: ArrayLike) -> FloatArray:
        """TCP ``(N, 3)`` mm, tracker frame, every modelled effect applied, at joint angles
        ``(N, n)`` deg and host UTC times ``(N,)`` ns."""
        q = np.radians(np.atleast_2d(np.asarray(q_deg, dtype=float)))
        t_s = (np.atleast_1d(np.asarray(t_ns, dtype=np.int64)) - self.t0_ns) * 1e-9
        return predict_tcp(self.description, q, t_s)


def _read_json(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ViewError(f"{path}: not a JSON document of twin run ({exc})") from None
    return doc if isinstance(doc, dict) else None


def load_calibration(model_path: str | Path, robot: str | None = None) -> TwinModel:
    """The twin of a ``twin run`` output directory, from its ``calibrated.toml``.

    ``scale.toml`` and ``phases.json`` must be beside it (else the arm cannot follow the
    gratings: an error names the missing file); ``report/report.json`` gives the stage
    table, the added effects and the nominal robot (``robot``, a preset or file,
    overrides it).
    """
    from calibration.scales.scale_files import read_scale_toml
    from calibration.twin.run_documents import stage_table

    path = Path(model_path)
    desc = RobotDescription.load(path)
    run_dir = path.parent
    scale_path = run_dir / "scale.toml"
    if not scale_path.is_file():
        raise ViewError(
            f"--model {path}: no scale.toml beside it (give the calibrated.toml of a "
            "`twin run --out DIR`, whose DIR holds scale.toml and phases.json)"
        )
    scale = read_scale_toml(scale_path)
    phases = _read_json(run_dir / "phases.json") or {}
    campaign = phases.get("campaign")
    campaign = campaign if isinstance(campaign, dict) else {}
    t0_ns = int(campaign.get("t0_ns", 0) or 0)
    report = _read_json(run_dir / "report" / "report.json")
    table = None
    effects: tuple[str, ...] = tuple(e.kind for e in desc.effects)
    nominal_name = robot
    if report is not None:
        try:
            table = stage_table(report)
        except (KeyError, IndexError, TypeError):
            table = None
        loop = report.get("closed_loop") or {}
        labels = [s.get("label", "") for s in loop.get("stages", []) if "effect" in s]
        effects = tuple(labels) or effects
        source = (report.get("robot") or {}).get("source")
        if nominal_name is None and isinstance(source, str):
            nominal_name = source
    ghost = None
    if nominal_name is not None:
        nominal = load_robot(nominal_name)
        try:
            ghost = ghost_model(nominal, desc)
        except ValueError as exc:
            raise ViewError(f"--robot {nominal_name}: {exc}") from None
    return TwinModel(
        description=desc,
        scales=dict(scale.joints),
        t0_ns=t0_ns,
        calibrated=True,
        source=f"calibrated model {path}",
        ghost=ghost,
        stage_table=table,
        effects=effects,
    )


def nominal_twin(robot: str) -> TwinModel:
    """The nominal robot with no scale maps: the arm stays at Home."""
    desc = load_robot(robot)
    return TwinModel(desc, None, 0, False, f"nominal {robot}, no scale maps (arm at Home)")


def provisional_twin(robot: str, meas: CampaignMeasurements) -> TwinModel:
    """The nominal ``robot`` read through scale maps fitted from a recording's sweeps.

    ``meas``: the recording's
    :class:`~calibration.twin.campaign_measurement.CampaignMeasurements`. The base is the
    rigid registration of the nominal TCPs onto the tracker's pose points (the
    identification's own starting point) when there are at least 3 poses.
    """
    from calibration.model.kinematics import tcp_positions
    from calibration.model.registration import rigid_registration
    from calibration.scales.chain_scale import calibrate_scales

    desc = load_robot(robot)
    limits = [(j.lower_deg, j.upper_deg) for j in desc.joints]
    scales = calibrate_scales(meas.sweeps, meas.home_counts, home_deg=desc.home, limits_deg=limits)
    maps = {r.joint: r.scale for r in scales}
    twin = TwinModel(desc, maps, int(meas.phases.dwells[0].t0_ns), False, "")
    q = twin.joint_deg(meas.pose_counts)
    base_note = "nominal base guess"
    if q is not None and len(q) >= 3 and np.isfinite(q).all():
        local = tcp_positions(twin.kinematics, np.radians(q), world=False)
        fit = rigid_registration(local, meas.pose_points_mm)
        rx, ry, rz = np.degrees(fit.fixed_xyz_rad())
        x, y, z = (float(v) for v in fit.translation_mm)
        old = desc.base or BaseDescription()
        desc = replace(desc, base=BaseDescription(x, y, z, rx, ry, rz, old.gravity))
        base_note = f"base registered onto {len(q)} poses (rms {fit.rms_mm:.2f} mm)"
    return replace(
        twin,
        description=desc,
        source=f"nominal {robot}, {base_note}, scale maps fitted from the recording's sweeps",
    )
