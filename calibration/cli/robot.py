"""``twin robot``: list presets, check a description file, print its home TCP."""

from __future__ import annotations

import argparse

import numpy as np

from calibration.effects.model_effects import description_effects, load_checked_robot
from calibration.errors import OutputFileError
from calibration.model.description import preset_names
from calibration.model.kinematics import KinematicModel, tcp_positions
from edges.outputs import OutputSet


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("robot", help="list presets or check a robot description file")
    p.add_argument("robot", nargs="?", help="preset name or path to a robot .toml")
    p.add_argument("--out", help="write the description back (normalized) to this file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.robot is None:
        print("\n".join(preset_names()))
        return 0
    with OutputSet([args.robot], error=OutputFileError) as outputs:
        out_path = outputs.file(args.out, "--out") if args.out else None
        desc = load_checked_robot(args.robot)  # [[effect]] tables as `twin predict` reads them
        specs, _ = description_effects(desc)
        model = KinematicModel.from_description(desc)
        home_tcp = tcp_positions(model, np.radians(desc.home))
        if out_path is not None:
            desc.save(out_path)
    print(f"{desc.name}: {desc.n_joints} joints, Home {list(desc.home)} deg")
    if specs:
        print(f"effects: {'; '.join(s.label for s in specs)}")
    print(f"Home TCP in the instrument frame: {np.round(home_tcp, 3).tolist()} mm")
    if out_path is not None:
        print(f"wrote {args.out}")
    return 0
