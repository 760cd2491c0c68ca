"""The image factory: one validated config, one root seed, shards of rendered, labelled, corrupted images.

A shard is the unit of work: `generate_shard(cfg, index, out_dir)` renders samples from the shard's own
seeds (`SeedSequence(root, spawn_key=(shard,))`, then `(shard, i)` per sample) and publishes one tar
atomically. Where it runs (this process, a process pool, a Dask cluster) changes nothing in its bytes.
`run_generate` runs the dataset as the core runner's resumable job (`dataset_job`): it skips the finished shards
(their sha256 verified), runs the rest and keeps `manifest.json` current after each shard, so a killed run
resumes where it stopped.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import json
import math
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

from envisat_pose.attitude import mrp_to_dcm, quat_to_mrp, quat_to_rotmat
from envisat_pose.datagen.labels import DEPTH_MAX_CODE
from envisat_pose.datagen.clearance import (TargetBoxes, clearance_m, farthest_depth_m, project_target_boxes,
                                            project_znear_m)
from envisat_pose.config import ConfigError, check, from_dict, to_dict
from envisat_pose.geometry import load_camera
from envisat_pose.runner import ResumableJob, RunnerConfig, check_out_dir, cpu_share
from envisat_pose.state import MRP, POS, RATE, VEL

Severity = Literal["none", "low", "medium", "high", "mixed"]
MANIFEST_FORMAT = "envisat-pose shards v1"
# Camera mount on the chaser, from camera chaser_cam of models/envisat.xml (boresight +y_C, image up +x_C).
# Rows are the K axes (x right, y down, z boresight) in C.
R_K_FROM_C = load_camera().R_K_from_C
# generate_shard's helper threads (same bytes either way): one draws the views, one finishes sample k (the
# passes' pixels, labels, corruption, PNG encoding, tar) while the calling thread renders sample k + 1, one makes
# the Earth textures from the start. They pay only where the worker has a core its rasterizer leaves idle
# (spare_core); where every core is busy they measured neutral to a few % slower. None: run_generate decides by
# spare_core; True/False: forced (benchmarks, tests).
FINISH_BESIDE_RENDER: bool | None = None
# While the helper threads run, the interpreter's GIL switch interval (s). The render thread gives up the GIL in
# every MuJoCo/GL call and must win it back from the helper; at Python's default 5 ms each call can wait that
# long (measured at 1024 px: a busy Python thread beside the render doubled its time at 5 ms, none at 50 us).
GIL_SWITCH_INTERVAL_S = 5e-5
# Rendered samples that may wait for the finishing thread (each holds its read-back passes, ~4 MB at 1024 px).
FINISH_QUEUE = 2
# Random-mode datasets of at least this many images make the Earth textures on a helper thread from the start
# (SceneRenderer.prefetch_earth_textures): a long run shows every one of them anyway.
PREFETCH_EARTH_MIN_IMAGES = 32
# Random mode redraws a view whose camera is too near the target or whose near plane cuts it, at most this often.
MAX_VIEW_DRAWS = 1000


Range = tuple[float, float]


def _check_range(value: tuple, field_name: str, lo: float, hi: float) -> None:
    check(lo <= value[0] <= value[1] <= hi, field_name, list(value), f"[low, high] with {lo:g} <= low <= high <= {hi:g}")


@dataclass(frozen=True)
class SensorConfig:
    """The space camera (datagen/sensor.py): ranges [low, high] drawn per image, fixed camera properties.

    exposure_s: exposure time, s. full_well_e: full-well capacity, electrons. white_fill: the share of the full
    well a white (255) clean pixel collects in the exposure (above 1: bright foil saturates and blooms).
    read_noise_e: read noise, e- RMS. dark_current_e_per_s: dark current, e-/s per pixel. prnu_sigma: pixel
    gain non-uniformity (fixed pattern, seeded by camera_seed). adc_bits: bit depths to draw from.
    blooming_decay_px: column spill length of saturated charge. psf: 'gaussian', 'airy' or 'mixed';
    psf_sigma_px_1024: Gaussian sigma at 1024 px; f_number, wavelength_m, pixel_pitch_m_1024: the Airy
    optics. vignetting_cos_power: exponent n of cos^n (4: natural vignetting).
    """

    exposure_s: Range = (0.001, 0.02)
    full_well_e: Range = (8000.0, 30000.0)
    white_fill: Range = (0.5, 1.5)
    read_noise_e: Range = (2.0, 15.0)
    dark_current_e_per_s: Range = (10.0, 500.0)
    prnu_sigma: float = 0.01
    camera_seed: int = 0
    adc_bits: tuple[int, ...] = (8, 10, 12)
    blooming_decay_px: Range = (1.0, 6.0)
    psf: Literal["gaussian", "airy", "mixed"] = "mixed"
    psf_sigma_px_1024: Range = (0.3, 1.2)
    f_number: Range = (4.0, 11.0)
    wavelength_m: float = 550e-9
    pixel_pitch_m_1024: float = 5.5e-6
    vignetting_cos_power: Range = (0.0, 4.0)

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        for name, lo, hi in (("exposure_s", 1e-6, 10.0), ("full_well_e", 100.0, 1e7), ("white_fill", 0.0, 100.0),
                             ("read_noise_e", 0.0, 1e4), ("dark_current_e_per_s", 0.0, 1e6),
                             ("blooming_decay_px", 0.1, 100.0), ("psf_sigma_px_1024", 0.05, 20.0),
                             ("f_number", 0.5, 64.0), ("vignetting_cos_power", 0.0, 8.0)):
            _check_range(getattr(self, name), f"{p}{name}", lo, hi)
        check(0.0 <= self.prnu_sigma <= 0.2, f"{p}prnu_sigma", self.prnu_sigma, "a gain spread in [0, 0.2]")
        check(0 <= self.camera_seed < 2**63, f"{p}camera_seed", self.camera_seed, "a non-negative integer seed")
        check(len(self.adc_bits) >= 1 and all(8 <= b <= 16 for b in self.adc_bits), f"{p}adc_bits",
              list(self.adc_bits), "one or more bit depths in [8, 16]")
        check(100e-9 <= self.wavelength_m <= 2e-6, f"{p}wavelength_m", self.wavelength_m, "a wavelength in m")
        check(0.5e-6 <= self.pixel_pitch_m_1024 <= 1e-4, f"{p}pixel_pitch_m_1024", self.pixel_pitch_m_1024,
              "a pixel pitch in m")


@dataclass(frozen=True)
class CorruptionConfig:
    """model 'sensor': the space camera (sensor table); 'paper': the paper's Gaussian noise and blur as
    severities per kind: none, low, medium, high, or mixed (a level drawn per image)."""

    model: Literal["sensor", "paper"] = "sensor"
    exposure: Severity = "mixed"
    motion_blur: Severity = "mixed"
    gaussian_blur: Severity = "mixed"
    shot_noise: Severity = "mixed"
    gaussian_noise: Severity = "mixed"
    sensor: SensorConfig = field(default_factory=SensorConfig)

    def validate(self, prefix: str = "") -> None:
        from envisat_pose.datagen.corrupt import KINDS, check_severities

        check_severities(self.model, {k: getattr(self, k) for k in KINDS}, prefix or "corruption")


@dataclass(frozen=True)
class AppearanceConfig:
    """Per-image materials within each face's covering class (datagen/appearance.py). enabled: None means on
    in random mode, off in sequence mode. texture_set_size: textures per class. texture_seed: the texture set.
    seed: the appearance draws' own seed (mixed with each sample's): another seed, other looks, same poses.
    specular, shininess, reflectance: ranges of MuJoCo's material terms; brightness: multiplier range on each
    class's base brightness. one_covering: draw every face of the main body in this one covering class (a
    target whose half-turn about x does not show by its coverings); None: each face its own class."""

    enabled: bool | None = None
    one_covering: str | None = None
    texture_set_size: int = 8
    texture_seed: int = 0
    seed: int = 0
    specular: Range = (0.2, 0.9)
    shininess: Range = (0.2, 0.9)
    reflectance: Range = (0.0, 0.1)
    brightness: Range = (0.7, 1.3)

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(1 <= self.texture_set_size <= 64, f"{p}texture_set_size", self.texture_set_size, "1 to 64 textures")
        for name in ("texture_seed", "seed"):
            check(0 <= getattr(self, name) < 2**63, f"{p}{name}", getattr(self, name), "a non-negative integer seed")
        for name in ("specular", "shininess", "reflectance"):
            _check_range(getattr(self, name), f"{p}{name}", 0.0, 1.0)
        _check_range(self.brightness, f"{p}brightness", 0.0, 3.0)
        if self.one_covering is not None:
            from envisat_pose.datagen.appearance import CLASSES

            check(self.one_covering in CLASSES, f"{p}one_covering", self.one_covering,
                  f"a covering class ({', '.join(sorted(CLASSES))})")


@dataclass(frozen=True)
class LightingConfig:
    """sun_intensity: range of the sun light's diffuse intensity (MuJoCo units; 1.2 is the MJCF's).
    earthshine: a light from the nadir side, intensity = sun x albedo x view_factor x the lit fraction of the
    Earth's disc seen from the target, (1 - sun . nadir) / 2; none in eclipse (the night side)."""

    sun_intensity: Range = (0.9, 1.6)
    earthshine: bool = True
    earth_albedo: Range = (0.25, 0.4)
    earth_view_factor: float = 0.8

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        _check_range(self.sun_intensity, f"{p}sun_intensity", 0.0, 5.0)
        _check_range(self.earth_albedo, f"{p}earth_albedo", 0.0, 1.0)
        check(0.0 <= self.earth_view_factor <= 1.0, f"{p}earth_view_factor", self.earth_view_factor, "in [0, 1]")


