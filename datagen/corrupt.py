"""Image corruption: exposure, motion blur, Gaussian blur, shot noise and Gaussian noise at named severities.

Each kind has four levels, 0 'none' .. 3 'high' (a config may also say 'mixed': a level drawn per image).
`draw_corruption` turns levels into concrete parameters with the sample's Generator; `apply_corruption`
applies them, its noise drawn from the parameters' own `noise_seed`, so the label's `corruption` entry alone
reproduces the image from the clean render (training can corrupt on the fly the same way). Blur sizes are
given at 1024 px and scale with the resolution. Level 0 for every kind returns the input unchanged, under
either model: the space camera (model 'sensor') honours the kinds only when all five are 'none'
(check_severities refuses any other choice but the default 'mixed' there).
"""

from __future__ import annotations

import cv2
import numpy as np

from envisat_pose.config import ConfigError
from envisat_pose.contracts import SEVERITIES
from envisat_pose.datagen.image_kernels import content_box, motion_kernel, standard_normal_fast
from envisat_pose.datagen.sensor import apply_sensor, bloom_reach_px, optics_reach_px

KINDS = ("exposure", "motion_blur", "gaussian_blur", "shot_noise", "gaussian_noise")

# Per level 0..3. Gaussian noise: sigma in grey levels. Gaussian blur: sigma in px at 1024 px. Shot noise:
# electrons at full scale (255), fewer electrons = more noise. Motion blur: streak length in px at 1024 px.
# Exposure: the largest factor of the log-uniform gain draw (gain in [1/g, g]).
GAUSSIAN_NOISE_SIGMA = (0.0, 2.0, 5.0, 10.0)
GAUSSIAN_BLUR_SIGMA_PX_1024 = (0.0, 1.0, 2.0, 4.0)
SHOT_NOISE_FULL_WELL_E = (np.inf, 20000.0, 4000.0, 800.0)
MOTION_BLUR_LENGTH_PX_1024 = (0.0, 4.0, 10.0, 24.0)
EXPOSURE_MAX_GAIN = (1.0, 1.25, 1.6, 2.5)


def severity_level(name: str, rng: np.random.Generator) -> int:
    """A configured severity ('none'..'high' or 'mixed') as a level 0..3; 'mixed' draws one uniformly."""
    if name == "mixed":
        return int(rng.integers(0, len(SEVERITIES)))
    return SEVERITIES.index(name)


def corruption_off(severities: dict[str, str]) -> bool:
    """Whether every kind is 'none': the user asked for uncorrupted frames, whatever the model."""
    return all(severities[k] == "none" for k in KINDS)


def check_severities(model: str, severities: dict[str, str], prefix: str = "corruption") -> None:
    """ConfigError (one line) unless the per-kind severities mean what they say under `model`.

    'paper' honours each kind. 'sensor' (the space camera, configured by [corruption.sensor]) honours only
    all five 'none' (uncorrupted frames); any other choice than the default 'mixed' would be ignored silently.
    """

    if model != "sensor" or corruption_off(severities):
        return
    p = f"{prefix}." if prefix else ""
    for k in KINDS:
        if severities[k] != "mixed":
            raise ConfigError(f"{p}{k}", severities[k],
                              "'mixed' with model = 'sensor': the severities " + ", ".join(KINDS) + " are "
                              "honoured by model = 'paper'; 'sensor' takes [corruption.sensor] ranges and "
                              "honours only all five 'none' (uncorrupted frames)")


def no_corruption() -> dict:
    """The parameters of an uncorrupted image (every kind 'none'; model 'none'): apply_corruption returns
    the clean render unchanged."""
    return {
        "model": "none",
        "levels": {k: "none" for k in KINDS},
        "exposure_gain": 1.0,
        "motion_blur_length_px": 0.0,
        "motion_blur_angle_deg": 0.0,
        "gaussian_blur_sigma_px": 0.0,
        "shot_noise_full_well_e": None,
        "gaussian_noise_sigma": 0.0,
        "noise_seed": 0,
    }


