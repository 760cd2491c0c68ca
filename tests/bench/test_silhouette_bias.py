"""bench/silhouette_bias.py's edge locator on a synthetic silhouette whose edges are known exactly: a rotated
bright quadrilateral rasterized by area coverage (16 x 16 samples a pixel) and blurred by a Gaussian PSF sits on its
projected outline to a few hundredths of a pixel; clipped at the 8-bit ceiling after the blur it reads outward."""

import importlib.util
import os

import cv2
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def load_bench():
    path = os.path.join(HERE, "..", "..", "bench", "silhouette_bias.py")
    spec = importlib.util.spec_from_file_location("silhouette_bias", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def inside(corners: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Whether points (x, y) lie inside the convex quadrilateral (corners in clockwise image order)."""
    out = np.ones(np.broadcast_shapes(x.shape, y.shape), bool)
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        out &= (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) >= 0
    return out


def box_image(gain: float, blur_px: float = 1.0, size: int = 240, ss: int = 16):
    """A quadrilateral (its 4 corners, px, OpenCV pixel centres) at grey 180 x gain on black, by area coverage
    (ss x ss samples per pixel), blurred, clipped to 8 bits; its mask (1 where the pixel centre is inside)."""
    corners = np.array([[60.3, 50.6], [190.2, 71.1], [176.7, 185.4], [45.9, 164.8]])
    f = (np.arange(size * ss) + 0.5) / ss - 0.5  # sample positions in pixel coordinates
    cover = inside(corners, f[None, :], f[:, None]).reshape(size, ss, size, ss).mean(axis=(1, 3))
    img = cv2.GaussianBlur((cover * 180.0 * gain).astype(np.float32), (0, 0), blur_px)
    c = np.arange(size, dtype=float)
    mask = inside(corners, c[None, :], c[:, None]).astype(np.uint8)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), mask, corners


def test_edges_are_found_where_they_are_and_clipping_reads_outward():
    sb = load_bench()
    # the corners as the bench takes them: 8 of a box; here the 4 of one face, the other 4 the same points
    img, mask, corners = box_image(gain=1.0)
    pts = np.concatenate([corners, corners])
    vis = np.array([True] * 4 + [False] * 4)
    rows = sb.edge_offsets(img, mask, pts, vis)
    e = np.array([r[0] for r in rows])
    assert len(e) > 100 and not any(r[1] for r in rows)
    assert abs(np.median(e)) < 0.03 and abs(e.mean()) < 0.03, (np.median(e), e.mean())
    clipped, _, _ = box_image(gain=3.0)
    rows = sb.edge_offsets(clipped, mask, pts, vis)
    e = np.array([r[0] for r in rows])
    assert all(r[1] for r in rows) and np.median(e) > 0.3
