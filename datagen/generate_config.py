"""The image factory's config (`envisat generate`): GenerateConfig, its two mode tables ([random]:
RandomModeConfig, [sequence]: SequenceModeConfig) and its four parts, the space camera
(SensorConfig), the corruption severities (CorruptionConfig), the target's appearance (AppearanceConfig) and the
lighting (LightingConfig); one validated config travels to the shard tasks as JSON (config_json /
config_from_json)."""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field, fields, replace
from typing import Literal

import numpy as np

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.camera_response import parse_response
from envisat_pose.config import Config, ConfigError, Derived, check, derived, from_dict, resolve_job_config, to_dict
from envisat_pose.datagen.appearance import CLASSES
from envisat_pose.datagen.clearance import farthest_depth_m, target_file_boxes
from envisat_pose.datagen.labels import DEPTH_MAX_CODE
from envisat_pose.datagen.scenario import (
    EARTH_RADIUS_M,
    MIN_PHYSICS_DT_S,
    ScenarioConfig,
    scenario_dict,
    sequence_scenario,
)
from envisat_pose.datagen.target_scene import scene_clip_planes_m, size_ratio
from envisat_pose.geometry import load_camera
from envisat_pose.state import MRP, POS
from envisat_pose.target import DEFAULT_TARGET, load_target
from envisat_pose.written_target import recorded_target_checked

Severity = Literal["none", "low", "medium", "high", "mixed"]
Range = tuple[float, float]

# Random mode's views of ENVISAT, m: the defaults every other target takes scaled by its size (sized_random_m)
ENVISAT_RANDOM_M = {"range_min_m": 20.0, "range_max_m": 80.0, "keepout_margin_m": 2.0}
DEPTH_SCALE_M = 0.002  # the depth PNG's default metres per unit (ENVISAT's: 131 m of range)
SIZED_DIGITS = 4  # significant digits of a sized default (the number the manifest records)
MAX_IMAGES = 100_000_000  # a dataset's most images (GenerateConfig.num_images)
# a sequence whose first frame shows the target fewer pixels across than this (2 reach / range x f_px) is refused
MIN_SEQUENCE_TARGET_SPAN_PX = 4.0
# sequence.range_scale's bounds: a target a thousandth of ENVISAT's size to one ten times it
MIN_RANGE_SCALE, MAX_RANGE_SCALE = 1e-3, 10.0


def _check_range(value: tuple, field_name: str, lo: float, hi: float) -> None:
    check(lo <= value[0] <= value[1] <= hi, field_name, list(value), f"[low, high] with {lo:g} <= low <= high <= {hi:g}")


def sized_value(value: float) -> float:
    """A sized default as the config records it: value to SIZED_DIGITS significant digits (1 stays 1 exactly)."""
    return Derived(f"{value:.{SIZED_DIGITS}g}")


def sized_random_m(ratio: float) -> dict[str, float]:
    """Random mode's default range_min_m, range_max_m and keepout_margin_m (m) of a target `ratio` times ENVISAT's
    size (target_scene.size_ratio): ENVISAT's (ENVISAT_RANDOM_M) times ratio, to SIZED_DIGITS significant digits
    (ENVISAT's own exactly: ratio 1)."""
    return {name: sized_value(value_m * ratio) for name, value_m in ENVISAT_RANDOM_M.items()}


def farthest_target_point_m(range_max_m: float, reach_m: float) -> float:
    """The farthest a target point lies from the camera in random mode, m: the view's range at the edge of the
    field of view (range_max_m / cos 30 deg) plus the target's reach."""
    return range_max_m / math.cos(math.radians(30.0)) + reach_m


def sized_depth_scale_m(far_m: float) -> float:
    """DEPTH_SCALE_M, or the least whole number of mm per unit whose 16-bit range covers far_m (a target so large
    that its sized ranges reach beyond 131 m)."""
    return Derived(max(DEPTH_SCALE_M, math.ceil(far_m / DEPTH_MAX_CODE * 1000.0) / 1000.0))