@dataclass(frozen=True)
class GenerateConfig:
    """What `envisat generate` makes.

    mode: 'random' (domain-randomized views) or 'sequence' (frames of a simulated truth every frame_dt_s).
    resolution_px: square image side. range_min_m/range_max_m: target range (random mode).
    max_offset_frac: target centre within this fraction of the half field of view (random mode).
    sun_dir: unit vector toward the sun, in C (random mode) or N (sequence mode); omitted: drawn from the seed.
    sun_phase_max_deg: random mode: the sun is drawn uniformly on the cap of directions within this phase angle
    of the direction from the target to the camera (0: sun behind the camera, 90: side light, 180: any), so most
    views are lit as an approach would plan them; backlit_probability: share of views whose sun is drawn from
    the whole sphere instead (backlit and silhouette views stay in the set).
    eclipse_probability: share of random-mode images in eclipse (sequence mode: Earth's cylindrical shadow).
    earth_probability: share of random-mode images that look toward the Earth and draw it behind the target
    (textured, lit by the view's sun; datagen/earth.py); sequence mode: above 0, the Earth is drawn at the
    orbit's nadir in the frames where it reaches the image. earth_orbit_radius_m: random mode: the chaser's
    orbit radius range, m (the disc's angular radius is asin(R / r)). earth_seed: the Earth texture set.
    depth_scale_m: metres per unit of the 16-bit depth PNG.
    keepout_margin_m: random mode: least distance of the camera from any part of the target, m (views closer,
    or whose near plane cuts the target, are drawn again from the same generator).
    rate_max_deg_s: random mode: the relative tumble rate is drawn uniform in [0, this] about a random axis
    (it sets the space camera's motion blur and goes into the label's x).
    appendages: draw the ASAR antenna and instrument boxes (mask value 8); None: on in random mode only.
    storage: 'corrupted' stores the corrupted image; 'clean' stores the clean render, and
    dataset.sample_image applies the label's corruption on read (the same bytes).
    """

    mode: Literal["random", "sequence"] = "random"
    num_images: int = 1000
    shard_size: int = 100
    resolution_px: int = 1024
    seed: int = 0
    range_min_m: float = 20.0
    range_max_m: float = 80.0
    max_offset_frac: float = 0.6
    sun_dir: tuple[float, float, float] | None = None
    sun_phase_max_deg: float = 100.0
    backlit_probability: float = 0.15
    eclipse_probability: float = 0.05
    earth_probability: float = 0.3
    earth_orbit_radius_m: Range = (6978.0e3, 7378.0e3)
    earth_seed: int = 0
    shadows: bool = True
    write_mask: bool = True
    write_depth: bool = True
    depth_scale_m: float = 0.002
    keepout_margin_m: float = 2.0
    scenario: str = "default"
    frame_dt_s: float = 1.0
    rate_max_deg_s: float = 5.0
    appendages: bool | None = None
    storage: Literal["clean", "corrupted"] = "corrupted"
    corruption: CorruptionConfig = field(default_factory=CorruptionConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)

    @property
    def appearance_on(self) -> bool:
        e = self.appearance.enabled
        return self.mode == "random" if e is None else e

    @property
    def appendages_on(self) -> bool:
        return self.mode == "random" if self.appendages is None else self.appendages

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.num_images >= 1, f"{p}num_images", self.num_images, "at least 1 image")
        check(self.shard_size >= 1, f"{p}shard_size", self.shard_size, "at least 1 image per shard")
        check(16 <= self.resolution_px <= 4096, f"{p}resolution_px", self.resolution_px, "a resolution in [16, 4096] px")
        check(0 <= self.seed < 2**63, f"{p}seed", self.seed, "a non-negative integer seed below 2^63")
        reach_m = project_target_boxes().reach_m
        check(self.range_min_m > reach_m / 2, f"{p}range_min_m", self.range_min_m,
              f"a range above {reach_m / 2:.1f} m (the camera must stay outside the target)")
        check(self.range_max_m >= self.range_min_m, f"{p}range_max_m", self.range_max_m,
              f"a range no shorter than range_min_m = {self.range_min_m}")
        check(0.0 <= self.max_offset_frac <= 1.0, f"{p}max_offset_frac", self.max_offset_frac, "a fraction in [0, 1]")
        check(0.0 <= self.sun_phase_max_deg <= 180.0, f"{p}sun_phase_max_deg", self.sun_phase_max_deg,
              "a phase angle in [0, 180] deg")
        check(0.0 <= self.backlit_probability <= 1.0, f"{p}backlit_probability", self.backlit_probability,
              "a probability in [0, 1]")
        if self.sun_dir is not None:
            check(np.linalg.norm(self.sun_dir) > 0, f"{p}sun_dir", list(self.sun_dir), "a non-zero vector")
        for name in ("eclipse_probability", "earth_probability"):
            value = getattr(self, name)
            check(0.0 <= value <= 1.0, f"{p}{name}", value, "a probability in [0, 1]")
        from envisat_pose.datagen.scenario import EARTH_RADIUS_M

        _check_range(self.earth_orbit_radius_m, f"{p}earth_orbit_radius_m", EARTH_RADIUS_M + 100e3, 1e8)
        check(0 <= self.earth_seed < 2**63, f"{p}earth_seed", self.earth_seed, "a non-negative integer seed")
        check(self.depth_scale_m > 0, f"{p}depth_scale_m", self.depth_scale_m, "a positive scale in m")
        if self.mode == "random":
            reach = self.range_max_m / math.cos(math.radians(30.0)) + reach_m
            check(DEPTH_MAX_CODE * self.depth_scale_m >= reach, f"{p}depth_scale_m", self.depth_scale_m,
                  f"a scale whose 16-bit range (65535 x scale) covers {reach:.1f} m, the farthest target point")
        check(self.keepout_margin_m >= 0, f"{p}keepout_margin_m", self.keepout_margin_m, "a non-negative distance in m")
        check(self.frame_dt_s > 0, f"{p}frame_dt_s", self.frame_dt_s, "a positive frame interval in s")
        check(0 <= self.rate_max_deg_s <= 90, f"{p}rate_max_deg_s", self.rate_max_deg_s, "a rate in [0, 90] deg/s")
        if self.mode == "sequence":
            from envisat_pose.datagen.scenario import scenario_dict

            scenario_dict(self.scenario)  # unknown names raise ConfigError

    @property
    def num_shards(self) -> int:
        return math.ceil(self.num_images / self.shard_size)

    def shard_count(self, index: int) -> int:
        """Number of samples in shard `index` (the last one may be short)."""
        return min(self.shard_size, self.num_images - index * self.shard_size)


