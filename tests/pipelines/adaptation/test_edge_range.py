"""pipelines/adaptation/edge_range.py: the outline's scale error from a frame's own silhouette edges, and the range correction.

(a) a box outline drawn by area coverage (16 x 16 samples a pixel), blurred and noisy, with its corners scaled
about their centroid by a known factor: the scale is recovered; (b) the project's own MuJoCo render at a known
pose, its corners projected from the renderer's own camera-frame corners through a pinhole built from the
render's field of view (not the code under test): the true outline gives ~0, the outline of the pose 0.5 % too
far gives +0.5 % (delta = image scale / projected scale - 1); (c) frames whose edges cannot be measured give no
delta, and no correction."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import cv2
import numpy as np
import pytest

from envisat_pose.pipelines.adaptation.edge_range import (
    ScaleFit,
    correct_range,
    edge_stations,
    fit_scale,
    frame_scale,
    outline_edges,
    sequence_scale,
)

HEX = np.array([[150.3, 80.6], [330.2, 101.1], [392.5, 210.0], [316.7, 335.4], [135.9, 314.8], [92.4, 190.2]])


def inside(poly: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Whether points (x, y) lie inside the convex polygon poly (vertices in clockwise image order)."""
    out = np.ones(np.broadcast_shapes(x.shape, y.shape), bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        out &= (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) >= 0
    return out


def draw(poly: np.ndarray, rng: np.random.Generator, grey: float = 160.0, size: int = 480, ss: int = 16,
         blur_px: float = 1.0, noise: float = 2.0) -> np.ndarray:
    """The convex polygon at `grey` on black by area coverage (ss x ss samples a pixel, OpenCV pixel centres),
    blurred by a Gaussian PSF, with Gaussian noise (grey levels) drawn from rng, 8 bits."""
    f = (np.arange(size * ss) + 0.5) / ss - 0.5
    cover = inside(poly, f[None, :], f[:, None]).reshape(size, ss, size, ss).mean(axis=(1, 3))
    img = cv2.GaussianBlur((cover * grey).astype(np.float32), (0, 0), blur_px)
    return np.clip(np.rint(img + rng.normal(0.0, noise, img.shape)), 0, 255).astype(np.uint8)


def as_box(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eight 'corners' (the polygon's and the rest near its centroid, inside it) and all visible: a box's hull is
    the polygon."""
    c = poly.mean(axis=0)
    return np.concatenate([poly, c + np.arange(8 - len(poly))[:, None] * np.array([1.0, 0.5])]), np.ones(8, bool)


@pytest.fixture(scope="module")
def scaled_image():
    """The hexagon scaled by 1.005 about its centroid and shifted by (0.3, -0.2) px, drawn."""
    c = HEX.mean(axis=0)
    return draw(c + 1.005 * (HEX - c) + np.array([0.3, -0.2]), np.random.default_rng(400))


def test_outline_is_the_hull_with_outward_normals():
    corners, use = as_box(HEX)
    edges, normals = outline_edges(corners, use)
    assert len(edges) == 6
    mid = edges.mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normals, mid - HEX.mean(axis=0)) > 0)
    assert np.allclose(np.einsum("ij,ij->i", normals, edges[:, 1] - edges[:, 0]), 0.0)


def test_a_known_scale_and_shift_are_recovered(scaled_image):
    corners, use = as_box(HEX)
    fit = frame_scale(scaled_image, corners, use)
    print(fit)
    assert fit.edges == 6 and fit.stations > 300
    assert abs(fit.delta - 0.005) < 0.0005, fit.delta
    assert fit.delta_se < 0.0003
    # the shift, about the hull's vertex mean (= HEX's centroid here, the scaling's centre)
    assert np.allclose(fit.shift_px, [0.3, -0.2], atol=0.05), fit.shift_px


def test_the_true_outline_reads_no_scale():
    corners, use = as_box(HEX)
    fit = frame_scale(draw(HEX, np.random.default_rng(401)), corners, use)
    assert abs(fit.delta) < 0.0005, fit.delta


def test_two_opposite_edges_alone_tell_the_scale():
    """A long thin box whose short edges are too short to measure: the long edges' normals are antiparallel, the
    shift along them unseen; delta from the two sides."""
    rect = np.array([[100.0, 200.0], [400.0, 210.0], [399.0, 238.0], [99.0, 228.0]])
    c = rect.mean(axis=0)
    img = draw(c + 1.005 * (rect - c), np.random.default_rng(402))
    corners, use = as_box(rect)
    fit = frame_scale(img, corners, use)
    assert fit.edges == 2
    # across the short side (28 px) the scale acts on 14 px half-widths: 0.07 px, so a looser bound
    assert abs(fit.delta - 0.005) < 0.002, fit.delta


def test_unmeasurable_frames_give_no_delta():
    corners, use = as_box(HEX)
    rng = np.random.default_rng(403)
    # no contrast: the box as dark as the sky behind it
    assert frame_scale(draw(HEX, rng, grey=10.0), corners, use).delta is None
    # one edge alone (the rest of the box as dark as the sky): scale and shift not separable
    img = draw(HEX, rng, grey=8.0)
    band = draw(np.array([[140.0, 60.0], [340.0, 90.0], [330.2, 101.1], [150.3, 80.6]]), rng, grey=160.0)
    assert frame_scale(np.maximum(img, band), corners, use).delta is None
    # a box too small for any station
    small = HEX.mean(axis=0) + 0.1 * (HEX - HEX.mean(axis=0))
    c_small, _ = as_box(small)
    assert frame_scale(draw(small, rng), c_small, use).delta is None
    # fewer than 3 corners in use
    assert frame_scale(draw(HEX, rng), corners, np.array([True, True] + [False] * 6)).delta is None
    # a textured inside (a 3 px checkerboard, +-45 grey levels): next to no station, no delta
    plain = edge_stations(draw(HEX, rng), corners, use)
    tex = draw(HEX, rng).astype(float)
    yy, xx = np.indices(tex.shape)
    tex += 45.0 * np.where((xx // 3 + yy // 3) % 2 == 0, 1.0, -1.0) * (tex > 80)
    st = edge_stations(np.clip(tex, 0, 255).astype(np.uint8), corners, use)
    assert len(st.offset_px) < 0.05 * len(plain.offset_px)
    assert fit_scale(st).delta is None


def test_no_fit_means_no_correction():
    x = np.array([1.0, 50.0, -2.0, 0.1, 0.2, 0.3, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03])
    cam = np.array([0.0, 0.0, 0.5])
    assert np.array_equal(correct_range(x, cam, np.nan), x)
    none = ScaleFit(None, None, np.full(2, np.nan), 0, 0)
    assert sequence_scale([none] * 20).delta is None
    fits = [ScaleFit(0.004, 0.001, np.zeros(2), 50, 3)] * 4
    assert sequence_scale(fits, min_frames=5).delta is None
    assert sequence_scale(fits + [none], min_frames=4).delta == pytest.approx(0.004)


def test_the_correction_moves_the_target_along_the_line_of_sight():
    rng = np.random.default_rng(404)
    x = np.concatenate([[3.0, 48.0, -2.0], rng.normal(size=9)])
    cam = np.array([0.2, 0.0, 0.5])
    y = correct_range(x, cam, 0.004)
    r0, r1 = x[:3] - cam, y[:3] - cam
    assert np.linalg.norm(r1) == pytest.approx(np.linalg.norm(r0) / 1.004, rel=1e-12)
    assert np.allclose(np.cross(r0, r1), 0.0, atol=1e-12)  # the same line of sight
    assert np.array_equal(y[3:], x[3:])                     # velocity, attitude, rate unchanged


def test_a_sequence_scale_is_robust_to_a_wild_frame():
    rng = np.random.default_rng(405)
    fits = [ScaleFit(float(0.004 + 0.0005 * rng.standard_normal()), 0.0005, np.zeros(2), 80, 3) for _ in range(30)]
    fits.append(ScaleFit(-0.05, 0.0003, np.zeros(2), 80, 3))
    seq = sequence_scale(fits)
    assert abs(seq.delta - 0.004) < 0.0005 and 0.0 < seq.delta_se < 0.0005


# ---------------------------------------------------------------------------------------------------------
# (b) physics: the project's MuJoCo render


def pinhole_px(corners_K_m: np.ndarray, fovy_deg: float, res: int) -> np.ndarray:
    """Camera-frame points (N, 3) to pixels (OpenCV centres) through the square render's pinhole: f = (res / 2) /
    tan(fovy / 2), principal point at the image centre."""
    f = 0.5 * res / np.tan(np.radians(fovy_deg) / 2.0)
    return f * corners_K_m[:, :2] / corners_K_m[:, 2:] + (res - 1) / 2.0


def test_the_rendered_outline_reads_its_range():
    """Own renders (datagen's SceneRenderer, 512 px, the MJCF's plain materials, no Earth) at random poses 45-55 m
    away: per frame, the true outline's delta and the outline of the same pose 0.5 % farther (every corner moved
    along the line of sight of the target's origin by 0.5 % of its range: the image scale of the far pose is
    1 / 1.005 of the true one, so delta = +0.5 %). Measured: the 12 frames' sequence_scale reads -0.02 % (true
    pose) and +0.48 % (far pose); the median frame within 0.05 % of either, single frames up to 0.6 % off (an
    edge next to the array or in the box's own shadow: why one scale per sequence). Bounds: 0.1 % on the
    sequence and on the median frame."""
    from envisat_pose.attitude import mrp_to_dcm, quat_to_mrp
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View

    res = 512
    renderer = SceneRenderer(res)
    rng = np.random.default_rng(4040)
    true_fits, far_fits = [], []
    try:
        while len(true_fits) < 12:
            q = rng.standard_normal(4)
            q /= np.linalg.norm(q)
            rho = np.array([rng.uniform(-2, 2), rng.uniform(45.0, 55.0), rng.uniform(-2, 2)])
            sun = rng.standard_normal(3)
            out = renderer.render(View(rho, mrp_to_dcm(quat_to_mrp(q)).T, sun / np.linalg.norm(sun)))
            use = np.ones(8, bool)
            true_px = pinhole_px(out.corners_K_m, out.fovy_deg, res)
            far_px = pinhole_px(out.corners_K_m + 0.005 * out.t_K_from_T_m, out.fovy_deg, res)
            f_true, f_far = frame_scale(out.gray_u8, true_px, use), frame_scale(out.gray_u8, far_px, use)
            if f_true.delta is None or f_far.delta is None:
                continue
            true_fits.append(f_true)
            far_fits.append(f_far)
    finally:
        renderer.close()
    d_true = np.array([f.delta for f in true_fits])
    d_far = np.array([f.delta for f in far_fits])
    s_true, s_far = sequence_scale(true_fits), sequence_scale(far_fits)
    print(f"true: {100 * s_true.delta:+.3f} % +- {100 * s_true.delta_se:.3f}, frames {np.round(100 * d_true, 3)}")
    print(f"far:  {100 * s_far.delta:+.3f} % +- {100 * s_far.delta_se:.3f}, frames {np.round(100 * d_far, 3)}")
    assert abs(s_true.delta) < 0.001
    assert abs(s_far.delta - 0.005) < 0.001
    assert abs(np.median(d_true)) < 0.001 and abs(np.median(d_far) - 0.005) < 0.001
