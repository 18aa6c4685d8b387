"""Emulated grating-scale calibration campaign (method §2): home returns and 2° sweeps.

For each joint, the others held at Home:

1. ``home_returns`` returns to Home, alternately from above and from below, each read by
   the grating (read noise, optional settling error of the true angle);
2. a sweep from the positive limit to the negative one (``forward``) in ``step_deg``
   stops, then back over the same commanded angles (``backward``); at every stop the
   grating is read and the tracker measures the target on the moving link
   (:meth:`TrueCell.link_target_mm`).

The wrist joints' full ±350° travel is swept (two turns of the target; nothing in the
fit minds). Commanded stops carry a small positioning error (``stop_jitter_deg``) that
the grating and the tracker both see, so it costs nothing but realism.

Off-by-default effects of this generator only (not in :mod:`sim_devices.truth`):

* ``hysteresis_counts``: the head reads ``+h/2`` counts when the joint moves towards the
  positive limit and ``-h/2`` when it moves towards the negative one (so ``h`` is
  backward-minus-forward at the same true angle);
* ``wild_points``: that many tracker points per joint displaced by ``wild_point_mm`` in a
  random direction.

Files (``write``): ``home.csv`` (``joint,trial,counts``), ``sweep.csv``
(``joint,pass,step,counts,x_mm,y_mm,z_mm``) and ``truth.toml`` (the cell's truth plus the
campaign options; the twin never reads it).

``python -m sim_devices.scale_campaign --robot kr500 --seed 1 --out DIR``
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import tomli_w
from numpy.typing import ArrayLike, NDArray

from calibration.description import load_robot
from sim_devices.truth import COUNTER_MODULUS, GratingStrip, TrueCell

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

PASSES: tuple[str, str] = ("forward", "backward")  # positive → negative limit, then back


@dataclass(frozen=True)
class CampaignOptions:
    """How the campaign is run; defaults follow the method (2° steps, 10 Home returns)."""

    step_deg: float = 2.0
    home_returns: int = 10
    settling_deg: float = 0.0  # 1σ of the true angle at each Home return
    stop_jitter_deg: float = 0.005  # 1σ of the true angle around each commanded stop
    hysteresis_counts: float = 0.0  # backward-minus-forward reading offset
    wild_points: int = 0  # tracker wild points per joint
    wild_point_mm: float = 1.0
    joints: tuple[int, ...] | None = None  # 1-based joints to calibrate (default: all)
    joints_without_home: tuple[int, ...] = ()  # 1-based joints that get no Home returns


@dataclass(frozen=True)
class JointTruth:
    """The true counts → angle relation of one joint (what the twin should recover).

    ``angle_deg(counts)`` is the true joint angle relative to the Home posture (the
    nominal Home, where the robot sits when told to go Home) for a raw, wrapped counter
    value, inverting :meth:`GratingStrip.ideal_counts` (no read noise).
    """

    joint: int  # 1-based
    strip: GratingStrip
    home_rad: float
    hysteresis_counts: float = 0.0

    @property
    def counts_per_rad(self) -> float:
        s = self.strip
        return s.direction * s.radius_mm * (1.0 + 1e-6 * s.scale_error_ppm) * s.counts_per_mm

    @property
    def home_counts(self) -> float:
        """Unwrapped ideal counter value at Home (no hysteresis)."""
        return float(self.strip.ideal_counts(self.home_rad))

    def counts_at(self, angle_deg: ArrayLike, direction: ArrayLike = 0.0) -> FloatArray:
        """Ideal (unwrapped, unquantized) counts at a true angle relative to Home.

        ``direction``: +1 moving towards the positive limit, -1 towards the negative one,
        0 for the direction average.
        """
        q = self.home_rad + np.radians(np.asarray(angle_deg, dtype=float))
        return self.strip.ideal_counts(q) + 0.5 * np.asarray(direction) * self.hysteresis_counts

    def angle_deg(self, counts: ArrayLike, direction: ArrayLike = 0.0) -> FloatArray:
        """True angle relative to Home (deg) of raw counter values (wrapped, 32-bit)."""
        c = np.asarray(counts, dtype=float)
        offset = np.mod(c - self.home_counts + COUNTER_MODULUS / 2, COUNTER_MODULUS)
        target = self.home_counts + offset - COUNTER_MODULUS / 2
        target = target - 0.5 * np.asarray(direction) * self.hysteresis_counts
        k = self.counts_per_rad
        q = self.home_rad + (target - self.home_counts) / k
        for _ in range(6):  # Newton; the cyclic term is a tiny fraction of the slope
            s = self.strip
            slope = k + s.direction * s.eccentricity_mm * s.counts_per_mm * np.cos(
                q + s.eccentricity_phase_rad
            )
            q = q - (self.strip.ideal_counts(q) - target) / slope
        return np.degrees(q - self.home_rad)


@dataclass(frozen=True, eq=False)
class ScaleCampaign:
    """The emulated measurements of one campaign, with the truth behind every row."""

    cell: TrueCell
    options: CampaignOptions
    home_joint: IntArray  # (H,) 1-based
    home_trial: IntArray  # (H,) 1-based
    home_counts: IntArray  # (H,) raw, wrapped
    sweep_joint: IntArray  # (S,) 1-based
    sweep_pass: NDArray[np.str_]  # (S,) "forward" / "backward"
    sweep_step: IntArray  # (S,) stop index from the start of the pass
    sweep_counts: IntArray  # (S,) raw, wrapped
    sweep_points_mm: FloatArray  # (S, 3) tracker measurements
    sweep_true_rad: FloatArray  # (S,) true joint angle at each stop
    sweep_true_points_mm: FloatArray  # (S, 3) true target positions
    wild_rows: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def truth(self, joint: int) -> JointTruth:
        """The true relation of ``joint`` (1-based)."""
        home = math.radians(self.cell.nominal.home[joint - 1])
        return JointTruth(joint, self.cell.strips[joint - 1], home, self.options.hysteresis_counts)

    def home_csv(self) -> str:
        lines = ["joint,trial,counts"]
        lines += [
            f"{j},{t},{c}"
            for j, t, c in zip(self.home_joint, self.home_trial, self.home_counts, strict=True)
        ]
        return "\n".join(lines) + "\n"

    def sweep_csv(self) -> str:
        lines = ["joint,pass,step,counts,x_mm,y_mm,z_mm"]
        for j, p, s, c, xyz in zip(
            self.sweep_joint,
            self.sweep_pass,
            self.sweep_step,
            self.sweep_counts,
            self.sweep_points_mm,
            strict=True,
        ):
            lines.append(f"{j},{p},{s},{c},{xyz[0]:.5f},{xyz[1]:.5f},{xyz[2]:.5f}")
        return "\n".join(lines) + "\n"

    def write(self, out_dir: str | Path) -> dict[str, Path]:
        """Write ``home.csv``, ``sweep.csv`` and ``truth.toml`` into ``out_dir``."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {"home": out / "home.csv", "sweep": out / "sweep.csv", "truth": out / "truth.toml"}
        paths["home"].write_text(self.home_csv(), encoding="utf-8")
        paths["sweep"].write_text(self.sweep_csv(), encoding="utf-8")
        doc = self.cell.truth_document()
        opts = {k: v for k, v in asdict(self.options).items() if v is not None}
        doc["campaign"] = {k: list(v) if isinstance(v, tuple) else v for k, v in opts.items()}
        paths["truth"].write_text(tomli_w.dumps(doc), encoding="utf-8")
        return paths


