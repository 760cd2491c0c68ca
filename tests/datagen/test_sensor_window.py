"""corrupt.apply_corruption_window (the space camera on the closed loop's region of interest alone) against the
full frame's crop: the margin is the reach of the blur and the blooming; the whole frame as a window is the full
frame byte for byte; on a flat grey image and on a rendered frame that saturates and blooms, the window's mean,
noise variance and noise lag-1 autocorrelation along x and y, and its mean picture over noise draws, are the full
frame crop's (the noise draws differ, so not the same pixels)."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np
import pytest

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.config import to_dict
from envisat_pose.datagen import sensor
from envisat_pose.datagen.corrupt import (
    KINDS,
    apply_corruption,
    apply_corruption_window,
    corruption_margin_px,
    draw_corruption,
)
from envisat_pose.datagen.generate_config import SensorConfig
from envisat_pose.datagen.image_kernels import motion_kernel

RES = 256
DRAWS = 12  # pairs of noise draws per parameter set and window
# Tolerances; in brackets the worst measured over 3 x (32 sensor and 16 paper parameter sets on the flat image,
# 2 windows each) and 2 x 16 sensor sets on the rendered one (3 windows each), 12 pairs of draws each:
MAX_MEAN_DIFF_SE = 5.0  # window mean vs the full frame crop's, in standard errors of the difference (3.0)
MAX_VAR_REL_DIFF = 0.1  # noise variance, relative (0.057)
MAX_RHO_DIFF = 0.05  # noise lag-1 autocorrelation along x, along y (0.032)
# the RMS difference of the two mean pictures over what the noise alone gives, sqrt(2 var / (2 DRAWS)) (1.052);
# the window corrupted alone, without margin nor place in the frame: 7.9 at least
MAX_RMS_RATIO = 1.15


def sensor_params(rng: np.random.Generator, f_px: float = 477.7) -> dict:
    """The space camera's parameters of one frame from the default ranges, with a random image motion."""
    return sensor.draw_sensor(to_dict(SensorConfig()), RES, f_px, float(rng.uniform(0, 300)),
                              float(rng.uniform(0, 180)), rng)


def window_of(img: np.ndarray, window_px: tuple[int, int, int]) -> np.ndarray:
    """The window (x0, y0, side) cut from an image, 0 outside it. (side, side)."""
    x0, y0, side = window_px
    pad = side + abs(x0) + abs(y0)
    return np.pad(img, pad)[y0 + pad : y0 + pad + side, x0 + pad : x0 + pad + side]


def grown(clean: np.ndarray, window_px: tuple[int, int, int], m: int) -> np.ndarray:
    """The clean window grown by m px on each side, 0 outside the image (what render_window gives)."""
    x0, y0, side = window_px
    return window_of(clean, (x0 - m, y0 - m, side + 2 * m))


