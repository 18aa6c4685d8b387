"""Real data for ``twin track``: the IPA UR10 (series C) poses in measurement order.

Reads ``../shared/data/real/ur10_series_c/measurements_random_poses.csv`` (MIT,
Fraunhofer IPA; see that directory's README: the rows are in measurement order, the
timestamps were damaged) and writes into OUTDIR: ``ur10.toml`` (Universal Robots'
published D-H in this project's modified form, the T-Mac point 93 mm out on the flange
axis), ``campaign.csv`` (the first 100 rows to identify, the next 150 to validate) and
``checks.csv`` (every later row, ``t_s`` = 60 s per row: the order is real, the clock is
not). Then:

    python -m benchmarks.ur10_checks OUT
    twin identify --robot OUT/ur10.toml --data OUT/campaign.csv --out OUT/cal.toml
    twin track --model OUT/cal.toml --data OUT/checks.csv --out OUT/tracked.csv --report OUT/rep
"""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

SOURCE = (
    Path(__file__).resolve().parents[2]
    / "shared/data/real/ur10_series_c/measurements_random_poses.csv"
)
JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
# (a_mm, alpha_deg, d_mm) per joint, README's table
DH = ((0.0, 0.0, 127.3), (0.0, 90.0, 0.0), (-612.0, 0.0, 0.0), (-572.3, 0.0, 163.941))
DH += ((0.0, 90.0, 115.7), (0.0, -90.0, 92.2))
N_IDENTIFY, N_VALIDATE, SECONDS_PER_ROW = 100, 150, 60.0


def robot_text() -> str:
    lines = ['name = "UR10 CB (nominal, modified D-H)"', "[tool]", "x_mm = 0.0", "y_mm = 0.0"]
    lines.append("z_mm = 93.0")
    for a, alpha, d in DH:
        lines += ["[[joint]]", f"a_mm = {a}", f"alpha_deg = {alpha}", f"d_mm = {d}"]
        lines += ["theta_offset_deg = 0.0", "lower_deg = -360.0", "upper_deg = 360.0"]
    return "\n".join(lines) + "\n"


def _number(text: str) -> float:
    return float(text.replace(",", "."))  # decimal commas


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m benchmarks.ur10_checks OUTDIR", file=sys.stderr)
        return 2
    out = Path(args[0])
    out.mkdir(parents=True, exist_ok=True)
    with SOURCE.open(encoding="utf-8") as fh:
        rows = list(csv.reader(fh, delimiter=";"))
    head, data = rows[0], rows[1:]
    header = ["pose", "set", "t_s", *(f"q{k}_deg" for k in range(1, 7)), "x_mm", "y_mm", "z_mm"]
    files = {"campaign.csv": data[: N_IDENTIFY + N_VALIDATE], "checks.csv": data[250:]}
    for name, part in files.items():
        first = 0 if name == "campaign.csv" else N_IDENTIFY + N_VALIDATE
        with (out / name).open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(header)
            for i, r in enumerate(part, start=first):
                q = [math.degrees(_number(r[head.index(j)])) for j in JOINTS]
                p = [_number(r[head.index(f"measurement_{c}")]) for c in "xyz"]
                kind = "identify" if i < N_IDENTIFY else "validate"
                w.writerow(
                    [f"r{i + 1}", kind, f"{i * SECONDS_PER_ROW:.3f}"]
                    + [f"{v:.9f}" for v in q]
                    + [f"{v:.6f}" for v in p]
                )
    (out / "ur10.toml").write_text(robot_text(), encoding="utf-8")
    print(f"wrote {out}: ur10.toml, campaign.csv, checks.csv ({len(data) - 250} checks)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
