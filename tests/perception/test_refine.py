"""Sub-pixel refinement of a corner from its edges (perception/refine.py) against synthetic corners of known
position: straight edges, area-sampled pixels, a Gaussian PSF of known sigma."""

import cv2
import numpy as np

from envisat_pose.perception.refine import RefineConfig, refine_corner, refine_named


def wedge(corner, angles_deg, size=96, ss=8, sigma=1.0, levels=(40.0, 200.0), noise=0.0, rng=None):
    """A bright wedge between the rays from `corner` (px, pixel centres at integers) at two angles, each pixel
    the mean of ss x ss sub-samples (the pixel's area), blurred by a Gaussian of sigma px, 8-bit: (image, unit
    directions (2, 2))."""
    c = (np.arange(size * ss) + 0.5) / ss - 0.5
    X, Y = np.meshgrid(c, c)
    d = np.array([[np.cos(np.radians(a)), np.sin(np.radians(a))] for a in angles_deg])
    px, py = X - corner[0], Y - corner[1]
    inside = (d[0, 0] * py - d[0, 1] * px >= 0) & (px * d[1, 1] - py * d[1, 0] >= 0)
    img = np.where(inside, levels[1], levels[0]).reshape(size, ss, size, ss).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img, (0, 0), sigma)
    if noise:
        img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), d


def test_refine_recovers_a_blurred_corner_without_bias():
    rng = np.random.default_rng(0)
    errs = []
    for _ in range(60):
        corner = np.array([48.0, 48.0]) + rng.uniform(-0.5, 0.5, 2)
        a1 = rng.uniform(0, 360)
        img, d = wedge(corner, (a1, a1 + rng.uniform(40, 140)), sigma=rng.uniform(0.7, 1.5))
        start = corner + np.clip(rng.normal(0, 0.7, 2), -1.5, 1.5)  # where the network put it
        out = refine_corner(img, start, d, np.array([60.0, 60.0]))
        assert out is not None
        errs.append(out[0] - corner)
    e = np.array(errs)
    assert np.sqrt(np.mean(np.sum(e ** 2, axis=1))) < 0.05
    assert np.all(np.abs(e.mean(axis=0)) < 0.01)  # no bias


def test_refine_covariance_follows_the_noise():
    """With pixel noise the errors grow and the fit's covariance with them: mean e^T C^-1 e near 2."""
    rng = np.random.default_rng(1)
    nees, errs = [], []
    for _ in range(80):
        corner = np.array([48.0, 48.0]) + rng.uniform(-0.5, 0.5, 2)
        a1 = rng.uniform(0, 360)
        img, d = wedge(corner, (a1, a1 + rng.uniform(50, 130)), noise=8.0, rng=rng)
        out = refine_corner(img, corner + np.clip(rng.normal(0, 0.7, 2), -1.5, 1.5), d, np.array([60.0, 60.0]))
        if out is None:
            continue
        e = out[0] - corner
        errs.append(e)
        nees.append(float(e @ np.linalg.solve(out[1], e)))
    assert len(nees) > 60
    assert np.sqrt(np.mean(np.sum(np.array(errs) ** 2, axis=1))) < 0.3
    assert 1.0 < np.mean(nees) < 4.0


def test_no_bias_toward_the_noisier_side():
    """Shot-like noise (larger on the bright side) must not pull the edges inward (the magnitude of the
    derivative would: -0.085 +- 0.007 px on these corners)."""
    rng = np.random.default_rng(5)
    outward = []
    for _ in range(150):
        corner = np.array([48.0, 48.0]) + rng.uniform(-0.5, 0.5, 2)
        a1 = rng.uniform(0, 360)
        img, d = wedge(corner, (a1, a1 + rng.uniform(50, 130)), levels=(10.0, 200.0))
        f = img.astype(float)
        f = f + rng.normal(0, 1, f.shape) * 0.6 * np.sqrt(f + 4.0)
        img = np.clip(np.round(f), 0, 255).astype(np.uint8)
        out = refine_corner(img, corner + np.clip(rng.normal(0, 0.7, 2), -1.5, 1.5), d, np.array([60.0, 60.0]))
        if out is None:
            continue
        inward = (d[0] + d[1]) / np.linalg.norm(d[0] + d[1])  # into the bright wedge
        outward.append(-(out[0] - corner) @ inward)
    assert len(outward) > 120
    assert abs(np.mean(outward)) < 3.5 * np.std(outward) / np.sqrt(len(outward)) + 0.005


def test_parallel_edges_and_far_starts_are_refused():
    img, d = wedge(np.array([48.3, 47.6]), (30.0, 33.0))  # 3 degrees apart: no corner
    assert refine_corner(img, np.array([48.3, 47.6]), d, np.array([60.0, 60.0])) is None
    img, d = wedge(np.array([48.3, 47.6]), (30.0, 120.0))
    cfg = RefineConfig(max_shift_px=0.2)
    assert refine_corner(img, np.array([49.3, 47.6]), d, np.array([60.0, 60.0]), cfg) is None  # moved 1 px


def test_refine_named_uses_the_wireframe_edges_of_visible_corners():
    corner = np.array([40.4, 50.7])
    img, d = wedge(corner, (-20.0, 75.0))
    named = np.full((8, 2), np.nan)
    named[0] = corner + np.array([0.6, -0.5])
    projected = np.zeros((8, 2))
    projected[0], projected[1], projected[4] = corner, corner + 50 * d[0], corner + 50 * d[1]
    visible = np.zeros(8, bool)
    visible[[0, 1, 4]] = True
    out, cov, done = refine_named(img, named, projected, visible, ((0, 1), (0, 4), (1, 5)))
    assert done.tolist() == [True] + [False] * 7
    assert np.linalg.norm(out[0] - corner) < 0.05 and np.all(np.isfinite(cov[0]))
    assert np.all(np.isnan(out[1]))  # a corner not found stays not found


def test_bicubic_samples_any_number_of_points():
    """40,000 points at once (a 1024-px frame's edge profiles: remap once took them as one row and failed from
    32,767 on): a plane's values, which bicubic interpolation reproduces inside the frame up to remap's 1/32-px
    table of positions (0.75 grey levels a px here: 0.047 at most), and the same values as a few points alone."""
    from envisat_pose.perception.refine import sample_bicubic

    yy, xx = np.mgrid[0:300, 0:400].astype(np.float32)
    image = 0.25 * xx + 0.5 * yy + 3.0
    xy = np.random.default_rng(5).uniform([4, 4], [395, 295], (200, 200, 2))
    got = sample_bicubic(image, xy)
    assert got.shape == (200, 200)
    np.testing.assert_allclose(got, 0.25 * xy[..., 0] + 0.5 * xy[..., 1] + 3.0, atol=0.75 / 16)
    np.testing.assert_allclose(sample_bicubic(image, xy[:3, :7]), got[:3, :7], rtol=0, atol=1e-4)  # float32