def config_from_json(text: str) -> GenerateConfig:
    """A GenerateConfig from its JSON text (how tasks travel to workers: plain data, never pickles)."""
    return from_dict(GenerateConfig, json.loads(text))


def config_json(cfg: GenerateConfig) -> str:
    return json.dumps(to_dict(cfg), sort_keys=True)


# ---------------------------------------------------------------------------------------------------------
# Seeds and views


def sample_seed(root_seed: int, shard_index: int, sample_index: int) -> int:
    """The seed of sample i of a shard: SeedSequence(root).spawn(...)[shard].spawn(...)[i], as one integer.

    The label stores it; `numpy.random.default_rng(seed)` replays every draw of the sample.
    """
    ss = np.random.SeedSequence(root_seed, spawn_key=(shard_index, sample_index))
    return int(ss.generate_state(1, dtype=np.uint64)[0])


def unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def view_is_clear(rho_C_m: np.ndarray, R_C_from_T: np.ndarray, boxes: TargetBoxes, margin_m: float,
                  znear_m: float) -> bool:
    """Whether the camera (at the origin of C) keeps margin_m from every target geom and every target point
    lies beyond the near plane (z_K > znear_m: nothing clipped). rho_C_m (3,) m, R_C_from_T (3, 3)."""
    c_T = -R_C_from_T.T @ rho_C_m
    if clearance_m(c_T[None], boxes)[0][0] < margin_m:
        return False
    z_K = (R_K_FROM_C @ (rho_C_m[:, None] + R_C_from_T @ boxes.corners_T_m.T))[2]
    return bool(z_K.min() > znear_m)