def noise_stats(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(mean, noise variance, noise lag-1 autocorrelation along x, along y) of two draws a, b of one picture:
    their difference is the noise alone (the picture, vignetting and PRNU cancel), with twice its variance and
    its autocorrelation."""
    d = a.astype(np.float64) - b
    d -= d.mean()
    v = (d * d).mean()
    return np.array([0.5 * (a.mean() + b.mean()), v / 2, (d[:, 1:] * d[:, :-1]).mean() / v,
                     (d[1:] * d[:-1]).mean() / v])


def compare(clean: np.ndarray, p: dict, window_px: tuple[int, int, int], rng: np.random.Generator,
            corrupt_window=None) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Statistics of the window (apply_corruption_window, or corrupt_window(clean, p) for a planted fault) and
    of the full frame's crop over DRAWS pairs of noise seeds: (full's mean noise_stats, window's, the RMS
    difference of their mean pictures over what the noise alone gives, the standard error of the difference of
    their means from the noise alone, sqrt(var / (DRAWS n))). Only the window's n pixels in the image."""
    m = corruption_margin_px(p)
    keep = window_of(np.ones(clean.shape, dtype=bool), window_px)
    rows, cols = keep.any(axis=1), keep.any(axis=0)
    s_full, s_win, mean_full, mean_win = [], [], 0.0, 0.0
    for _ in range(DRAWS):
        pa, pb = (dict(p, noise_seed=int(rng.integers(0, 2**63))) for _ in range(2))
        fa, fb = (window_of(apply_corruption(clean, q), window_px)[rows][:, cols] for q in (pa, pb))
        if corrupt_window is None:
            wa, wb = (apply_corruption_window(grown(clean, window_px, m), window_px, RES, q)[rows][:, cols]
                      for q in (pa, pb))
        else:
            wa, wb = (corrupt_window(window_of(clean, window_px), q)[rows][:, cols] for q in (pa, pb))
        s_full.append(noise_stats(fa, fb))
        s_win.append(noise_stats(wa, wb))
        mean_full = mean_full + (fa + fb.astype(np.float64)) / (2 * DRAWS)
        mean_win = mean_win + (wa + wb.astype(np.float64)) / (2 * DRAWS)
    s_full, s_win = np.mean(s_full, axis=0), np.mean(s_win, axis=0)
    noise_var = 0.5 * (s_full[1] + s_win[1])
    rms_ratio = float(np.sqrt(((mean_win - mean_full) ** 2).mean() / (2 * noise_var / (2 * DRAWS))))
    return s_full, s_win, rms_ratio, float(np.sqrt(noise_var / (DRAWS * mean_full.size)))


def assert_same_statistics(s_full: np.ndarray, s_win: np.ndarray, rms_ratio: float, mean_se: float,
                           what: str) -> None:
    assert abs(s_win[0] - s_full[0]) <= MAX_MEAN_DIFF_SE * mean_se, (what, "mean", s_full, s_win, mean_se)
    assert abs(s_win[1] - s_full[1]) <= MAX_VAR_REL_DIFF * s_full[1], (what, "noise variance", s_full, s_win)
    assert np.all(np.abs(s_win[2:] - s_full[2:]) <= MAX_RHO_DIFF), (what, "noise autocorrelation", s_full, s_win)
    assert rms_ratio <= MAX_RMS_RATIO, (what, "mean picture", rms_ratio)


def test_the_margin_is_the_reach_of_the_kernels_and_the_blooming():
    """optics_reach_px is the half-size of the kernels the chain builds (PSF, streak); the margin adds the
    blooming's spill length; the paper model's margin is its blurs'; an uncorrupted image needs none."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        p = sensor_params(rng)
        psf = (sensor.gaussian_psf_1d(p["psf"]["sigma_px"]) if p["psf"]["kind"] == "gaussian"
               else sensor.airy_psf(p["psf"]["first_zero_px"]))
        length = p["motion_blur_length_px"]
        streak = motion_kernel(length, p["motion_blur_angle_deg"]).shape[0] // 2 if length > 0.05 else 0
        assert sensor.optics_reach_px(p) == psf.shape[0] // 2 + streak
        decay = p["blooming_decay_px"]
        bloom_half = sensor.bloom_reach_px(decay)
        assert bloom_half == int(np.ceil(6 * decay))
        assert corruption_margin_px(p) == sensor.optics_reach_px(p) + bloom_half
    p = draw_corruption({k: "high" for k in KINDS}, RES, rng)
    streak = motion_kernel(p["motion_blur_length_px"], p["motion_blur_angle_deg"]).shape[0] // 2
    assert corruption_margin_px(p) == streak + int(np.ceil(4 * p["gaussian_blur_sigma_px"])) + 1
    assert corruption_margin_px(draw_corruption({k: "none" for k in KINDS}, RES, rng)) == 0


@pytest.mark.parametrize("model", ["sensor", "paper"])
def test_the_whole_frame_as_a_window_is_the_full_frame(model):
    """A window holding the whole image (its margin off the image) runs the very chain of the full frame with
    the same seed: byte for byte apply_corruption; a window off the image is black."""
    rng = np.random.default_rng(1)
    clean = np.zeros((RES, RES), np.uint8)
    clean[60:190, 40:220] = rng.integers(0, 256, (130, 180))
    p = sensor_params(rng) if model == "sensor" else draw_corruption({k: "high" for k in KINDS}, RES, rng)
    m = corruption_margin_px(p)
    out = apply_corruption_window(grown(clean, (0, 0, RES), m), (0, 0, RES), RES, p)
    assert np.array_equal(out, apply_corruption(clean, p))
    off = apply_corruption_window(np.zeros((40 + 2 * m,) * 2, np.uint8), (RES + 3, 0, 40), RES, p)
    assert off.shape == (40, 40) and not off.any()
    with pytest.raises(ValueError, match="grown by corruption_margin_px"):
        apply_corruption_window(window_of(clean, (0, 0, 64)), (0, 0, 64), RES, p)


def test_the_windows_light_is_the_full_frames():
    """Steps 1-3 (vignetting at the window's place in the frame, PSF, streak) on the grown window: the full
    frame's irradiance over the window and the blooming reach around it (the charge that can spill in), to float
    rounding."""
    rng = np.random.default_rng(2)
    clean = np.zeros((RES, RES), np.uint8)
    clean[30:230, 50:200] = rng.integers(0, 256, (200, 150))
    x0, y0, side = 90, 100, 64
    for _ in range(10):
        p = sensor_params(rng)
        p["vignetting_cos_power"] = 4.0
        m, reach = corruption_margin_px(p), sensor.bloom_reach_px(p["blooming_decay_px"])
        irr = sensor.optics(grown(clean, (x0, y0, side), m), p, (y0 - m, x0 - m), (RES, RES))
        ref = sensor.optics(clean, p)[y0 - reach : y0 + side + reach, x0 - reach : x0 + side + reach]
        np.testing.assert_allclose(irr[m - reach : m + side + reach, m - reach : m + side + reach], ref, atol=1e-6)


@pytest.mark.parametrize("model", ["sensor", "paper"])
def test_a_flat_grey_window_has_the_full_frames_statistics(model):
    """A flat grey frame (vignetting, PRNU and noise only): an inner window and one clipped by the image's
    corner, several parameter draws: mean, noise variance, noise autocorrelation and mean picture agree."""
    rng = np.random.default_rng(3)
    flat = np.full((RES, RES), 128, np.uint8)
    for _ in range(4):
        paper = {k: "mixed" for k in KINDS} | {"exposure": "low", "shot_noise": "high"}  # noisy, unsaturated
        p = sensor_params(rng) if model == "sensor" else draw_corruption(paper, RES, rng)
        for window in ((40, 72, 96), (-20, 200, 80)):
            assert_same_statistics(*compare(flat, p, window, rng), f"{model} {window}")


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, float]:
    """ENVISAT at 30 m on the boresight, lit from behind the chaser, at RES px: (clean gray (RES, RES), f_px)."""
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_view import View

    r = SceneRenderer(RES)
    q = np.array([0.9, 0.3, -0.2, 0.25])
    view = View(np.array([0.0, 30.0, 0.0]), quat_to_rotmat(q / np.linalg.norm(q)), np.array([0.1, -1.0, 0.05]))
    gray = r.render(view, labels=False).gray_u8
    f_px = float(r.K[0, 0])
    r.close()
    return gray, f_px


def test_a_rendered_window_that_blooms_has_the_full_frames_statistics(rendered):
    """The rendered target with its bright foil saturating (white at grey 140) and blooming 4 px along the
    columns: windows on the target (bright pixels beyond their edges spill in), across the image's corner and
    in the dark agree with the full frame's crop. The window corrupted alone, without its margin and its place
    in the frame, does not: the test sees a missing margin."""
    clean, f_px = rendered
    assert (clean > 140).sum() > 1000, "the foil saturates"
    rng = np.random.default_rng(4)
    for _ in range(3):
        p = sensor_params(rng, f_px)
        p["white_e"], p["blooming_decay_px"], p["vignetting_cos_power"] = 255.0 / 140.0 * p["full_well_e"], 4.0, 4.0
        for window in ((100, 110, 96), (60, 40, 64), (200, 200, 80)):
            assert_same_statistics(*compare(clean, p, window, rng), f"rendered {window}")
        bare = compare(clean, p, (100, 110, 96), rng, corrupt_window=apply_corruption)[2]
        assert bare > 3 * MAX_RMS_RATIO, ("the window alone must differ", bare)
