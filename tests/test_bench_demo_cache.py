"""bench_demo_seeds' ``--cache``: the streams read back are the streams kept (no pickle)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np

# `benchmarks` is not an installed package (tests/test_benchmarks_smoke.py)
ROOT = str(Path(__file__).resolve().parents[1])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
bench = importlib.import_module("benchmarks.bench_demo_seeds")


def test_kept_streams_read_back_as_they_were(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    wall = np.arange(0.0, 0.05, 0.001)
    counts = rng.integers(0, 2**32, size=(len(wall), 6))
    points = rng.normal(size=(len(wall), 3))
    ok = np.full((len(wall), 3), 1, dtype=np.uint16)
    ok[7] = 5  # a sample with another status
    grating = bench._stream(
        "cell/grating/samples", "grating", [f"grating{j}_counts" for j in range(1, 7)],
        wall, counts, np.ones(counts.shape, dtype=np.uint16),
    )  # fmt: skip
    tracker = bench._stream(
        "cell/tracker/samples", "tracker", ["x_mm", "y_mm", "z_mm"], wall, points, ok
    )
    kept = bench.CellStreams(grating, tracker, None, "a test")
    path = tmp_path / "s.npz"
    bench._save_streams(path, kept)
    back = bench._load_streams(path)
    assert back.source == "a test" and back.encoders is None
    for a, b in ((kept.grating, back.grating), (kept.tracker, back.tracker)):
        assert (a.key, a.kind, a.device, a.channels, a.meta) == (
            b.key, b.kind, b.device, b.channels, b.meta,
        )  # fmt: skip
        for name in bench._STREAM_ARRAYS:
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert not list(tmp_path.glob("*.tmp.npz"))  # moved into place
