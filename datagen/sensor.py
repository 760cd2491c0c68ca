"""A space camera: the clean render as scene irradiance through optics, motion and a CCD/CMOS sensor to 8 bits.

The clean 8-bit render is read as irradiance relative to white (grey 255 = 1). The chain, in the order light
meets the camera:

1. vignetting: irradiance x cos^n(theta), theta the angle off the optical axis (n = 4: the natural law);
2. optics point-spread function: a Gaussian (sigma, px) or the Airy pattern of a circular aperture
   (first dark ring at 1.22 lambda N / pixel pitch, px), normalised to integrate to 1;
3. motion blur: a linear streak of the target's image velocity (from the true relative rate) x exposure;
4. photo-electrons: irradiance x white_e (the electrons a white pixel collects in the exposure = flux x
   exposure) x the camera's fixed-pattern gain (PRNU: 1 + prnu_sigma N(0, 1), seeded per camera), plus the
   dark current x exposure;
5. shot noise: Poisson in electrons (variance = mean); exact below 100 e-, its Gaussian limit above;
6. saturation and blooming: charge above the full well spills along the column (exponential profile of
   blooming_decay_px, charge conserved while the neighbours have room), then everything clips at full well;
7. read noise: Gaussian, electrons;
8. ADC: adc_bits bits over the full well (gain = full_well / (2^bits - 1) e-/DN), rounded and clipped, then
   shown as 8 bits (DN x 255 / (2^bits - 1), rounded);
9. response: the 8 bits stored linear (the default) or encoded, by the sRGB curve or a gamma (the label's
   `response`, envisat_pose/camera_response.py: an 8-bit lookup table, as a camera's JPEG or a renderer's PNG).

Every parameter is in the label's `corruption`; the noise comes from its `noise_seed` and the PRNU pattern
from its `camera_seed`, so `apply_sensor(clean, params)` is a pure function of its inputs.

Where the work goes (bench/sensor_speed.py): steps 1-3 only in the box around the non-black pixels; steps 4-8
pixel by pixel only in that box grown by the blooming reach. Every other pixel receives no light, so its 8-bit
value is an independent draw from one distribution known exactly (dark_pixel_pmf: the dark charge's Poisson,
read noise, ADC, display), taken by table lookup (sample_discrete); so are the box's unlit pixels' electrons.
Same distribution as running the chain on every pixel, ~7x faster on the closed loop's frames.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from envisat_pose.camera_response import parse_response
from envisat_pose.datagen.image_kernels import content_box, motion_kernel, standard_normal_fast

POISSON_EXACT_BELOW_E = 100.0  # exact Poisson draws below this mean; N(mean, mean) above (skewness < 0.1)
AIRY_FIRST_ZERO_X = 3.8317059702075125  # first zero of J1: the Airy pattern's first dark ring


# ---------------------------------------------------------------------------------------------------------
# Pieces with closed forms


def vignetting_factor(shape: tuple[int, int], f_px: float, cos_power: float,
                      box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """cos^n(theta) per pixel, theta the angle of the pixel's ray off the optical axis (principal point at
    the image centre, OpenCV convention). (H, W) float32; with box (y0, y1, x0, x1), only that window of it.
    Computed as exp(n log cos theta) from the camera's cached log cos theta map (float32)."""
    h, w = shape
    y0, y1, x0, x1 = box if box is not None else (0, h, 0, w)
    out = _log_cos_map(int(h), int(w), float(f_px))[y0:y1, x0:x1] * np.float32(cos_power)
    return np.exp(out, out=out)


@functools.lru_cache(maxsize=4)
def _log_cos_map(h: int, w: int, f_px: float) -> np.ndarray:
    """log cos theta of every pixel's ray, computed in float64 once per camera. (h, w) float32, read-only."""
    dv2 = (np.arange(h, dtype=np.float64) - (h - 1) / 2.0) ** 2
    du2 = (np.arange(w, dtype=np.float64) - (w - 1) / 2.0) ** 2
    out = (-0.5 * np.log1p((dv2[:, None] + du2[None, :]) / f_px**2)).astype(np.float32)
    out.setflags(write=False)
    return out


