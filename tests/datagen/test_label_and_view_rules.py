"""Rules of the labels, the random views and the corruption models against computations written here.

- labels: a corner is in frame when its projection lies on the image area [-0.5, N - 0.5)^2 (OpenCV pixel centres at
  integers) and it is in front of the camera (z > 0); make_label takes N = 2 c_u + 1 from K. Hand-written points
  0.1 px either side of each edge, and one behind the camera that projects inside the image.
- views: view_is_clear refuses a camera nearer than keepout margin to the target's surface (a box of our own, its
  distance computed here); the random attitude is uniform on SO(3) (rotation angle CDF (theta - sin theta) / pi);
  the tumble rate is uniform in [0, rate_max_deg_s] converted to rad/s.
- sensor: the Airy first dark ring at 1.22 lambda N / pitch with the pixel pitch scaled to the resolution.
- corrupt ('paper' model): on a flat grey patch the noise variance is v 255 / full_well + sigma^2 + 1/12 (the
  Gaussian shot noise in grey levels, the read noise, and rounding to integers).
"""

import math

import numpy as np
import pytest
from scipy import stats

from envisat_pose.config import from_dict, to_dict
from envisat_pose.datagen.clearance import TargetBoxes, target_file_boxes
from envisat_pose.datagen.corrupt import KINDS, apply_corruption
from envisat_pose.datagen.generate_config import GenerateConfig, SensorConfig
from envisat_pose.datagen.labels import in_frame, make_label
from envisat_pose.datagen.sensor import draw_sensor
from envisat_pose.datagen.views import R_K_FROM_C, sample_random_view, view_is_clear

# ---------------------------------------------------------------------------------------------------------
# labels: in_frame and make_label

N_PX = 64
F_PX = 50.0


def _points_and_expected(n):
    """(u, v, z, expected in_frame): 0.1 px either side of each image edge, and a point behind the camera."""
    rows = [
        (-0.6, 10.0, 5.0, False),
        (-0.4, 10.0, 5.0, True),
        (n - 0.6, 10.0, 5.0, True),
        (n - 0.4, 10.0, 5.0, False),
        (10.0, -0.6, 5.0, False),
        (10.0, -0.4, 5.0, True),
        (10.0, n - 0.6, 5.0, True),
        (10.0, n - 0.4, 5.0, False),
        (20.0, 20.0, -5.0, False),  # behind the camera, its projection inside the image
        (n - 0.6, n - 0.6, 3.0, True),
    ]
    u, v, z, exp = (np.array(c) for c in zip(*rows))
    return u, v, z, exp.astype(bool)


def test_in_frame_edges_and_behind_the_camera():
    u, v, z, expected = _points_and_expected(N_PX)
    got = in_frame(np.stack([u, v], axis=-1), z, N_PX)
    # the rule, computed here: u, v in [-0.5, N - 0.5) and z > 0
    rule = (u >= -0.5) & (u < N_PX - 0.5) & (v >= -0.5) & (v < N_PX - 0.5) & (z > 0)
    np.testing.assert_array_equal(rule, expected)
    np.testing.assert_array_equal(np.asarray(got, bool), expected)


def test_make_label_in_frame_uses_the_image_size_from_the_principal_point():
    """N = 64 px: c = (N - 1) / 2 = 31.5. Corners placed in K so that they project 0.1 px inside or outside each
    edge; one behind the camera projects inside the image and is neither in frame nor visible."""
    u, v, z, expected = _points_and_expected(N_PX)
    sel = [0, 1, 2, 3, 5, 6, 7, 8]  # 8 corners
    u, v, z, expected = u[sel], v[sel], z[sel], expected[sel]
    c = (N_PX - 1) / 2.0
    K = np.array([[F_PX, 0.0, c], [0.0, F_PX, c], [0.0, 0.0, 1.0]])
    corners_K = np.stack([(u - c) * z / F_PX, (v - c) * z / F_PX, z], axis=-1)
    unoccluded = np.array([True, True, True, True, True, False, True, True])
    label = make_label(corners_K, unoccluded, K, np.eye(3), np.zeros(3), np.zeros(12), 1e-3, {}, 7, {})
    np.testing.assert_allclose(np.array(label["corners_px"]), np.stack([u, v], -1), atol=1e-3)
    np.testing.assert_array_equal(np.array(label["in_frame"], bool), expected)
    np.testing.assert_array_equal(np.array(label["visible"], bool), expected & unoccluded)


# ---------------------------------------------------------------------------------------------------------
# views: clearance, attitude, tumble rate

HALF_M = np.array([1.0, 2.0, 0.5])


def _one_box():
    return TargetBoxes(("block",), np.zeros((1, 3)), np.eye(3)[None], HALF_M[None].copy())


def _rotation(seed):
    q = np.random.default_rng(seed).standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.mark.parametrize("rot_seed", [None, 11, 12])
@pytest.mark.parametrize("margin_m", [2.0, 0.8])
def test_view_is_clear_at_the_keepout_margin(rot_seed, margin_m):
    """The target (one box, centred on T's origin) straight down the boresight at a range that puts the camera
    margin -/+ 0.05 m from the box's surface: refused inside the margin, kept outside it."""
    boxes = _one_box()
    R = np.eye(3) if rot_seed is None else _rotation(rot_seed)
    b_C = R_K_FROM_C[2]  # the boresight in C
    d = -R.T @ b_C  # direction of the camera from the target centre, in T

    def dist(range_m):  # camera's distance to the box surface, computed here
        return float(np.linalg.norm(np.maximum(np.abs(range_m * d) - HALF_M, 0.0)))

    def range_at(target_m):  # bisection: dist grows monotonically with the range outside the box
        lo, hi = 0.0, 100.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if dist(mid) < target_m else (lo, mid)
        return 0.5 * (lo + hi)

    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * HALF_M
    znear = 0.001
    for target_m, clear in ((margin_m - 0.05, False), (margin_m + 0.05, True)):
        r = range_at(target_m)
        assert abs(dist(r) - target_m) < 1e-9
        rho_C = r * b_C
        z_K = (rho_C[None] + corners @ R.T) @ b_C
        assert z_K.min() > znear + 0.05  # the near plane does not decide here
        assert view_is_clear(rho_C, R, boxes, margin_m, znear) is clear


