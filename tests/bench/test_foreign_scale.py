"""bench/foreign_scale.py: the per-frame scale and offset it reports are those of a known similarity (the
detector and the renderers are the bench's own run)."""

import importlib.util
import os
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def fs():
    spec = importlib.util.spec_from_file_location("foreign_scale", os.path.join(ROOT, "bench", "foreign_scale.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    yield mod
    sys.path.remove(os.path.join(ROOT, "bench"))


def test_frame_scale_recovers_a_scale_about_the_centroid_and_a_shift(fs):
    rng = np.random.default_rng(3)
    t = rng.uniform(100, 300, size=(6, 2))
    c = t.mean(axis=0)
    d = c + 0.996 * (t - c) + np.array([0.4, -0.2])
    s, off = fs.frame_scale(d, t)
    assert abs(s - 0.996) < 1e-12
    np.testing.assert_allclose(off, [0.4, -0.2], atol=1e-9)
    assert fs.frame_scale(d[:3], t[:3]) is None


def test_an_outlier_is_counted_not_fitted(fs):
    t = np.array([[100.0, 100], [200, 100], [200, 180], [100, 180], [150, 60], [250, 140], [0, 0], [0, 0]])
    d = t.copy()
    d[2] += (-8.0, 3.0)  # a corner hidden behind the array, found where the array's edge crosses the box
    use = np.array([True] * 6 + [False] * 2)
    d[6:] = np.nan
    row = fs.score_frame(d, t, use)
    assert row["outliers"] == 1 and abs(row["s"] - 1.0) < 1e-12 and len(row["err"]) == 5