def gaussian_psf(sigma_px: float) -> np.ndarray:
    """A Gaussian PSF integrated over each pixel (4 x 4 sub-samples), normalised to sum 1. (k, k) float32."""
    half = int(math.ceil(4.0 * sigma_px)) + 1
    return _radial_kernel(half, lambda r: np.exp(-0.5 * (r / sigma_px) ** 2))


def airy_profile(r_px: np.ndarray, first_zero_px: float) -> np.ndarray:
    """Airy intensity [2 J1(x) / x]^2 at radius r (px), x = 3.8317 r / first_zero_px; 1 at the centre."""
    from scipy.special import j1

    x = AIRY_FIRST_ZERO_X * np.asarray(r_px, dtype=float) / first_zero_px
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (2.0 * j1(x) / x) ** 2
    return np.where(x == 0, 1.0, out)


def airy_psf(first_zero_px: float) -> np.ndarray:
    """The Airy PSF out to its third dark ring, integrated over pixels, normalised to sum 1. (k, k) float32."""
    half = int(math.ceil(3.3 * first_zero_px)) + 1
    return _radial_kernel(half, lambda r: airy_profile(r, first_zero_px) * (r <= 3.3 * first_zero_px))


def _radial_kernel(half: int, profile) -> np.ndarray:
    k = 2 * half + 1
    sub = (np.arange(4) + 0.5) / 4.0 - 0.5  # sub-pixel offsets
    c = np.arange(k) - half
    xs = (c[:, None] + sub[None, :]).ravel()
    r = np.hypot(xs[None, :], xs[:, None])
    fine = profile(r)
    kern = fine.reshape(k, 4, k, 4).sum(axis=(1, 3))
    if not kern.sum() > 0:  # a PSF so much smaller than a pixel that no sub-sample meets it: all in the centre
        kern = np.zeros((k, k))
        kern[half, half] = 1.0
    return (kern / kern.sum()).astype(np.float32)


# the widest field of view a camera images: |x / z| and |y / z| up to 4 (76 deg off the axis; no space camera's
# half field of view comes near it), so only points no camera sees are left out of the image motion
MAX_TAN_FROM_AXIS = 4.0


def image_velocity_px_s(points_T_m: np.ndarray, R_K_from_T: np.ndarray, t_K_m: np.ndarray, w_K_rad_s: np.ndarray,
                        v_K_m_s: np.ndarray, f_px: float) -> tuple[float, float]:
    """The target's image motion as one streak: (speed px/s, angle deg) of the principal axis of the image
    velocities of points_T_m (P, 3), for a target turning at w_K about its centre t_K and moving at v_K, all
    in the camera frame K. Speed: the RMS velocity along that axis (a rotation about the boresight, whose
    velocities cancel on average, still blurs). Only points the camera can image count: in front of it and within
    MAX_TAN_FROM_AXIS of its axis (a point near the camera's plane, such as a solar-array corner beside a near
    camera, would otherwise divide by its tiny depth: a 123953 px streak was once asked for at 20 m). (0, 0) when
    none is."""
    p = t_K_m + points_T_m @ R_K_from_T.T  # (P, 3) in K
    pdot = v_K_m_s + np.cross(w_K_rad_s, p - t_K_m)
    z_all = p[:, 2]
    seen = (z_all > 0.0) & (np.abs(p[:, :2]).max(axis=1) <= MAX_TAN_FROM_AXIS * np.maximum(z_all, 0.0))
    if not seen.any():
        return 0.0, 0.0
    p, pdot = p[seen], pdot[seen]
    z = p[:, 2:3]
    vel = f_px * (pdot[:, :2] / z - p[:, :2] * pdot[:, 2:3] / z**2)  # d/dt of f x / z, f y / z
    m = vel.T @ vel / len(vel)
    evals, evecs = np.linalg.eigh(m)
    d = evecs[:, 1]
    return float(math.sqrt(max(evals[1], 0.0))), float(math.degrees(math.atan2(d[1], d[0])) % 180.0)


