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
from envisat_pose.datagen.sensor import apply_sensor

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
        reach = (kern.shape[0] // 2 if kern is not None else 0) + (int(np.ceil(4.0 * sigma)) + 1 if sigma > 0 else 0)
        box = content_box(gray_u8, reach)
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