def sequence_depth_m(cfg: "GenerateConfig") -> np.ndarray:
    """(N,) m: the farthest depth (along the boresight) of any target point, its geoms' boxes, in each frame of
    the sequence-mode config cfg, from its simulated truth (truth.sequence_truth, which runs its keep-out check)."""
    from envisat_pose.datagen.truth import sequence_truth  # MuJoCo: not for a verb's parser, which reads this module

    seq = cfg.sequence
    x = sequence_truth(seq.scenario, seq.range_scale, cfg.num_images, seq.frame_dt_s, cfg.seed, cfg.target)[2]
    R_K_from_C = load_camera().R_K_from_C
    R_K_from_T = R_K_from_C @ np.swapaxes(mrp_to_dcm(x[:, MRP]), 1, 2)
    return farthest_depth_m(x[:, POS] @ R_K_from_C.T, R_K_from_T, target_file_boxes(cfg.target))


def target_span_px(reach_m: float, range_m: float, f_px: float) -> float:
    """The target's span in the image, px: 2 reach_m / range_m x f_px (its bounding sphere's diameter at range_m,
    m, seen with focal length f_px, px)."""
    return 2.0 * reach_m / range_m * f_px


@dataclass(frozen=True)
class SensorConfig(Config):
    """The space camera (datagen/sensor.py): ranges [low, high] drawn per image, fixed camera properties.

    exposure_s: exposure time, s. full_well_e: full-well capacity, electrons. white_fill: the share of the full
    well a white (255) clean pixel collects in the exposure (above 1: bright foil saturates and blooms).
    read_noise_e: read noise, e- RMS. dark_current_e_per_s: dark current, e-/s per pixel. prnu_sigma: pixel
    gain non-uniformity (fixed pattern, seeded by camera_seed). adc_bits: bit depths to draw from.
    blooming_decay_px: column spill length of saturated charge. psf: 'gaussian', 'airy' or 'mixed';
    psf_sigma_px_1024: Gaussian sigma at 1024 px; f_number, wavelength_m, pixel_pitch_m_1024: the Airy
    optics. vignetting_cos_power: exponent n of cos^n (4: natural vignetting). response: how the 8-bit output
    stores the light, encoded after optics and sensor: 'linear', 'srgb' or 'gamma G' (envisat_pose/camera_response.py).
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
    response: str = "linear"

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        parse_response(self.response, f"{p}response")
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
class CorruptionConfig(Config):
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

        check_severities(self.model, {k: getattr(self, k) for k in KINDS}, prefix)


@dataclass(frozen=True)
class AppearanceConfig(Config):
    """Per-image materials within each face's covering class (datagen/appearance.py). enabled: None means on
    in random mode, off in sequence mode. texture_set_size: textures per class. texture_seed: the texture set.
    seed: the appearance draws' own seed (mixed with each sample's): another seed, other appearance draws, same poses.
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
            check(self.one_covering in CLASSES, f"{p}one_covering", self.one_covering,
                  f"a covering class ({', '.join(sorted(CLASSES))})")


