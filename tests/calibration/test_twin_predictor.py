"""The live twin's TCP (calibration.twin.twin_predictor.TwinPredictor) against the full predictor,
and its link frames against the kinematics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.effects.model_effects import predict_tcp
from calibration.model.description import load_robot
from calibration.model.kinematics import KinematicModel, flange_poses
from calibration.twin.twin_predictor import TwinPredictor, rotation_quaternions

MODEL = Path(__file__).parents[1] / "data" / "twin_calibrated_small" / "calibrated.toml"


@pytest.fixture(scope="module")
def desc():
    d = load_robot(str(MODEL))
    assert d.effects, "the shipped model carries the found gravity deflection"
    return d


def _walk(rng, start_deg, n, step_deg):
    """A path of ``n`` poses from ``start_deg`` in random small steps (rad)."""
    steps = rng.normal(0.0, step_deg, size=(n, len(start_deg)))
    return np.radians(np.asarray(start_deg) + np.cumsum(steps, axis=0))


def test_linearised_effects_match_the_full_predictor(desc):
    rng = np.random.default_rng(3)
    pred = TwinPredictor(desc, radius_deg=0.25)
    worst = 0.0
    for start in ([0, 0, 0, 0, 0, 0], [30, 20, -40, 90, 45, -120], [-120, 80, 30, -200, -90, 60]):
        q = _walk(rng, start, 400, 0.02)  # crosses the radius many times
        t = np.linspace(0.0, 0.4, len(q))
        for a in range(0, len(q), 3):  # batches of 3 samples, as they arrive
            tcp, fl = pred.tcp_and_flange(q[a : a + 3], t[a : a + 3])
            full = predict_tcp(desc, q[a : a + 3], t[a : a + 3])
            worst = max(worst, float(np.abs(tcp - full).max()))
            assert np.allclose(
                fl, flange_poses(KinematicModel.from_description(desc), q[a : a + 3])
            )
    effect = np.abs(
        predict_tcp(desc, q, t) - pred._geometric(q)[0]
    ).max()  # what the effects add: tenths of a millimetre
    assert effect > 0.01
    assert worst < 1e-4, worst  # mm: second order in the distance to the linearisation
    assert pred.refreshes > 10  # it moved with the robot


def test_a_batch_wider_than_the_radius_gets_the_full_predictor(desc):
    pred = TwinPredictor(desc, radius_deg=0.25)
    q = np.radians([[0, 0, 0, 0, 0, 0], [3, 0, 0, 0, 0, 0]])
    tcp, _ = pred.tcp_and_flange(q, np.zeros(2))
    assert np.allclose(tcp, predict_tcp(desc, q, np.zeros(2)), atol=1e-9)
    assert pred.full_calls == 2  # the linearisation at the newest sample, then the batch


def test_radius_zero_is_the_full_predictor(desc):
    pred = TwinPredictor(desc, radius_deg=0.0)
    q = np.radians([[10, 20, -30, 40, 50, 60]])
    tcp, _ = pred.tcp_and_flange(q, np.zeros(1))
    assert np.array_equal(tcp, predict_tcp(desc, q, np.zeros(1)))


def test_link_frames_follow_the_kinematics(desc):
    pred = TwinPredictor(desc)
    model = KinematicModel.from_description(desc)
    q = np.radians([[10, 20, -30, 40, 50, 60], [0, 0, 0, 0, 0, 0]])
    pos, quat = pred.frames(q)
    assert pos.shape == (2, 8, 3) and quat.shape == (2, 8, 4)
    assert pred.frame_names == ("base", "link1", "link2", "link3", "link4", "link5", "link6", "tcp")
    fl = flange_poses(model, q)
    assert np.allclose(pos[:, 6], fl[:, :3, 3]) and np.allclose(
        quat[:, 6], rotation_quaternions(fl[:, :3, :3])
    )
    assert np.allclose(pos[:, 7], pred._geometric(q)[0])  # the TCP
    assert np.allclose(pos[:, 0], model.base_mm)
    assert np.allclose(np.linalg.norm(quat, axis=2), 1.0)


def test_linearised_scale_maps_match_the_maps():
    import json

    from calibration.scales.scale_files import read_scale_toml
    from calibration.twin.twin_predictor import AngleReader

    data = MODEL.parent
    scale = read_scale_toml(str(data / "scale.toml"))
    home_counts = np.array(json.loads((data / "phases.json").read_text())["home_counts"])
    reader = AngleReader(scale, 6, [0.0] * 6, radius_deg=0.25)
    exact = AngleReader(scale, 6, [0.0] * 6, radius_deg=0.0)
    rng = np.random.default_rng(5)
    worst = 0.0
    for start in (home_counts, home_counts + 200_000, home_counts - 150_000):
        # a path of small random steps (counts), crossing the radius many times, and
        # through the 32-bit counter's wrap for one joint
        counts = np.round(start + np.cumsum(rng.normal(0, 40, (600, 6)), axis=0)).astype(np.int64)
        counts[:, 0] = (counts[:, 0] - counts[300, 0] + (1 << 32)) % (1 << 32)  # wraps at 300
        for a in range(0, len(counts), 4):
            q = reader.angles(counts[a : a + 4])
            worst = max(worst, float(np.abs(q - exact.angles(counts[a : a + 4])).max()))
    assert worst < 5e-6, worst  # degrees; one count is ~1e-4 degrees
    assert reader.refreshes > 5 and exact.full_calls > 100
    # a batch wider than the radius: the maps themselves
    before = reader.full_calls
    wide = np.stack([home_counts, home_counts + 50_000]).astype(np.int64)
    assert np.allclose(reader.angles(wide), exact.angles(wide), atol=1e-12)
    assert reader.full_calls == before + 1