@pytest.fixture(scope="module")
def random_draws():
    """3000 random-mode views far from the target (no redraws), seed 1234: rotation angles and tumble rates."""
    cfg = from_dict(GenerateConfig, {"earth_probability": 0.0,
                                     "random": {"range_min_m": 60.0, "range_max_m": 100.0, "rate_max_deg_s": 5.0}})
    boxes = target_file_boxes(cfg.target)
    assert 60.0 > boxes.reach_m + cfg.random.keepout_margin_m + 1.0  # every first draw is kept
    rng = np.random.default_rng(1234)
    theta, w = [], []
    for _ in range(3000):
        view, x, _ = sample_random_view(cfg, 30.0, rng, znear_m=0.1, boxes=boxes)
        R = np.asarray(view.R_C_from_T)
        theta.append(math.acos(min(1.0, max(-1.0, (np.trace(R) - 1.0) / 2.0))))
        w.append(np.asarray(x[9:12], float))
    return cfg, np.array(theta), np.array(w)


def test_random_attitude_is_uniform_on_so3(random_draws):
    """Haar measure on SO(3): the rotation angle has density (1 - cos theta) / pi, CDF (theta - sin theta) / pi."""
    _, theta, _ = random_draws
    res = stats.kstest(theta, lambda t: (t - np.sin(t)) / np.pi)
    assert res.pvalue > 1e-3, res


def test_random_tumble_rate_is_in_rad_per_s_up_to_the_configured_deg_per_s(random_draws):
    cfg, _, w = random_draws
    w_max = math.radians(cfg.random.rate_max_deg_s)  # 0.0873 rad/s
    speed = np.linalg.norm(w, axis=1)
    assert speed.max() <= w_max * (1 + 1e-12)
    n = len(speed)
    # uniform on [0, w_max]: mean w_max / 2, sd w_max / sqrt(12)
    assert abs(speed.mean() - w_max / 2) < 5 * w_max / math.sqrt(12 * n)
    assert stats.kstest(speed, stats.uniform(0.0, w_max).cdf).pvalue > 1e-3
    # a uniform axis: the mean unit axis is near 0 (each component sd 1 / sqrt(3 n))
    axis = w / speed[:, None]
    assert np.all(np.abs(axis.mean(axis=0)) < 5 / math.sqrt(3 * n))


# ---------------------------------------------------------------------------------------------------------
# sensor: the Airy ring at another resolution


@pytest.mark.parametrize("resolution_px", [512, 256])
def test_airy_first_zero_scales_the_pixel_pitch_with_the_resolution(resolution_px):
    """The same optics at a lower resolution: the pixel pitch grows as 1024 / N, so the ring shrinks in pixels."""
    cfg = {**to_dict(SensorConfig()), "psf": "airy"}
    rng = np.random.default_rng(5)
    for _ in range(5):
        p = draw_sensor(cfg, resolution_px, 900.0, 0.0, 0.0, rng)
        pitch_m = 5.5e-6 * 1024.0 / resolution_px  # pixel_pitch_m_1024's default, scaled here
        expected = 1.22 * 550e-9 * p["psf"]["f_number"] / pitch_m
        assert p["psf"]["kind"] == "airy"
        assert abs(p["psf"]["first_zero_px"] - expected) < 2e-3 * expected + 1e-5


# ---------------------------------------------------------------------------------------------------------
# corrupt: the 'paper' model's shot noise on a flat patch


@pytest.mark.parametrize("grey, full_well_e, sigma", [(100, 800.0, 0.0), (60, 4000.0, 2.0), (180, 20000.0, 0.0)])
def test_paper_shot_noise_variance_on_a_flat_patch(grey, full_well_e, sigma):
    """Shot noise in grey levels: N(0, v 255 / full_well) (v grey levels = v / 255 of full scale = v full_well /
    255 electrons, Poisson sd sqrt of that, times 255 / full_well grey levels per electron); plus read noise
    sigma^2 and rounding to integers (uniform, 1/12)."""
    clean = np.full((400, 400), grey, np.uint8)
    levels = {k: "none" for k in KINDS} | {"shot_noise": "high"}
    if sigma:
        levels["gaussian_noise"] = "low"
    params = {"model": "paper", "levels": levels, "exposure_gain": 1.0, "motion_blur_length_px": 0.0,
              "motion_blur_angle_deg": 0.0, "gaussian_blur_sigma_px": 0.0, "shot_noise_full_well_e": full_well_e,
              "gaussian_noise_sigma": sigma, "noise_seed": 2024}
    out = apply_corruption(clean, params).astype(np.float64)
    diff = out - grey
    n = diff.size
    electrons = grey / 255.0 * full_well_e
    expected = (math.sqrt(electrons) * 255.0 / full_well_e) ** 2 + sigma**2 + 1.0 / 12.0
    assert abs(diff.mean()) < 5 * math.sqrt(expected / n)
    # sd of a sample variance of a near-normal variable: var sqrt(2 / n)
    assert abs(diff.var() - expected) < 5 * expected * math.sqrt(2.0 / n) + 0.01