def sample_cap(axis: np.ndarray, half_angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A unit vector uniform on the spherical cap of half_angle_deg around the unit vector `axis`. (3,)"""
    cos_t = rng.uniform(math.cos(math.radians(half_angle_deg)), 1.0)
    phi = rng.uniform(0.0, 2.0 * math.pi)
    a = unit(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = unit(np.cross(a, helper))
    e2 = np.cross(a, e1)
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    return cos_t * a + sin_t * (math.cos(phi) * e1 + math.sin(phi) * e2)


def sample_random_view(cfg: GenerateConfig, fovy_deg: float, rng: np.random.Generator,
                       znear_m: float | None = None, boxes: TargetBoxes | None = None) -> tuple:
    """A domain-randomized view: uniform attitude, range uniform in [range_min_m, range_max_m], target centre
    off the boresight within max_offset_frac of the half field of view, random or configured sun, eclipse
    and Earth backdrop by their probabilities, a relative tumble rate uniform in [0, rate_max_deg_s] about a
    uniform axis (in x; the translation rate is zero).

    A pose whose camera comes within keepout_margin_m of any target geom (body, boom, array, clutter), or whose
    near plane (znear_m, m; default that of models/envisat.xml) cuts the target, is drawn again from the same
    rng: deterministic, at most MAX_VIEW_DRAWS times (then ConfigError). boxes: the target (default the
    project's).

    Returns (View, x (12,), scene dict) without a look (see with_look). In random mode C is the camera mount's
    frame; the Earth's direction is drawn independently of it, except in views with the Earth backdrop (a
    share earth_probability): there the Earth (distance, nadir toward the image, attitude, texture) comes from
    earth.draw_backdrop with a generator spawned from rng, so poses, labels and the later draws of rng are the
    same with and without the Earth.
    """
    from envisat_pose.datagen.render import View

    boxes = boxes if boxes is not None else project_target_boxes()
    znear_m = znear_m if znear_m is not None else project_znear_m()
    tan_half = math.tan(math.radians(fovy_deg) / 2.0)
    for _ in range(MAX_VIEW_DRAWS):
        q = unit(rng.standard_normal(4))
        range_m = rng.uniform(cfg.range_min_m, cfg.range_max_m)
        off = rng.uniform(-1.0, 1.0, size=2) * cfg.max_offset_frac * tan_half
        rho_C = R_K_FROM_C.T @ (range_m * unit([off[0], off[1], 1.0]))
        if view_is_clear(rho_C, quat_to_rotmat(q), boxes, cfg.keepout_margin_m, znear_m):
            break
    else:
        raise ConfigError("range_min_m", cfg.range_min_m,
                          f"ranges that allow a clear view: none of {MAX_VIEW_DRAWS} draws kept the camera "
                          f"keepout_margin_m = {cfg.keepout_margin_m:g} m from the target with all of it beyond "
                          f"the near plane ({znear_m:.2f} m)")
    if cfg.sun_dir is not None:
        sun_C = unit(cfg.sun_dir)
    else:
        backlit = rng.random() < cfg.backlit_probability
        sun_C = sample_cap(-unit(rho_C), 180.0 if backlit else cfg.sun_phase_max_deg, rng)
    eclipse = bool(rng.random() < cfg.eclipse_probability)
    earth_draw = bool(rng.random() < cfg.earth_probability)
    earth_C = unit(rng.standard_normal(3))
    w_T = unit(rng.standard_normal(3)) * math.radians(rng.uniform(0.0, cfg.rate_max_deg_s))
    view = View(rho_C, quat_to_rotmat(q), None if eclipse else sun_C, earth_C, earth_backdrop=earth_draw)
    if earth_draw:
        import dataclasses

        from envisat_pose.attitude import rotmat_to_quat
        from envisat_pose.datagen.earth import draw_backdrop

        K = load_camera().scaled(cfg.resolution_px, cfg.resolution_px).K
        nadir_K, r_m, R_K_from_E, tex = draw_backdrop(rng.spawn(1)[0], cfg.earth_orbit_radius_m, K,
                                                      cfg.resolution_px, None if eclipse else R_K_FROM_C @ sun_C)
        view = dataclasses.replace(view, earth_dir_C=R_K_FROM_C.T @ nadir_K, earth_distance_m=r_m,
                                   earth_quat_C=rotmat_to_quat(R_K_FROM_C.T @ R_K_from_E), earth_texture=tex)
    x = np.concatenate([rho_C, np.zeros(3), quat_to_mrp(q), w_T])
    scene = {"mode": "random", "sun_dir_cam": (R_K_FROM_C @ sun_C).round(9).tolist(), "eclipse": eclipse,
             "earth_backdrop": earth_draw}
    return view, x, scene


def look_rng(cfg: GenerateConfig, seed: int) -> np.random.Generator:
    """The generator of a sample's appearance and light intensities: seeded by (sample seed, appearance.seed),
    apart from the pose's, so appearance on/off or another appearance seed leaves poses and labels alone."""
    return np.random.default_rng(np.random.SeedSequence([seed, cfg.appearance.seed]))


def with_look(cfg: GenerateConfig, view, scene: dict, seed: int) -> tuple:
    """The view with its appearance (materials if appearance is on, sun intensity, Earth-shine) and clutter,
    and the scene dict with every choice needed to render it again (view_from_scene). Returns (View, scene)."""
    import dataclasses

    from envisat_pose.datagen.appearance import FACE_GEOMS, GEOM_CLASS, Look, draw_look
    from envisat_pose.datagen.render import APPENDAGE_MASK_VALUE, MASK_VALUES

    rng = look_rng(cfg, seed)
    lit = cfg.lighting
    sun_i = round(float(rng.uniform(*lit.sun_intensity)), 6)
    albedo = float(rng.uniform(*lit.earth_albedo))
    geoms = tuple(g for g in GEOM_CLASS if cfg.appendages_on or MASK_VALUES[g] != APPENDAGE_MASK_VALUE)
    a = cfg.appearance
    classes = dict(GEOM_CLASS)
    if a.one_covering is not None:
        classes.update({g: a.one_covering for g in FACE_GEOMS})
    materials = draw_look(rng, a.texture_set_size, a.specular, a.shininess, a.reflectance, a.brightness,
                          geoms, classes) if cfg.appearance_on else {}
    phase = 0.0
    if view.sun_dir_C is not None and view.earth_dir_C is not None:
        # lit fraction of the Earth's disc seen from the target: 1 with the sun behind us, 0 toward it
        phase = 0.5 * (1.0 - float(unit(view.sun_dir_C) @ unit(view.earth_dir_C)))
    earth_i = round(sun_i * albedo * lit.earth_view_factor * phase, 6) if lit.earthshine else 0.0
    look = Look(materials, sun_i, earth_i)
    view = dataclasses.replace(view, look=look, appendages=cfg.appendages_on)
    scene = dict(scene)
    scene.update({
        "appearance": cfg.appearance_on,
        "appendages": cfg.appendages_on,
        "face_classes": {g: classes[g] for g in FACE_GEOMS},
        "earthshine": {"intensity": earth_i, "earth_phase": round(phase, 6), "albedo": round(albedo, 6),
                       "dir_cam": None if view.earth_dir_C is None else (-R_K_FROM_C @ unit(view.earth_dir_C)).tolist()},
        "look": look.to_json(),
        "render": render_inputs(view),
    })
    return view, scene


def render_inputs(view) -> dict:
    """What the renderer needs of a view, exactly (floats round-trip through JSON), for the label."""
    def vec(v):
        return None if v is None else [float(c) for c in np.asarray(v, dtype=float)]

    return {"rho_C_m": vec(view.rho_C_m), "R_C_from_T": [vec(r) for r in np.asarray(view.R_C_from_T)],
            "sun_dir_C": vec(view.sun_dir_C), "earth_dir_C": vec(view.earth_dir_C),
            "earth_distance_m": float(view.earth_distance_m), "earth_backdrop": bool(view.earth_backdrop),
            "earth_quat_C": vec(view.earth_quat_C), "earth_texture": int(view.earth_texture),
            "appendages": bool(view.appendages)}


def view_from_scene(scene: dict):
    """The View a label's scene records (with_look): the same render, bit for bit."""
    from envisat_pose.datagen.appearance import Look
    from envisat_pose.datagen.render import View

    r = scene["render"]
    arr = lambda v: None if v is None else np.array(v, dtype=float)  # noqa: E731
    return View(arr(r["rho_C_m"]), arr(r["R_C_from_T"]), arr(r["sun_dir_C"]), arr(r["earth_dir_C"]),
                r["earth_distance_m"], Look.from_json(scene["look"]), r["appendages"], r["earth_backdrop"],
                arr(r.get("earth_quat_C")), int(r.get("earth_texture", 0)))


@functools.lru_cache(maxsize=2)
def sequence_frames(cfg_json: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The truth of a sequence-mode config at its frame times: (t_s (N,), x (N, 12), sun_dir_C (N, 3),
    eclipse (N,) bool, nadir_C (N, 3) with chaser_r_m folded in as its norm)."""
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import EARTH_RADIUS_M, scenario_config
    from envisat_pose.datagen.truth import simulate

    cfg = config_from_json(cfg_json)
    n = cfg.num_images
    scen = scenario_config(cfg.scenario, duration_s=max(n - 1, 1) * cfg.frame_dt_s, dt_s=cfg.frame_dt_s, seed=cfg.seed)
    traj = simulate(scen)
    t_s, x = traj.t_s[:n], traj.x[:n]
    orb = chaser_orbit(scen.orbit, t_s)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(2**32 - 1,)))
    sun_N = unit(cfg.sun_dir) if cfg.sun_dir is not None else unit(rng.standard_normal(3))
    sun_C = np.einsum("nji,j->ni", orb.R_N_from_C, sun_N)
    # cylindrical Earth shadow: behind the Earth (r . s < 0) and within one Earth radius of the sun line
    along = orb.r_N_m @ sun_N
    perp = np.linalg.norm(orb.r_N_m - along[:, None] * sun_N, axis=1)
    eclipse = (along < 0) & (perp < EARTH_RADIUS_M)
    nadir_C = np.zeros((len(t_s), 3))
    nadir_C[:, 0] = -orb.r_m  # the Earth's centre is at -r x_C
    return t_s, x, sun_C, eclipse, nadir_C


@functools.lru_cache(maxsize=2)
def sequence_earth(cfg_json: str) -> tuple[np.ndarray, np.ndarray, int]:
    """The Earth of a sequence-mode config at its frame times: (quat_C (N, 4), the Earth's attitude in C (it
    turns with the orbit and its sidereal rate from an angle drawn from the seed); in_frame (N,) bool, whether
    its disc reaches the image; texture index)."""
    from envisat_pose.datagen.earth import EARTH_TEXTURE_SET_SIZE, earth_in_frame, earth_quat_C
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import scenario_config

    cfg = config_from_json(cfg_json)
    t_s, _, _, _, nadir_C = sequence_frames(cfg_json)
    scen = scenario_config(cfg.scenario, duration_s=max(cfg.num_images - 1, 1) * cfg.frame_dt_s,
                           dt_s=cfg.frame_dt_s, seed=cfg.seed)
    orb = chaser_orbit(scen.orbit, t_s)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(2**32 - 1, 0xEA27)))
    theta0 = float(rng.uniform(0.0, 2.0 * math.pi))
    texture = int(rng.integers(0, EARTH_TEXTURE_SET_SIZE))
    K = load_camera().scaled(cfg.resolution_px, cfg.resolution_px).K
    in_frame = np.array([earth_in_frame(R_K_FROM_C @ n, float(np.linalg.norm(n)), K, cfg.resolution_px)
                         for n in nadir_C], dtype=bool)
    return earth_quat_C(t_s, orb.R_N_from_C, theta0), in_frame, texture


def sequence_view(cfg: GenerateConfig, k: int) -> tuple:
    """Frame k of a sequence-mode config: (View, x (12,), scene dict). The Earth is drawn (earth_probability
    above 0) in the frames where its disc reaches the image."""
    from envisat_pose.datagen.render import View

    t_s, x, sun_C, eclipse, nadir_C = sequence_frames(config_json(cfg))
    xk = x[k]
    earth = False
    quat, texture = None, 0
    if cfg.earth_probability > 0:
        quats, in_frame, texture = sequence_earth(config_json(cfg))
        earth, quat = bool(in_frame[k]), quats[k]
    r_m = float(np.linalg.norm(nadir_C[k]))
    view = View(xk[POS], mrp_to_dcm(xk[MRP]).T, None if eclipse[k] else sun_C[k], unit(nadir_C[k]), r_m,
                earth_backdrop=earth, earth_quat_C=quat, earth_texture=texture)
    scene = {"mode": "sequence", "t_s": float(t_s[k]), "sun_dir_cam": (R_K_FROM_C @ sun_C[k]).round(9).tolist(),
             "eclipse": bool(eclipse[k]), "earth_backdrop": earth}
    return view, xk, scene


# ---------------------------------------------------------------------------------------------------------
# One sample, one shard


def image_motion(out, x: np.ndarray, f_px: float, boxes: TargetBoxes) -> tuple[float, float]:
    """The target's image motion (speed px/s, angle deg) from the state's relative rates: w_r (in T) turns the
    target about its centre, rho' (in C) moves it; the camera is fixed in C."""
    from envisat_pose.datagen.sensor import image_velocity_px_s

    w_K = out.R_K_from_T @ x[RATE]
    v_K = R_K_FROM_C @ x[VEL]
    return image_velocity_px_s(boxes.corners_T_m, out.R_K_from_T, out.t_K_from_T_m, w_K, v_K, f_px)


def draw_corruption_params(cfg: GenerateConfig, out, x: np.ndarray, f_px: float, boxes: TargetBoxes,
                           rng: np.random.Generator) -> dict:
    """The corruption parameters of one image: the space camera's (with the true image motion), none when
    every kind is 'none', or the paper's severities."""
    from envisat_pose.datagen.corrupt import KINDS, corruption_off, draw_corruption, no_corruption
    from envisat_pose.datagen.sensor import draw_sensor

    if cfg.corruption.model == "sensor":
        if corruption_off({k: getattr(cfg.corruption, k) for k in KINDS}):
            return no_corruption()  # every kind 'none': the user asked for uncorrupted frames
        speed, angle = image_motion(out, x, f_px, boxes)
        return draw_sensor(to_dict(cfg.corruption.sensor), cfg.resolution_px, f_px, speed, angle, rng)
    return draw_corruption(to_dict(cfg.corruption), cfg.resolution_px, rng)


def render_sample(renderer, cfg: GenerateConfig, view, x: np.ndarray, scene: dict, rng: np.random.Generator,
                  seed: int) -> dict[str, bytes]:
    """Render, label, corrupt (unless storage is 'clean') and encode one sample: {suffix: bytes} per the
    shard contract. `view` carries its look (with_look)."""
    return finish_sample(renderer.K, renderer.target_boxes, cfg, renderer.render(view), x, scene, rng, seed)


def finish_sample(K: np.ndarray, boxes: TargetBoxes, cfg: GenerateConfig, out, x: np.ndarray, scene: dict,
                  rng: np.random.Generator, seed: int) -> dict[str, bytes]:
    """Everything of a sample after its render (`out`, a RenderOutput of the renderer whose intrinsics are K
    and whose target is `boxes`): the corruption draw, the label, the corruption (unless storage is 'clean')
    and the PNG and JSON encoding. Touches no GL state, so it may run beside the next render."""
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.datagen.labels import encode_depth, make_label
    from envisat_pose.datagen.shards import encode_png, label_bytes

    params = draw_corruption_params(cfg, out, x, K[0, 0], boxes, rng)
    image = out.gray_u8 if cfg.storage == "clean" else apply_corruption(out.gray_u8, params)
    label = make_label(out.corners_K_m, out.depth_m, K, out.R_K_from_T, out.t_K_from_T_m, x,
                       cfg.depth_scale_m, params, seed, scene)
    label["image_stored"] = cfg.storage
    members = {"png": encode_png(image), "json": label_bytes(label)}
    if cfg.write_mask:
        members["mask.png"] = encode_png(out.mask_u8)
    if cfg.write_depth:
        members["depth.png"] = encode_png(encode_depth(out.depth_m, cfg.depth_scale_m), "depth")
    return members


@contextlib.contextmanager
def gil_switch_interval(interval_s: float):
    """Set the interpreter's GIL switch interval (s) inside the block, restore it after."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(interval_s)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def spare_core(workers: int, backend: str = "local", scheduler: str | None = None) -> bool:
    """Whether each of `workers` workers has a core its renderer leaves idle: LP_NUM_THREADS (llvmpipe's
    rasterizer threads, set before the run) below the worker's share of this machine's cores. Unset, the run
    sets it to that share (no core spare); an existing Dask scheduler's machines are unknown (False)."""
    lp = os.environ.get("LP_NUM_THREADS", "")
    if scheduler or not lp.isdigit():
        return False
    return int(lp) < cpu_share(workers)


def generate_shard(cfg: GenerateConfig, shard_index: int, out_dir: str, beside: bool = False) -> dict:
    """Write shard `shard_index` of the dataset into out_dir (atomically). Returns its manifest entry:
    index, name, count, sha256, bytes. beside: use the helper threads (FINISH_BESIDE_RENDER; same bytes)."""
    import cv2

    from envisat_pose.datagen.render import shared_renderer
    from envisat_pose.datagen.shards import ShardWriter, sample_key, shard_name
    from envisat_pose.io import sha256_file

    cv2.setNumThreads(1)  # one core per worker; also keeps filters on one code path
    renderer = shared_renderer(cfg.resolution_px, cfg.shadows, cfg.appearance.texture_set_size if cfg.appearance_on
                               else 0, cfg.appearance.texture_seed, cfg.earth_seed)
    beside = bool(beside if FINISH_BESIDE_RENDER is None else FINISH_BESIDE_RENDER)
    if (beside and cfg.mode == "random" and cfg.earth_probability > 0
            and cfg.num_images >= PREFETCH_EARTH_MIN_IMAGES):
        renderer.prefetch_earth_textures()  # a worker's start-up beside its first renders (no-op once made)
    path = os.path.join(out_dir, shard_name(shard_index))
    count = cfg.shard_count(shard_index)
    K, boxes = renderer.K.copy(), renderer.target_boxes
    fovy_deg, znear_m = renderer.fovy_deg, renderer.znear_m

    def prepare(i: int) -> tuple:
        """Sample i's view with its look: (k, seed, rng, view, x, scene); no GL."""
        k = shard_index * cfg.shard_size + i
        seed = sample_seed(cfg.seed, shard_index, i)
        rng = np.random.default_rng(seed)
        if cfg.mode == "random":
            view, x, scene = sample_random_view(cfg, fovy_deg, rng, znear_m, boxes)
        else:
            view, x, scene = sequence_view(cfg, k)
        view, scene = with_look(cfg, view, scene, seed)
        return k, seed, rng, view, x, scene

    def finish_and_write(k, out, x, scene, rng, seed):
        writer.write(sample_key(k), finish_sample(K, boxes, cfg, out, x, scene, rng, seed))

    def decode_finish_and_write(k, passes, x, scene, rng, seed):
        finish_and_write(k, renderer.decode(passes), x, scene, rng, seed)

    if not beside:
        with ShardWriter(path) as writer:
            for i in range(count):
                k, seed, rng, view, x, scene = prepare(i)
                finish_and_write(k, renderer.render(view), x, scene, rng, seed)
    else:
        # This thread only renders (the GL passes). One helper thread draws the next samples' views; another
        # finishes the rendered ones (the passes' pixel work, corruption draw, label, corruption, PNG encoding,
        # tar) while the next render runs: the render spends most of its time waiting in GL calls that release
        # the GIL (llvmpipe's rasterizer thread does the work), so they overlap. Up to FINISH_QUEUE samples wait
        # to be finished, so a slow finish (a tar flush, another process) does not stall the render. Each
        # sample's own generator is used in the same order (its view, then after its render its corruption draw)
        # and one finishing thread writes first in first out: the same bytes in the same order as doing it all
        # one after the other. The pools close (every sample written or failed) before the writer publishes or
        # discards the shard.
        with gil_switch_interval(GIL_SWITCH_INTERVAL_S), ShardWriter(path) as writer, \
                ThreadPoolExecutor(1, thread_name_prefix="finish") as finisher, \
                ThreadPoolExecutor(1, thread_name_prefix="prepare") as preparer:
            upcoming = preparer.submit(prepare, 0)
            pending: collections.deque = collections.deque()
            for i in range(count):
                k, seed, rng, view, x, scene = upcoming.result()
                if i + 1 < count:
                    upcoming = preparer.submit(prepare, i + 1)
                passes = renderer.render_passes(view)
                pending.append(finisher.submit(decode_finish_and_write, k, passes, x, scene, rng, seed))
                while len(pending) > FINISH_QUEUE:
                    pending.popleft().result()  # its error surfaces here
            while pending:
                pending.popleft().result()
    return {"index": shard_index, "name": shard_name(shard_index), "count": count, "sha256": sha256_file(path),
            "bytes": os.path.getsize(path)}


def shard_task(cfg_json: str, shard_index: int, out_dir: str, beside: bool = False) -> dict:
    """generate_shard for workers: the config travels as JSON text."""
    return generate_shard(config_from_json(cfg_json), shard_index, out_dir, beside)


# ---------------------------------------------------------------------------------------------------------
# Planning, resuming, running


def check_sequence_depth(cfg: GenerateConfig) -> None:
    """Sequence mode: ConfigError on depth_scale_m unless 65535 x depth_scale_m covers the farthest target
    point of every frame (from the simulated truth, which also runs the scenario's keep-out check)."""
    _, x, _, _, _ = sequence_frames(config_json(cfg))
    R_K_from_T = R_K_FROM_C @ np.swapaxes(mrp_to_dcm(x[:, MRP]), 1, 2)
    far_m = farthest_depth_m(x[:, POS] @ R_K_FROM_C.T, R_K_from_T, project_target_boxes())
    k = int(np.argmax(far_m))
    check(DEPTH_MAX_CODE * cfg.depth_scale_m >= far_m[k], "depth_scale_m", cfg.depth_scale_m,
          f"a scale whose 16-bit range (65535 x scale = {DEPTH_MAX_CODE * cfg.depth_scale_m:.1f} m) covers "
          f"{far_m[k]:.1f} m, the farthest target point of scenario {cfg.scenario!r} (frame {k})")


def dataset_job(cfg: GenerateConfig, out_dir: str) -> ResumableJob:
    """The dataset in out_dir as the core's resumable job: one unit per shard, the config and root seed as its
    identity, a shard kept on resume only when its sha256 matches and its tar holds the recorded count."""
    from envisat_pose.datagen.render import MASK_VALUES
    from envisat_pose.datagen.shards import check_shard, shard_name

    return ResumableJob(
        out_dir, MANIFEST_FORMAT, "dataset", {"config": to_dict(cfg), "root_seed": cfg.seed}, "shards",
        cfg.num_shards, shard_name,
        header={"num_images": cfg.num_images, "num_shards": cfg.num_shards,
                "mask_values": {"background": 0, **MASK_VALUES},
                "members": ["png", "json"] + (["mask.png"] if cfg.write_mask else [])
                + (["depth.png"] if cfg.write_depth else [])},
        verify_unit=lambda entry, path: check_shard(path, None, entry["count"]) is None)


def run_generate(cfg: GenerateConfig, out_dir: str, workers: int = 1, backend: str = "local",
                 scheduler: str | None = None, progress: bool = False,
                 on_shard: Callable[[dict], None] | None = None) -> dict:
    """Generate (or finish) the dataset of `cfg` in out_dir; returns the final manifest.

    on_shard, if given, is called with each finished shard's manifest entry once it is recorded.
    """
    from envisat_pose.config import to_toml
    from envisat_pose.io import atomic_write_text

    check(backend in ("local", "dask"), "backend", backend, "'local' or 'dask'")
    # one rasterizer thread count per worker: the machine's cores shared among the workers
    runner = RunnerConfig(backend, workers, scheduler, {"LP_NUM_THREADS": str(cpu_share(workers))})
    runner.validate()
    check_out_dir(out_dir)
    if cfg.mode == "sequence":  # before anything is written: the truth's keep-out and the depth range
        check_sequence_depth(cfg)
    job = dataset_job(cfg, out_dir)
    done = job.resume(job.open())
    atomic_write_text(os.path.join(out_dir, "generate.config.toml"),
                      "# envisat generate: the full validated config of this dataset\n" + to_toml(to_dict(cfg)))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.num_images, initial=sum(e["count"] for e in done.values()), unit="img",
                   desc="generate", mininterval=0.5)

    def on_unit(entry: dict) -> None:
        if bar is not None:
            bar.update(entry["count"])
        if on_shard is not None:
            on_shard(entry)

    try:
        cfg_text, where = config_json(cfg), os.path.abspath(out_dir)
        beside = spare_core(workers, backend, scheduler)
        return job.run(shard_task, lambda idx: (cfg_text, idx, where, beside), runner, on_unit)
    finally:
        if bar is not None:
            bar.close()
