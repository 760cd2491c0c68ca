"""Junction targets encode and decode back to sub-pixel positions."""

import numpy as np

from envisat_pose.perception.heatmaps import decode_junctions, encode_junctions, to_cells, to_pixels


def test_cells_round_trip():
    p = np.random.default_rng(0).uniform(-10, 300, size=(20, 2))
    assert np.allclose(to_pixels(to_cells(p, 4), 4), p)
    # the centre of cell 0 is the centre of input pixels 0..3: 1.5
    assert np.allclose(to_pixels(np.zeros(2), 4), 1.5)


def test_encode_decode_subpixel():
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(20):
        n = 8
        pts = rng.uniform(2, 318, size=(n, 2))
        # keep junctions at least 3 cells apart so each has its own peak
        while np.min(np.linalg.norm(pts[:, None] - pts[None], axis=-1) + 1e9 * np.eye(n)) < 12:
            pts = rng.uniform(2, 318, size=(n, 2))
        types = rng.integers(0, 4, n)
        t = encode_junctions(pts, np.ones(n, bool), types, (80, 80), stride=4)
        assert t["jmap"].shape == (4, 80, 80) and t["joff"].shape == (2, 80, 80)
        assert np.all(np.abs(t["joff"]) <= 0.5)
        d = decode_junctions(t["jmap"], t["joff"], stride=4, top_k=16, threshold=0.5)
        assert len(d["points_px"]) == n
        dist = np.linalg.norm(d["points_px"][:, None] - pts[None], axis=-1)
        j = dist.argmin(axis=1)
        assert sorted(j) == list(range(n))
        assert np.array_equal(d["jtype"], types[j])
        worst = max(worst, dist.min(axis=1).max())
    assert worst < 0.05


def test_invalid_and_outside_junctions_are_not_marked():
    t = encode_junctions(np.array([[10.0, 10.0], [500.0, 5.0], [np.nan, 3.0], [40.0, 40.0]]),
                         np.array([True, True, True, False]), np.zeros(4, int), (20, 20), stride=4)
    assert t["jmask"].sum() == 1
    assert np.array_equal(t["cell"][1:], -np.ones((3, 2)))