@dataclass(frozen=True)
class LightingConfig(Config):
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
class RandomModeConfig(Config):
    """Random mode's view draws (table [random]; unused in sequence mode).

    range_min_m/range_max_m: target range, m; keepout_margin_m: least distance of the camera from any part of the
    target, m (views closer, or whose near plane cuts the target, are drawn again from the same generator). Not
    given (None), each is ENVISAT's default (20, 80 and 2 m) times the target's size against ENVISAT's
    (sized_random_m of target_scene.size_ratio: the 3U CubeSat 0.7289, 2.916 and 0.07289 m, the upper stage
    14.45, 57.79 and 1.445 m); GenerateConfig fills them in, so a config and a manifest always hold numbers
    (config.Derived: dataclasses.replace with another target sizes them again; read back from a file, given).
    max_offset_frac: target centre within this fraction of the half field of view. sun_phase_max_deg: the sun is
    drawn uniformly on the cap of directions within this phase angle of the direction from the target to the
    camera (0: sun behind the camera, 90: side light, 180: any), so most views are lit as an approach would plan
    them; backlit_probability: share of views whose sun is drawn from the whole sphere instead (backlit and
    silhouette views stay in the set). eclipse_probability: share of images in eclipse. earth_orbit_radius_m: the
    chaser's orbit radius range, m (the Earth disc's angular radius is asin(R / r)). rate_max_deg_s: the relative
    tumble rate is drawn uniform in [0, this] about a random axis (it sets the space camera's motion blur and
    goes into the label's x).
    """

    range_min_m: float | None = None
    range_max_m: float | None = None
    max_offset_frac: float = 0.6
    sun_phase_max_deg: float = 100.0
    backlit_probability: float = 0.15
    eclipse_probability: float = 0.05
    earth_orbit_radius_m: Range = (6978.0e3, 7378.0e3)
    keepout_margin_m: float | None = None
    rate_max_deg_s: float = 5.0

    def validate(self, prefix: str = "") -> None:
        """The table's own checks; a range or margin not given (None) is checked once GenerateConfig has sized it."""
        p = f"{prefix}." if prefix else ""
        if self.range_min_m is not None and self.range_max_m is not None:
            check(self.range_max_m >= self.range_min_m, f"{p}range_max_m", self.range_max_m,
                  f"a range no shorter than range_min_m = {self.range_min_m}")
        check(0.0 <= self.max_offset_frac <= 1.0, f"{p}max_offset_frac", self.max_offset_frac, "a fraction in [0, 1]")
        check(0.0 <= self.sun_phase_max_deg <= 180.0, f"{p}sun_phase_max_deg", self.sun_phase_max_deg,
              "a phase angle in [0, 180] deg")
        check(0.0 <= self.backlit_probability <= 1.0, f"{p}backlit_probability", self.backlit_probability,
              "a probability in [0, 1]")
        check(0.0 <= self.eclipse_probability <= 1.0, f"{p}eclipse_probability", self.eclipse_probability,
              "a probability in [0, 1]")

        _check_range(self.earth_orbit_radius_m, f"{p}earth_orbit_radius_m", EARTH_RADIUS_M + 100e3, 1e8)
        if self.keepout_margin_m is not None:
            check(self.keepout_margin_m >= 0, f"{p}keepout_margin_m", self.keepout_margin_m,
                  "a non-negative distance in m")
        check(0 <= self.rate_max_deg_s <= 90, f"{p}rate_max_deg_s", self.rate_max_deg_s, "a rate in [0, 90] deg/s")


@dataclass(frozen=True)
class SequenceModeConfig(Config):
    """Sequence mode's truth (table [sequence]; unused in random mode): scenario, the named truth scenario whose
    simulation the frames show; frame_dt_s, the interval between frames, s; range_scale: the scenario's start
    (relative.rho0_C_m, rhodot0_C_m_s) and keep-out margin times this (datagen.scenario.scaled_start); not given,
    the target's size against ENVISAT's (target_scene.size_ratio, to SIZED_DIGITS significant digits: ENVISAT 1
    exactly, the 3U CubeSat 0.03644, a 1.8 m hold for the default scenario's 50 m), so a sequence frames another
    target as random mode's sized views do; 1 flies the scenario's own metres."""

    scenario: str = "default"
    frame_dt_s: float = 1.0
    range_scale: float | None = None

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.frame_dt_s >= MIN_PHYSICS_DT_S, f"{p}frame_dt_s", self.frame_dt_s, f"a frame interval of at "
              f"least {MIN_PHYSICS_DT_S:g} s (the truth's least physics step: each frame's step holds one or more)")
        if self.range_scale is not None:
            check(MIN_RANGE_SCALE <= self.range_scale <= MAX_RANGE_SCALE, f"{p}range_scale", self.range_scale,
                  f"a factor on the scenario's start in [{MIN_RANGE_SCALE:g}, {MAX_RANGE_SCALE:g}] (1: its metres)")


# The keys that moved from the top level into [random] and [sequence] (datasets written before keep reading:
# nest_moved_keys; a config file or flag with the old key gets one line naming its new home).
MOVED_KEYS = {**{f.name: f"random.{f.name}" for f in fields(RandomModeConfig)},
              **{f.name: f"sequence.{f.name}" for f in fields(SequenceModeConfig)}}