def commanded_stops_deg(lower_deg: float, upper_deg: float, step_deg: float) -> FloatArray:
    """Commanded angles of the forward pass: from the positive limit down in ``step_deg``."""
    n = math.floor((upper_deg - lower_deg) / step_deg + 1e-9) + 1
    return upper_deg - step_deg * np.arange(n)


def _read(
    strip: GratingStrip, q: FloatArray, offset: FloatArray, rng: np.random.Generator
) -> IntArray:
    """Grating readings with a direction offset (counts) added before rounding and wrap."""
    noisy = strip.ideal_counts(q) + offset + rng.normal(0.0, strip.noise_counts, q.shape)
    return np.mod(np.rint(noisy).astype(np.int64), COUNTER_MODULUS)


def run_campaign(
    cell: TrueCell, options: CampaignOptions | None = None, *, seed: int | None = None
) -> ScaleCampaign:
    """Emulate the whole campaign for ``cell``; ``seed`` defaults to the cell's seed."""
    opt = options or CampaignOptions()
    rng = np.random.default_rng([cell.seed if seed is None else seed, 20250502])
    nominal = cell.nominal
    home_rad = np.radians(nominal.home)
    joints = opt.joints or tuple(range(1, nominal.n_joints + 1))
    h = opt.hysteresis_counts
    hj, ht, hc = [], [], []
    sj, sp, ss, sc, spts, sq, strue, wild = [], [], [], [], [], [], [], []
    row0 = 0
    for joint in joints:
        i = joint - 1
        strip = cell.strips[i]
        if joint not in opt.joints_without_home and opt.home_returns > 0:
            trials = np.arange(1, opt.home_returns + 1)
            moving = np.where(trials % 2 == 1, 1.0, -1.0)  # from below, from above, ...
            q_home = home_rad[i] + np.radians(opt.settling_deg) * rng.normal(size=trials.size)
            hj.append(np.full(trials.size, joint))
            ht.append(trials)
            hc.append(_read(strip, q_home, 0.5 * h * moving, rng))

        jnt = nominal.joints[i]
        fwd = commanded_stops_deg(jnt.lower_deg, jnt.upper_deg, opt.step_deg)
        cmd = np.concatenate([fwd, fwd[::-1]])
        moving = np.concatenate([-np.ones(fwd.size), np.ones(fwd.size)])
        q = np.radians(cmd + opt.stop_jitter_deg * rng.normal(size=cmd.size))
        counts = _read(strip, q, 0.5 * h * moving, rng)
        q_all = np.tile(home_rad, (q.size, 1))
        q_all[:, i] = q
        true_pts = cell.link_target_mm(i, q_all)
        measured, ok = cell.tracker.measure(true_pts, rng)
        while not ok.all():  # a broken beam is simply measured again
            again, ok_again = cell.tracker.measure(true_pts[~ok], rng)
            measured[~ok] = again
            ok[~ok] = ok_again
        if opt.wild_points:
            rows = rng.choice(q.size, size=min(opt.wild_points, q.size), replace=False)
            direction = rng.normal(size=(rows.size, 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            measured[rows] += opt.wild_point_mm * direction
            wild.append(row0 + np.sort(rows))
        sj.append(np.full(q.size, joint))
        sp.append(np.repeat(np.array(PASSES), fwd.size))
        ss.append(np.concatenate([np.arange(fwd.size)] * 2))
        sc.append(counts)
        spts.append(measured)
        sq.append(q)
        strue.append(true_pts)
        row0 += q.size

    def cat(parts: list, dtype=None, shape=(0,)) -> NDArray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype=dtype)

    return ScaleCampaign(
        cell=cell,
        options=opt,
        home_joint=cat(hj, np.int64),
        home_trial=cat(ht, np.int64),
        home_counts=cat(hc, np.int64),
        sweep_joint=cat(sj, np.int64),
        sweep_pass=cat(sp, str),
        sweep_step=cat(ss, np.int64),
        sweep_counts=cat(sc, np.int64),
        sweep_points_mm=cat(spts, float, (0, 3)),
        sweep_true_rad=cat(sq, float),
        sweep_true_points_mm=cat(strue, float, (0, 3)),
        wild_rows=cat(wild, np.int64),
    )


def _joint_list(text: str) -> tuple[int, ...]:
    return tuple(int(t) for t in text.split(",") if t.strip())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m sim_devices.scale_campaign",
        description="Write home.csv, sweep.csv and truth.toml of an emulated scale campaign.",
    )
    parser.add_argument("--robot", default="kr500", help="preset name or description file")
    parser.add_argument("--seed", type=int, default=1, help="seed of the true cell")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--eccentricity-mm", type=float, default=0.0, help="strip cyclic error")
    parser.add_argument("--hysteresis-counts", type=float, default=0.0)
    parser.add_argument("--settling-deg", type=float, default=0.0)
    parser.add_argument("--wild-points", type=int, default=0, help="wild tracker points/joint")
    parser.add_argument("--joints", type=_joint_list, default=None, help="e.g. 1,2,3")
    parser.add_argument("--no-home", type=_joint_list, default=(), help="joints without home")
    args = parser.parse_args(argv)
    cell = TrueCell.create(load_robot(args.robot), args.seed, eccentricity_mm=args.eccentricity_mm)
    options = CampaignOptions(
        settling_deg=args.settling_deg,
        hysteresis_counts=args.hysteresis_counts,
        wild_points=args.wild_points,
        joints=args.joints,
        joints_without_home=args.no_home,
    )
    paths = run_campaign(cell, options).write(args.out)
    for p in paths.values():
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