def draw_corruption(severities: dict[str, str], resolution_px: int, rng: np.random.Generator) -> dict:
    """Concrete corruption parameters of one image from its Generator. Returns plain JSON data:
    levels per kind, exposure_gain, motion_blur_length_px, motion_blur_angle_deg, gaussian_blur_sigma_px,
    shot_noise_full_well_e (None when off), gaussian_noise_sigma, noise_seed."""
    lv = {k: severity_level(severities[k], rng) for k in KINDS}
    scale = resolution_px / 1024.0
    g_max = EXPOSURE_MAX_GAIN[lv["exposure"]]
    gain = float(np.exp(rng.uniform(-np.log(g_max), np.log(g_max)))) if lv["exposure"] else 1.0
    angle = float(rng.uniform(0.0, 180.0))
    full_well = SHOT_NOISE_FULL_WELL_E[lv["shot_noise"]]
    return {
        "model": "paper",
        "levels": {k: SEVERITIES[v] for k, v in lv.items()},
        "exposure_gain": round(gain, 6),
        "motion_blur_length_px": round(MOTION_BLUR_LENGTH_PX_1024[lv["motion_blur"]] * scale, 6),
        "motion_blur_angle_deg": round(angle, 6),
        "gaussian_blur_sigma_px": round(GAUSSIAN_BLUR_SIGMA_PX_1024[lv["gaussian_blur"]] * scale, 6),
        "shot_noise_full_well_e": None if not np.isfinite(full_well) else float(full_well),
        "gaussian_noise_sigma": GAUSSIAN_NOISE_SIGMA[lv["gaussian_noise"]],
        "noise_seed": int(rng.integers(0, 2**63)),
    }