@dataclass(frozen=True)
class GenerateConfig(Config):
    """What `envisat generate` makes.

    mode: 'random' (domain-randomized views, drawn by the [random] table) or 'sequence' (frames of a simulated
    truth, the [sequence] table). target: the target's MJCF file (envisat_pose/target.py: a body 'target' with its
    inertial, geoms and keypoint sites kp_<name>; default ENVISAT, models/envisat.xml): random mode's ranges and
    keep-out margin not given are sized to it (__post_init__). resolution_px: square image side.
    sun_dir: unit vector toward the sun, in C (random mode) or N (sequence mode); omitted: drawn from the seed.
    earth_probability: share of random-mode images that look toward the Earth and draw it behind the target
    (textured, lit by the view's sun; datagen/earth.py); sequence mode: above 0, the Earth is drawn at the
    orbit's nadir in the frames where it reaches the image. earth_seed: the Earth texture set.
    depth_scale_m: metres per unit of the 16-bit depth PNG; not given: DEPTH_SCALE_M, or for a target whose
    farthest point lies beyond its 16-bit range the least whole mm that covers it (__post_init__): in random mode
    the farthest of its ranges (farthest_target_point_m), in sequence mode with write_depth the farthest of its
    frames (sequence_depth_m: the truth simulated once, cached for the frames).
    appendages: draw the ASAR antenna and instrument boxes (mask value 8); None: on in random mode only.
    storage: 'corrupted' stores the corrupted image; 'clean' stores the clean render, and
    dataset.sample_image applies the label's corruption on read (the same bytes).
    """

    moved_keys = MOVED_KEYS

    mode: Literal["random", "sequence"] = "random"
    target: str = DEFAULT_TARGET
    num_images: int = 1000
    shard_size: int = 100
    resolution_px: int = 1024
    seed: int = 0
    sun_dir: tuple[float, float, float] | None = None
    earth_probability: float = 0.3
    earth_seed: int = 0
    shadows: bool = True
    write_mask: bool = True
    write_depth: bool = True
    depth_scale_m: float | None = None
    appendages: bool | None = None
    storage: Literal["clean", "corrupted"] = "corrupted"
    random: RandomModeConfig = field(default_factory=RandomModeConfig)
    sequence: SequenceModeConfig = field(default_factory=SequenceModeConfig)
    corruption: CorruptionConfig = field(default_factory=CorruptionConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)

    def __post_init__(self) -> None:
        """Fill in random mode's range_min_m, range_max_m and keepout_margin_m not given with the target's sized
        defaults (sized_random_m of target_scene.size_ratio: ENVISAT's own numbers for ENVISAT) and sequence mode's
        range_scale not given with the same ratio (sized_value), then depth_scale_m not given
        (_sized_depth_scale_m). A target that cannot be read leaves them unset: validate names the target."""
        unset = [name for name in ENVISAT_RANDOM_M if derived(getattr(self.random, name))]
        ratio = self._size_ratio() if unset or derived(self.sequence.range_scale) else None
        if ratio is not None and unset:
            sized = sized_random_m(ratio)
            try:
                filled = replace(self.random, **{name: sized[name] for name in unset})
            except ConfigError as err:  # a given range against a sized one: named in its table
                raise ConfigError(f"random.{err.field}", err.value, err.expected) from None
            object.__setattr__(self, "random", filled)
        if ratio is not None and derived(self.sequence.range_scale):
            sized = MIN_RANGE_SCALE <= sized_value(ratio) <= MAX_RANGE_SCALE
            if not sized and (self.mode == "sequence" or unset):  # random mode's own ranges need no range_scale
                yours = ("sequence.range_scale" if self.mode == "sequence" else
                         "random.range_min_m, range_max_m and keepout_margin_m")
                raise ConfigError("target", self.target, f"a spacecraft {MIN_RANGE_SCALE:g} to {MAX_RANGE_SCALE:g} "
                                  f"times ENVISAT's size, the views sized to it (this one: {ratio:.4g} times; or "
                                  f"give {yours} yourself)")
            if sized:
                object.__setattr__(self, "sequence", replace(self.sequence, range_scale=sized_value(ratio)))
        from_truth = derived(self.depth_scale_m) and self.mode == "sequence" and self.write_depth
        if derived(self.depth_scale_m):
            object.__setattr__(self, "depth_scale_m", self._sized_depth_scale_m())
        super().__post_init__()
        if from_truth:  # the validated sequence's truth simulated (cached for its frames), its depths covered
            object.__setattr__(self, "depth_scale_m", sized_depth_scale_m(float(sequence_depth_m(self).max())))

    def _size_ratio(self) -> float | None:
        """target_scene.size_ratio of the target; None for a target that cannot be read (validate names it)."""
        try:
            return size_ratio(load_target(self.target))
        except ConfigError:
            return None

    def _sized_depth_scale_m(self) -> float:
        """sized_depth_scale_m of random mode's farthest target point; DEPTH_SCALE_M in sequence mode (sized from
        its truth once validated: __post_init__) and for a target that cannot be read (validate names it)."""
        if self.mode != "random" or self.random.range_max_m is None:
            return Derived(DEPTH_SCALE_M)
        try:
            reach_m = target_file_boxes(self.target).reach_m
        except ConfigError:
            return Derived(DEPTH_SCALE_M)
        return sized_depth_scale_m(farthest_target_point_m(self.random.range_max_m, reach_m))

    @property
    def appearance_on(self) -> bool:
        e = self.appearance.enabled
        return self.mode == "random" if e is None else e

    @property
    def appendages_on(self) -> bool:
        return self.mode == "random" if self.appendages is None else self.appendages

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        # 1e12 images hung before any output (the job lists its shards); 1e8 are ~100 TB of 1024 px PNGs
        check(1 <= self.num_images <= MAX_IMAGES, f"{p}num_images", self.num_images, f"1 to {MAX_IMAGES} images")
        check(self.shard_size >= 1, f"{p}shard_size", self.shard_size, "at least 1 image per shard")
        check(16 <= self.resolution_px <= 4096, f"{p}resolution_px", self.resolution_px, "a resolution in [16, 4096] px")
        check(0 <= self.seed < 2**63, f"{p}seed", self.seed, "a non-negative integer seed below 2^63")
        reach_m = target_file_boxes(self.target, f"{p}target").reach_m
        self.random.validate(f"{p}random")  # again, with the sized defaults filled in
        check(self.random.range_min_m > reach_m / 2, f"{p}random.range_min_m", self.random.range_min_m,
              f"a range above {reach_m / 2:.1f} m (the camera must stay outside the target)")
        if self.sun_dir is not None:
            with np.errstate(over="ignore"):  # its length overflowed to inf at 1e300: NaN images, no word
                norm = float(np.linalg.norm(np.asarray(self.sun_dir, dtype=float)))
            check(np.isfinite(norm) and norm > 0, f"{p}sun_dir", list(self.sun_dir), "a non-zero vector of finite length")
        check(0.0 <= self.earth_probability <= 1.0, f"{p}earth_probability", self.earth_probability,
              "a probability in [0, 1]")
        check(0 <= self.earth_seed < 2**63, f"{p}earth_seed", self.earth_seed, "a non-negative integer seed")
        # a unit longer than the target's reach gives its whole relief a code or two: a flat depth image (1e300: all 0)
        check(0 < self.depth_scale_m <= reach_m, f"{p}depth_scale_m", self.depth_scale_m,
              f"a positive scale of at most the target's reach ({reach_m:.3g} m: its relief in 2 codes or more)")
        if self.mode == "random":
            reach = farthest_target_point_m(self.random.range_max_m, reach_m)
            check(DEPTH_MAX_CODE * self.depth_scale_m >= reach, f"{p}depth_scale_m", self.depth_scale_m,
                  f"a scale whose 16-bit range (65535 x scale) covers {reach:.1f} m, the farthest target point")
            zfar_m = scene_clip_planes_m(load_target(self.target))[1]
            check(reach < zfar_m, f"{p}random.range_max_m", self.random.range_max_m,
                  f"a range whose farthest target point ({reach:.1f} m) lies before the far clipping plane "
                  f"({zfar_m:.0f} m)")
        if self.mode == "sequence":
            self._check_sequence_target_size(p)
            seq = self.sequence  # the truth it simulates: a sequence too long for it named by num_images
            sequence_scenario(seq.scenario, seq.range_scale, self.num_images, seq.frame_dt_s, self.seed, self.target,
                              prefix)

    def _check_sequence_target_size(self, p: str) -> None:
        """ConfigError naming sequence.scenario (an unknown name, too) when the scenario's first frame shows the
        target fewer than MIN_SEQUENCE_TARGET_SPAN_PX across (target_span_px of its reach at |relative.rho0_C_m|
        times sequence.range_scale): the fix is a larger resolution_px, a smaller range_scale or a nearer
        scenario."""
        range_m = self.sequence.range_scale * _start_range_m(json.dumps(scenario_dict(self.sequence.scenario),
                                                                        sort_keys=True))
        reach_m = load_target(self.target).reach_m
        f_px = float(load_camera().scaled(self.resolution_px, self.resolution_px).K[0, 0])
        span_px = target_span_px(reach_m, range_m, f_px)
        if span_px >= MIN_SEQUENCE_TARGET_SPAN_PX:
            return
        need_px = math.ceil(self.resolution_px * MIN_SEQUENCE_TARGET_SPAN_PX / span_px)
        near_m = range_m * span_px / MIN_SEQUENCE_TARGET_SPAN_PX
        raise ConfigError(f"{p}sequence.scenario", self.sequence.scenario,
                          f"a scenario whose first frame shows the target at least {MIN_SEQUENCE_TARGET_SPAN_PX:g} px "
                          f"across: its reach {reach_m:.3g} m at {range_m:.3g} m (relative.rho0_C_m x sequence.range_scale "
                          f"{self.sequence.range_scale:g}) spans {span_px:.1f} px at resolution_px = "
                          f"{self.resolution_px}; set resolution_px to at least {need_px} or start the sequence "
                          f"within {near_m:.3g} m (a smaller sequence.range_scale or a nearer scenario)")

    @property
    def num_shards(self) -> int:
        return math.ceil(self.num_images / self.shard_size)

    def shard_count(self, index: int) -> int:
        """Number of samples in shard `index` (the last one may be short)."""
        return min(self.shard_size, self.num_images - index * self.shard_size)