@functools.lru_cache(maxsize=4)
def prnu_gain(camera_seed: int, shape: tuple[int, int], prnu_sigma: float) -> np.ndarray:
    """The camera's fixed pixel gain map 1 + prnu_sigma N(0, 1), seeded by camera_seed alone. (H, W) float32."""
    rng = np.random.default_rng(np.random.SeedSequence(camera_seed, spawn_key=(0x5052,)))
    g = 1.0 + prnu_sigma * rng.standard_normal(shape, dtype=np.float32)
    g.setflags(write=False)
    return g


def shot_noise_e(mean_e: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Photon (and dark-current) shot noise: a draw with variance = mean, electrons. Exact Poisson where the
    mean is below POISSON_EXACT_BELOW_E, the Gaussian N(mean, mean) above. (shape) float32."""
    mean_e = np.asarray(mean_e, dtype=np.float32)
    out = np.empty(mean_e.shape, dtype=np.float32)
    low = mean_e < POISSON_EXACT_BELOW_E
    out[low] = rng.poisson(mean_e[low])
    hi = ~low
    n_hi = int(hi.sum())
    if n_hi:
        lam = mean_e[hi]
        out[hi] = lam + np.sqrt(lam) * standard_normal_fast(rng, (n_hi,))
    return out


def bloom(charge_e: np.ndarray, full_well_e: float, decay_px: float) -> np.ndarray:
    """Blooming: the charge above full well spreads along each column (rows: axis 0) with the profile
    exp(-|d| / decay_px) / Z over d != 0 (sum 1), is added to the neighbours, and the result clips at the full
    well. Charge is conserved while the neighbours stay below full well. (H, W) float32."""
    excess = np.maximum(charge_e - np.float32(full_well_e), np.float32(0.0))
    out = np.minimum(charge_e, np.float32(full_well_e))
    if not excess.any():
        return out
    half = bloom_reach_px(decay_px)
    d = np.arange(-half, half + 1)
    prof = np.where(d == 0, 0.0, np.exp(-np.abs(d) / decay_px))
    kern = (prof / prof.sum()).astype(np.float32).reshape(-1, 1)
    rows = np.flatnonzero(excess.any(axis=1))
    cols = np.flatnonzero(excess.any(axis=0))
    y0, y1 = max(0, rows[0] - half), min(out.shape[0], rows[-1] + half + 1)
    x0, x1 = cols[0], cols[-1] + 1
    spill = cv2.filter2D(excess[y0:y1, x0:x1], -1, kern[::-1], borderType=cv2.BORDER_CONSTANT)
    out[y0:y1, x0:x1] = np.minimum(out[y0:y1, x0:x1] + spill, np.float32(full_well_e))
    return out


def bloom_reach_px(decay_px: float) -> int:
    """How far (px, along a column) bloom spills a saturated pixel's excess charge: ceil(6 decay_px), at least 1."""
    return max(1, int(math.ceil(6.0 * decay_px)))


def adc_to_u8(charge_e: np.ndarray, full_well_e: float, adc_bits: int) -> np.ndarray:
    """ADC: DN = round(e- / gain), gain = full_well / (2^bits - 1), clipped to [0, 2^bits - 1]; then 8-bit
    display DN x 255 / (2^bits - 1), rounded. (H, W) uint8."""
    top = float(2**adc_bits - 1)
    dn = np.rint(charge_e * np.float32(top / full_well_e))
    np.clip(dn, 0.0, top, out=dn)
    if adc_bits != 8:
        dn = np.rint(dn * np.float32(255.0 / top))
    return dn.astype(np.uint8)


# ---------------------------------------------------------------------------------------------------------
# Drawing the parameters of one image, applying them


def draw_sensor(cfg: dict, resolution_px: int, f_px: float, speed_px_s: float, angle_deg: float,
                rng: np.random.Generator) -> dict:
    """Concrete camera parameters of one image (plain JSON data) from the [corruption.sensor] ranges (cfg,
    as to_dict gives it), the image's true motion (speed px/s, angle deg) and its Generator."""

    def u(name):
        lo, hi = cfg[name]
        return float(rng.uniform(lo, hi))

    exposure_s = u("exposure_s")
    full_well = u("full_well_e")
    white_e = u("white_fill") * full_well
    kind = cfg["psf"] if cfg["psf"] != "mixed" else ("gaussian", "airy")[int(rng.integers(0, 2))]
    pitch_m = cfg["pixel_pitch_m_1024"] * 1024.0 / resolution_px  # the same optics at another resolution
    if kind == "gaussian":
        psf = {"kind": "gaussian", "sigma_px": round(u("psf_sigma_px_1024") * resolution_px / 1024.0, 6)}
    else:
        n_f = u("f_number")
        lam = cfg["wavelength_m"]
        psf = {"kind": "airy", "f_number": round(n_f, 6), "wavelength_m": lam, "pixel_pitch_m": pitch_m,
               "first_zero_px": round(1.2196698912665045 * lam * n_f / pitch_m, 6)}
    bits = int(cfg["adc_bits"][int(rng.integers(0, len(cfg["adc_bits"])))])
    return {
        "model": "sensor",
        "exposure_s": round(exposure_s, 9),
        "full_well_e": round(full_well, 3),
        "white_e": round(white_e, 3),
        "photon_flux_e_per_s_at_white": round(white_e / exposure_s, 3),
        "read_noise_e": round(u("read_noise_e"), 6),
        "dark_current_e_per_s": round(u("dark_current_e_per_s"), 6),
        "prnu_sigma": cfg["prnu_sigma"],
        "camera_seed": cfg["camera_seed"],
        "adc_bits": bits,
        "blooming_decay_px": round(u("blooming_decay_px"), 6),
        "psf": psf,
        "image_speed_px_s": round(speed_px_s, 6),
        "motion_blur_length_px": round(speed_px_s * exposure_s, 6),
        "motion_blur_angle_deg": round(angle_deg, 6),
        "vignetting_cos_power": round(u("vignetting_cos_power"), 6),
        "f_px": f_px,
        "noise_seed": int(rng.integers(0, 2**63)),
    } | ({} if cfg.get("response", "linear") == "linear" else {"response": cfg["response"]})


def gaussian_psf_1d(sigma_px: float) -> np.ndarray:
    """The separable factor of gaussian_psf: gaussian_psf(s) = outer(g, g) with g = gaussian_psf_1d(s) (the
    Gaussian and its 4 x 4 pixel sub-samples both factor in x and y). (k,) float32, sum 1."""
    half = int(math.ceil(4.0 * sigma_px)) + 1
    sub = (np.arange(4) + 0.5) / 4.0 - 0.5
    x = (np.arange(2 * half + 1) - half)[:, None] + sub[None, :]
    g = np.exp(-0.5 * (x / sigma_px) ** 2).sum(axis=1)
    return (g / g.sum()).astype(np.float32)


def optics_reach_px(p: dict) -> int:
    """How far (px) steps 2-3 carry light: the half-size of the PSF (Gaussian: ceil(4 sigma) + 1; Airy: to its
    third dark ring, airy_psf) plus that of the motion streak (motion_kernel: ceil(length / 2), when over 0.05 px)."""
    psf = p["psf"]
    half = (int(math.ceil(4.0 * psf["sigma_px"])) + 1 if psf["kind"] == "gaussian"
            else int(math.ceil(3.3 * psf["first_zero_px"])) + 1)
    length = p["motion_blur_length_px"]
    return half + (int(np.ceil(length / 2.0)) if length > 0.05 else 0)


def optics_box(gray_u8: np.ndarray, p: dict, origin_px: tuple[int, int] = (0, 0),
               frame_shape: tuple[int, int] | None = None
               ) -> tuple[np.ndarray | None, tuple[int, int, int, int] | None]:
    """Steps 1-3 (irradiance, white = 1, after vignetting, the PSF and the motion streak) on the box around
    the non-black pixels grown by twice the filters' reach, the only place it is not 0: (crop (h, w) float32,
    box (y0, y1, x0, x1) in gray_u8's pixels), or (None, None) for a black image. A Gaussian PSF is applied as
    its two separable factors (the same kernel). gray_u8 may be a window of a frame of frame_shape (default: its
    own shape) whose top-left pixel is the frame's (row, col) origin_px: the vignetting is the frame's there."""
    gauss = p["psf"]["kind"] == "gaussian"
    psf = gaussian_psf_1d(p["psf"]["sigma_px"]) if gauss else airy_psf(p["psf"]["first_zero_px"])
    kern = motion_kernel(p["motion_blur_length_px"], p["motion_blur_angle_deg"]) if p["motion_blur_length_px"] > 0.05 else None
    box = content_box(gray_u8, optics_reach_px(p))
    if box is None:
        return None, None
    y0, y1, x0, x1 = box
    crop = gray_u8[y0:y1, x0:x1].astype(np.float32) * np.float32(1.0 / 255.0)
    if p["vignetting_cos_power"] > 0:
        oy, ox = origin_px
        crop *= vignetting_factor(frame_shape or gray_u8.shape, p["f_px"], p["vignetting_cos_power"],
                                  (y0 + oy, y1 + oy, x0 + ox, x1 + ox))
    if gauss:
        crop = cv2.sepFilter2D(crop, -1, psf, psf, borderType=cv2.BORDER_REFLECT)
    else:
        crop = cv2.filter2D(crop, -1, psf, borderType=cv2.BORDER_REFLECT)
    if kern is not None:
        crop = cv2.filter2D(crop, -1, kern, borderType=cv2.BORDER_REFLECT)
    np.maximum(crop, 0.0, out=crop)  # filter2D's DFT path (kernels of 11 px and more) leaves -1e-16 where it is dark
    return crop, box


def optics(gray_u8: np.ndarray, p: dict, origin_px: tuple[int, int] = (0, 0),
           frame_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Steps 1-3 on the whole of gray_u8 (optics_box, zeros around it; a window as optics_box says). (H, W) float32."""
    img = np.zeros(gray_u8.shape, dtype=np.float32)
    crop, box = optics_box(gray_u8, p, origin_px, frame_shape)
    if box is not None:
        y0, y1, x0, x1 = box
        img[y0:y1, x0:x1] = crop
    return img


# ---------------------------------------------------------------------------------------------------------
# Exact sampling of the unlit pixels: one discrete distribution, drawn by table lookup


def sample_discrete(pmf: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n indices drawn from the probabilities pmf (K <= 256,) by inverse transform: the uniform U = (B + V) / 256
    with B a random byte and V a uniform of 2^-32 resolution (drawn only where needed). A byte whose interval
    [B, B + 1) / 256 holds no step of the cdf fixes the index by table lookup (cv2.LUT); the rest (a share
    below K / 256, in practice a few per cent) are found in the cdf with V. Exact to 2^-40. (n,) uint8."""
    pmf = np.asarray(pmf, dtype=np.float64)
    if len(pmf) > 256:
        raise ValueError(f"sample_discrete takes at most 256 outcomes, got {len(pmf)}")
    cdf = np.cumsum(pmf)
    cdf /= cdf[-1]
    b = np.arange(256)
    first = np.minimum(np.searchsorted(cdf, b / 256.0, side="right"), len(pmf) - 1)
    last = np.minimum(np.searchsorted(cdf, (b + 1) / 256.0, side="left"), len(pmf) - 1)
    value_lut = first.astype(np.uint8)
    exact_lut = (first == last).astype(np.uint8)
    byte = np.frombuffer(rng.bytes(n), dtype=np.uint8)
    out = cv2.LUT(byte, value_lut).ravel()
    amb = np.flatnonzero(cv2.LUT(byte, exact_lut).ravel() == 0)
    if amb.size:
        v = rng.integers(0, 2**32, size=amb.size, dtype=np.uint64).astype(np.float64) * 2.0**-32
        u = (byte[amb].astype(np.float64) + v) / 256.0
        out[amb] = np.minimum(np.searchsorted(cdf, u, side="right"), len(pmf) - 1)
    return out


def poisson_pmf(lam: float, kmax: int) -> np.ndarray:
    """Poisson probabilities of 0 .. kmax events at mean lam. (kmax + 1,) float64."""
    from scipy.special import gammaln

    k = np.arange(kmax + 1, dtype=np.float64)
    if lam <= 0:
        return (k == 0).astype(np.float64)
    return np.exp(k * math.log(lam) - lam - gammaln(k + 1.0))


def _poisson_support(lam: float) -> int:
    return int(math.ceil(lam + 12.0 * math.sqrt(lam) + 20.0))  # tail beyond it below 1e-25


def dark_pixel_pmf(p: dict) -> np.ndarray | None:
    """The exact distribution of the 8-bit value of a pixel that receives no light (steps 4-8 with only the
    dark current): shot noise of the dark charge (Poisson below POISSON_EXACT_BELOW_E, its Gaussian above),
    read noise, the ADC and the 8-bit display, as probabilities of the values 0..255. (256,) float64; None
    when such a pixel could reach the full well (blooming would couple it to its neighbours)."""
    from scipy.special import ndtr

    lam = float(np.float32(p["dark_current_e_per_s"] * p["exposure_s"]))
    sig = float(p["read_noise_e"])
    fw = float(p["full_well_e"])
    if lam + 12.0 * math.sqrt(lam) + 20.0 >= fw:
        return None
    top = 2 ** int(p["adc_bits"]) - 1
    s = np.float32(top / fw)  # DN per electron, as adc_to_u8 computes it
    if lam < POISSON_EXACT_BELOW_E:
        k = np.arange(_poisson_support(lam) + 1)
        w = poisson_pmf(lam, len(k) - 1)
        if sig > 0:  # charge = k + N(0, sig^2): DN = rint(charge s) falls in bins of charge
            d = np.arange(0, min(top, int(math.ceil((k[-1] + 10 * sig) * float(s))) + 2) + 1)
            lo = np.where(d == 0, -np.inf, (d - 0.5) / float(s))
            up = np.where(d == top, np.inf, (d + 0.5) / float(s))
            p_dn = ((ndtr((up[None, :] - k[:, None]) / sig) - ndtr((lo[None, :] - k[:, None]) / sig))
                    * w[:, None]).sum(axis=0)
        else:  # whole electrons, converted exactly as adc_to_u8 does
            dn = np.clip(np.rint(k.astype(np.float32) * s), 0, top).astype(np.int64)
            d = np.arange(dn.max() + 1)
            p_dn = np.bincount(dn, weights=w, minlength=len(d))
    else:  # the Gaussian limit: charge ~ N(lam, lam + sig^2)
        sd = math.sqrt(lam + sig * sig)
        d = np.arange(0, min(top, int(math.ceil((lam + 10 * sd) * float(s))) + 2) + 1)
        lo = np.where(d == 0, -np.inf, (d - 0.5) / float(s))
        up = np.where(d == top, np.inf, (d + 0.5) / float(s))
        p_dn = ndtr((up - lam) / sd) - ndtr((lo - lam) / sd)
    u8 = d if top == 255 else np.rint(d.astype(np.float32) * np.float32(255.0 / top)).astype(np.int64)
    return np.bincount(np.clip(u8, 0, 255), weights=p_dn[: len(d)], minlength=256)[:256]


def apply_sensor(gray_u8: np.ndarray, p: dict, origin_px: tuple[int, int] = (0, 0),
                 frame_shape: tuple[int, int] | None = None) -> np.ndarray:
    """The whole chain (module docstring) on a clean render. (H, W) uint8 -> (H, W) uint8.

    Work goes where the light is: the pixels outside the optics box (grown along the columns by the blooming
    reach) receive no light, so their 8-bit values are independent draws from one exact distribution
    (dark_pixel_pmf), taken by table lookup; the box runs the chain pixel by pixel (apply_sensor_box). The
    noise comes from noise_seed: the box's draws first, then the dark pixels'. gray_u8 may be a window of a
    frame of frame_shape (default: its own shape) at the frame's (row, col) origin_px: the vignetting and PRNU
    maps are the frame's there, and the window's edges act as the image's (corrupt.apply_corruption_window
    grows the window by the reach of the blur and blooming, then cuts that margin off)."""
    h, w = gray_u8.shape
    oy, ox = origin_px
    rng = np.random.default_rng(p["noise_seed"])
    crop, box = optics_box(gray_u8, p, origin_px, frame_shape)
    pmf = dark_pixel_pmf(p)
    if pmf is None:  # the dark charge alone may bloom: the whole frame pixel by pixel
        crop, box = optics(gray_u8, p, origin_px, frame_shape), (0, h, 0, w)
    out = np.empty((h, w), dtype=np.uint8)
    if box is not None:
        y0, y1, x0, x1 = box
        if pmf is not None:  # room for the spill of saturated charge along the columns
            grow = bloom_reach_px(p["blooming_decay_px"])
            g0, g1 = max(0, y0 - grow), min(h, y1 + grow)
            irr = np.zeros((g1 - g0, x1 - x0), dtype=np.float32)
            irr[y0 - g0 : y1 - g0] = crop
            y0, y1 = g0, g1
        else:
            irr = crop
        frame_box = (y0 + oy, y1 + oy, x0 + ox, x1 + ox)  # the window's box in the frame (its PRNU)
        out[y0:y1, x0:x1] = apply_sensor_box(irr, frame_box, frame_shape or (h, w), p, rng)
    if pmf is not None:  # the unlit rest: drawn for the whole frame (cheaper than picking pixels), box kept
        keep = out[y0:y1, x0:x1].copy() if box is not None else None
        out = sample_discrete(pmf, h * w, rng).reshape(h, w)
        if keep is not None:
            out[y0:y1, x0:x1] = keep
    return encode_response(out, p)


def encode_response(out_u8: np.ndarray, p: dict) -> np.ndarray:
    """Step 9: the 8-bit linear output stored by the label's response (absent or 'linear': as it is)."""
    if p.get("response", "linear") == "linear":
        return out_u8
    return cv2.LUT(out_u8, parse_response(p["response"], "response").encode_lut())


def apply_sensor_box(irr: np.ndarray, box: tuple[int, int, int, int], shape: tuple[int, int], p: dict,
                     rng: np.random.Generator) -> np.ndarray:
    """Steps 4-8 pixel by pixel on the irradiance irr (h, w) of the window box (y0, y1, x0, x1) of an image of
    `shape` (the window of the camera's PRNU map): electrons, shot noise, blooming, read noise, ADC.
    (h, w) uint8."""
    y0, y1, x0, x1 = box
    gain = prnu_gain(p["camera_seed"], shape, p["prnu_sigma"])[y0:y1, x0:x1]
    lam_dark = np.float32(p["dark_current_e_per_s"] * p["exposure_s"])
    mean_e = irr * np.float32(p["white_e"])
    mean_e *= gain
    mean_e += lam_dark
    unlit = irr == 0  # mean exactly lam_dark: one Poisson distribution, drawn by table lookup
    if lam_dark < POISSON_EXACT_BELOW_E and unlit.any():
        charge = np.empty_like(mean_e)
        kmax = _poisson_support(float(lam_dark))
        charge[unlit] = sample_discrete(poisson_pmf(float(lam_dark), kmax), int(unlit.sum()), rng)
        lit = ~unlit
        charge[lit] = shot_noise_e(mean_e[lit], rng)
    else:
        charge = shot_noise_e(mean_e, rng)
    charge = bloom(charge, p["full_well_e"], p["blooming_decay_px"])
    if p["read_noise_e"] > 0:
        noise = standard_normal_fast(rng, charge.shape)
        noise *= np.float32(p["read_noise_e"])
        charge += noise
    return adc_to_u8(charge, p["full_well_e"], p["adc_bits"])