def apply_corruption(gray_u8: np.ndarray, params: dict) -> np.ndarray:
    """Corrupt a clean 8-bit image with `params` (from draw_corruption, or sensor.draw_sensor when
    params['model'] == 'sensor': the space camera). (H, W) uint8 -> (H, W) uint8.

    Order, as light meets the sensor: exposure gain, motion blur, optics blur, then shot noise (Poisson,
    in its Gaussian form with variance = signal / full well) and read noise, then rounding to 8 bits.
    """
    if params.get("model") == "sensor":
        return apply_sensor(gray_u8, params)
    lv = params["levels"]
    if all(v == "none" for v in lv.values()):
        return gray_u8
    img = gray_u8.astype(np.float32)
    if params["exposure_gain"] != 1.0:
        img *= np.float32(params["exposure_gain"])
    kern = None
    if params["motion_blur_length_px"] > 0:
        kern = motion_kernel(params["motion_blur_length_px"], params["motion_blur_angle_deg"])
    sigma = params["gaussian_blur_sigma_px"]
    if kern is not None or sigma > 0:
        # Blur only where the image is not black: the box of its non-zero pixels grown by the kernels' reach.
        # Outside it the blurred image is 0 as well, so the result equals blurring the whole frame.
        box = content_box(gray_u8, paper_blur_reach_px(params))
        if box is not None:
            y0, y1, x0, x1 = box
            crop = img[y0:y1, x0:x1]
            if kern is not None:
                crop = cv2.filter2D(crop, -1, kern, borderType=cv2.BORDER_REFLECT)
            if sigma > 0:
                crop = cv2.GaussianBlur(crop, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
            img[y0:y1, x0:x1] = crop
    var = np.float32(params["gaussian_noise_sigma"] ** 2)
    full_well = params["shot_noise_full_well_e"]
    if full_well is not None or var > 0:
        rng = np.random.default_rng(params["noise_seed"])
        noise = standard_normal_fast(rng, img.shape)
        if full_well:  # per-pixel sigma: sqrt(read variance + signal x 255 / full well), in place
            std = np.maximum(img, np.float32(0.0))
            std *= np.float32(255.0 / full_well)
            std += var
            np.sqrt(std, out=std)
            noise *= std
        else:
            noise *= np.sqrt(var)
        img += noise
    np.rint(img, out=img)
    np.clip(img, 0, 255, out=img)
    return img.astype(np.uint8)


def paper_blur_reach_px(params: dict) -> int:
    """How far (px) the 'paper' blurs carry light: the motion streak's half-size (motion_kernel: ceil(length / 2))
    plus the Gaussian's (ceil(4 sigma) + 1); 0 for a kind that is off."""
    length, sigma = params["motion_blur_length_px"], params["gaussian_blur_sigma_px"]
    return (int(np.ceil(length / 2.0)) if length > 0 else 0) + (int(np.ceil(4.0 * sigma)) + 1 if sigma > 0 else 0)


def corruption_margin_px(params: dict) -> int:
    """Clean pixels a window needs on each side for apply_corruption_window: how far the corruption carries a
    pixel's light. Space camera ('sensor'): the PSF's and the motion streak's half-sizes (sensor.optics_reach_px)
    plus the blooming's reach along a column (sensor.bloom_reach_px: a saturated pixel spills its excess charge
    that far); the blur is computed right on the window grown by the blooming reach, and the charge there is what
    can spill into the window. 'paper': the blurs' reach (paper_blur_reach_px). 0 for an uncorrupted image."""
    if params.get("model") == "sensor":
        return optics_reach_px(params) + bloom_reach_px(params["blooming_decay_px"])
    if all(v == "none" for v in params["levels"].values()):
        return 0
    return paper_blur_reach_px(params)


def apply_corruption_window(clean_u8: np.ndarray, window_px: tuple[int, int, int], resolution_px: int,
                            params: dict) -> np.ndarray:
    """apply_corruption(full_clean, params)[y0:y0 + side, x0:x0 + side] in distribution, from the window
    (x0, y0, side) px of the square frame of resolution_px alone (the closed loop's region of interest).

    clean_u8: (side + 2 m, side + 2 m) uint8, m = corruption_margin_px(params): the clean render of the window
    grown by m px on each side, 0 outside the image (SceneRenderer.render_window(view, (x0 - m, y0 - m,
    side + 2 m)).gray_u8). params: the full frame's, from draw_corruption_params, taken whole: nothing in them
    is computed from the image's pixels (exposure, white level, full well, noise levels and ADC are drawn from
    the configured ranges, the motion streak from the true pose; neither camera model has an auto-gain). What
    depends on a pixel's place is taken from the full frame at the window's offset: the vignetting (cos^n of
    the pixel's ray in the full frame) and the PRNU gain map (the camera's, at its full-frame pixels). Blooming
    from bright pixels outside the window reaches it from within the margin only (the spill's support is
    sensor.bloom_reach_px), and the margin's own irradiance is blurred from clean pixels within the margin.
    The chain runs on the grown window's part inside the image (its edges at the image's edges are the frame's
    own, as in apply_corruption); the noise is drawn from params' noise_seed (other draws than the full frame's:
    the same distribution, not the same pixels). Returns (side, side) uint8, 0 outside the image.
    """
    x0, y0, side = (int(v) for v in window_px)
    m, n = corruption_margin_px(params), int(resolution_px)
    if clean_u8.shape != (side + 2 * m, side + 2 * m):
        raise ValueError(f"clean window of shape {clean_u8.shape}: expected ({side + 2 * m}, {side + 2 * m}), the "
                         f"window side {side} px grown by corruption_margin_px = {m} px on each side")
    out = np.zeros((side, side), dtype=np.uint8)
    gy0, gx0, gy1, gx1 = max(y0 - m, 0), max(x0 - m, 0), min(y0 + side + m, n), min(x0 + side + m, n)
    wy0, wx0, wy1, wx1 = max(y0, 0), max(x0, 0), min(y0 + side, n), min(x0 + side, n)
    if wy1 <= wy0 or wx1 <= wx0:  # the window misses the image
        return out
    sub = np.ascontiguousarray(clean_u8[gy0 - y0 + m : gy1 - y0 + m, gx0 - x0 + m : gx1 - x0 + m])
    if params.get("model") == "sensor":
        img = apply_sensor(sub, params, (gy0, gx0), (n, n))
    else:  # the paper kinds do not depend on a pixel's place
        img = apply_corruption(sub, params)
    out[wy0 - y0 : wy1 - y0, wx0 - x0 : wx1 - x0] = img[wy0 - gy0 : wy1 - gy0, wx0 - gx0 : wx1 - gx0]
    return out