@functools.lru_cache(maxsize=16)
def _start_range_m(truth_json: str) -> float:
    """|relative.rho0_C_m|, m, of the validated scenario whose truth part (scenario_dict) is the JSON text
    truth_json: cached by that text, since every build of a sequence-mode config checks it (a run's, twice)."""
    return float(np.linalg.norm(from_dict(ScenarioConfig, json.loads(truth_json)).relative.rho0_C_m))


def nest_moved_keys(data: dict) -> dict:
    """A stored generate config (a dataset's manifest, a look's record) with the keys of the flat layout (before
    [random] and [sequence]) moved into their tables, and a sequence written before sequence.range_scale read at
    range_scale 1 (its frames flew the scenario's metres); a config of today's layout comes back unchanged."""
    out = {k: v for k, v in data.items() if k not in MOVED_KEYS}
    for key, value in data.items():
        if key in MOVED_KEYS:
            table, name = MOVED_KEYS[key].split(".")
            out[table] = {**out.get(table, {}), name: value}
    if out.get("mode") == "sequence" and "range_scale" not in out.get("sequence", {}):
        out["sequence"] = {**out.get("sequence", {}), "range_scale": 1.0}
    return out


def config_from_json(text: str) -> GenerateConfig:
    """A GenerateConfig from its JSON text (how tasks travel to workers: plain data, never pickles)."""
    return from_dict(GenerateConfig, nest_moved_keys(json.loads(text)))


def config_json(cfg: GenerateConfig) -> str:
    return json.dumps(to_dict(cfg), sort_keys=True)


def layered_generate(defaults: dict, config_path: str | None, flags: dict) -> GenerateConfig:
    """The GenerateConfig of `envisat generate --config FILE` (and of train's --generate-config): `defaults`, the
    TOML file at config_path and the flags, each over the last (config.resolve_job_config); a written
    generate.config.toml's record of its target file set aside, the file checked against it
    (written_target.recorded_target_checked: a rerun refuses the file once it changed)."""
    return resolve_job_config(GenerateConfig, defaults, config_path, flags,
                              recorded_target_checked(config_path, "generate"))
