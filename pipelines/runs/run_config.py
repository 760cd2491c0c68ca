"""The config of `envisat run` (RunConfig), complete when built: the scenario's duration, rate and filter, a
worker per run, the shipped weights, the image factory's sequence fields and the sun (finished_image); and the
sun and the Earth's shadow per frame along the chaser's orbit (sun_and_shadow). The closed loop
(pipelines/runs/closed_loop.py) runs a RunConfig as it is."""

from __future__ import annotations

import dataclasses
import json
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from envisat_pose.config import UNMARKED, Config, DerivedInt, check, derived, filled_for, from_dict, mark_filled
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.scenario import in_earth_shadow, scenario_config, scenario_eclipse
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.geometry import load_camera
from envisat_pose.pipelines.common.job_defaults import fill_from_scenario, job_weights, layered_job, scenario_table
from envisat_pose.pipelines.tracking.integrity import check_min_target_px
from envisat_pose.pipelines.tracking.onboard import orbit_config
from envisat_pose.pipelines.tracking.tracker import TRACKER_FILTER, TrackerConfig
from envisat_pose.pipelines.tracking.tracker_bounds import MAX_PREDICTION_S, MAX_RUN_FRAMES
from envisat_pose.pools import MAX_WORKERS, default_processes

if TYPE_CHECKING:  # the stage's type for annotations; imported where a config is made
    from envisat_pose.datagen.generate_config import GenerateConfig

# a lit default: the sun 45 deg off the line of sight, behind the camera, from above the orbit plane at t = 0 (in
# C: radial, along-track, normal); in the default orbit the chaser enters the Earth's shadow at t = 1203 s
DEFAULT_SUN_C0 = (0.7, -0.7, 0.15)
# a closed loop's process (renderer, detector, tracker) for the default worker count (pools.default_processes):
# peak RSS 1.17-1.32 GB at 1024 px (2026-12, `envisat run --runs 8`), with a margin
RUN_PROCESS_BYTES = 1_400_000_000


def _image_defaults() -> "GenerateConfig":
    return GenerateConfig(mode="sequence", num_images=1, shard_size=1, write_mask=False, write_depth=False)


@dataclass(frozen=True)
class RunConfig(Config):
    """One `envisat run` job, complete and validated when built: `RunConfig(scenario=NAME, runs=4)` is the job of
    `envisat run --scenario NAME --runs 4` (pipelines.jobs.resolve_job adds a config file and flags).

    scenario: named truth; duration_s: simulated time; rate_hz: camera and filter rate; filter: the UKF (the
    scenario's [filter] table over TRACKER_FILTER). Those three left None take the scenario's (its duration and
    [measurement] rate, else 600 s and 1 Hz; job_defaults.fill_from_scenario; a filter given as a dict sets its keys
    over the scenario's, as a config file's [filter] table does; a FilterConfig is taken whole). runs: closed loops
    on the same truth; workers: processes for them (None: one per run, within cores and memory); seed: the truth's
    random attitude, every run's camera noise (and warm start); weights: detector weights file ("": the shipped
    ones; the file must exist; another target's (image.target) keypoint detector, required for it); bf16: ENVISAT's
    corner detector runs its network in bfloat16 (perception.detect.DetectConfig.bf16; `--bf16`). warm_start: start
    each run's filter from the truth plus a draw from filter.p0_sigma (filter studies), instead of cold from the
    images. threads: torch CPU threads per run; jpeg_quality: run 0's images in the recording. image: the camera
    frames as the image factory's sequence mode makes them (its sequence fields, seed and frame count are set from
    the ones above, its sun made explicit: finished_image). tracker: pipelines.tracker.TrackerConfig. render_window
    (on; `--full-frames` off): once the tracker holds one confirmed hypothesis, MuJoCo renders and the space camera
    corrupts only the window its detector will look at, the rest of the frame black: planned a frame early (the
    frames are made while the tracker steps the one before) and grown, made again when it does not hold the
    tracker's plan (pipelines/runs/loop_frames.py); a full frame every full_frame_every frames (where ENVISAT's
    array cue reads: it reads no window) and whenever the tracker acquires, holds twins, has not confirmed its claim
    or its last window held too few keypoints. The window's noise is drawn apart from the full frame's (the same
    distribution, other pixels): a seed's figures differ from its full frames' within their noise (docs/design.md,
    "The closed loop")."""

    scenario: str = "default"
    duration_s: float | None = None
    rate_hz: float | None = None
    runs: int = 1
    workers: int | None = None
    seed: int = 0
    weights: str = ""
    bf16: bool = False
    warm_start: bool = False
    threads: int = 1
    jpeg_quality: int = 80
    image: "GenerateConfig" = field(default_factory=_image_defaults)
    filter: FilterConfig | None = None
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    render_window: bool = True
    full_frame_every: int = 10

    table_bases: ClassVar[dict] = {"filter": scenario_table("run", "filter")}

    def __post_init__(self) -> None:
        fill_from_scenario(self, "run", RUN_FALLBACKS)
        if derived(self.workers):  # one process per run, no more than the usable cores and memory hold (marked:
            n = default_processes(min(self.runs, MAX_WORKERS), RUN_PROCESS_BYTES)  # a replace's runs count again)
            object.__setattr__(self, "workers", DerivedInt(n))
        super().__post_init__()
        if self.workers > self.runs:  # the processes that run: one per run at most
            object.__setattr__(self, "workers", type(self.workers)(self.runs))
        object.__setattr__(self, "weights", job_weights(self.weights, self.image.target))  # never ENVISAT's for another
        # after validation: the frame count needs a valid duration and rate
        object.__setattr__(self, "image", finished_image(self))

    @classmethod
    def from_scenario(cls, name: str = "default", config_path: str | None = None, overrides: dict | None = None,
                      **fields) -> "RunConfig":
        """Deprecated (goes in the next release): RunConfig(scenario=NAME, ...), or pipelines.jobs.resolve_job
        ("run", NAME, config_path, overrides, ...) for a config file and dotted flags; this is the latter."""
        warnings.warn("RunConfig.from_scenario is deprecated and goes in the next release: use "
                      "RunConfig(scenario=NAME, ...) (or pipelines.jobs.resolve_job for a config file)",
                      DeprecationWarning, stacklevel=2)
        return layered_job(cls, "run", name, config_path, overrides, fields)

    def validate(self, prefix: str = "") -> None:
        # frames at most MAX_PREDICTION_S apart (1e-300 Hz was refused naming sequence.frame_dt_s, no key of a run)
        check(1.0 / MAX_PREDICTION_S <= self.rate_hz <= 10.0, "rate_hz", self.rate_hz, f"a rate in "
              f"[{1.0 / MAX_PREDICTION_S:g}, 10] Hz (frames at most {MAX_PREDICTION_S:g} s apart, the longest gap a "
              "track is predicted over)")
        # the truth steps at the frame interval: a shorter run (1e-300 s) was refused after the run began, naming dt_s
        check(self.duration_s >= 1.0 / self.rate_hz, "duration_s", self.duration_s,
              f"a duration of at least one frame interval (1 / rate_hz = {1.0 / self.rate_hz:g} s)")
        check(self.duration_s * self.rate_hz <= MAX_RUN_FRAMES, "duration_s", self.duration_s,
              f"at most {MAX_RUN_FRAMES} frames (duration_s x rate_hz)")
        check(1 <= self.runs <= 1000, "runs", self.runs, "1 to 1000 runs")
        check(1 <= self.workers <= MAX_WORKERS, "workers", self.workers, f"1 to {MAX_WORKERS} processes")
        check(0 <= self.seed < 2**63, "seed", self.seed, "a non-negative integer seed")
        check(1 <= self.threads <= 256, "threads", self.threads, "1 to 256 threads")
        check(1 <= self.jpeg_quality <= 100, "jpeg_quality", self.jpeg_quality, "a JPEG quality in [1, 100]")
        check(self.full_frame_every >= 1, "full_frame_every", self.full_frame_every, "at least 1 frame")
        cam = load_camera()
        check(cam.width_px == cam.height_px and 16 <= self.image.resolution_px <= 4096, "image.resolution_px",
              self.image.resolution_px, "a square image side in [16, 4096] px (the MJCF's chaser_cam, "
              f"{cam.width_px} px, read out at that size: the same field of view)")
        n = self.image.resolution_px  # the camera the run's tracker sees through
        check_min_target_px(self.tracker.integrity.min_target_px, cam.scaled(n, n).f_px,
                            "tracker.integrity.min_target_px")


# what a run takes where its scenario sets nothing (no duration_s, no [measurement] rate_hz)
RUN_FALLBACKS = {"duration_s": lambda: 600.0, "rate_hz": lambda: 1.0, "filter": lambda: FilterConfig(**TRACKER_FILTER)}


def run_stage_types() -> None:
    """Make the annotation "GenerateConfig" resolvable (typing.get_type_hints reads this module's globals): the
    image factory's config is a stage's type, imported when a run is configured, not when the CLI starts."""

    globals()["GenerateConfig"] = GenerateConfig


def finished_image(cfg: RunConfig) -> "GenerateConfig":
    """cfg.image with its sequence fields from the run's (mode, scenario, seed, frames, frame period) and the sun
    made explicit (scenario_sun); a sun already set is kept, so a finished image comes back unchanged
    (RunConfig.__post_init__ runs it on every build), but for the sun another scenario's run put there (the image
    finished for it: `dataclasses.replace(run, scenario=...)`), which is this scenario's again."""
    n = n_frames(cfg)
    sun, before = cfg.image.sun_dir, filled_for(cfg.image)  # the scenario a run finished this image for
    if sun is None or (before not in (UNMARKED, cfg.scenario) and sun == scenario_sun(before)):
        sun = scenario_sun(cfg.scenario)
    sequence = dataclasses.replace(cfg.image.sequence, scenario=cfg.scenario, frame_dt_s=1.0 / cfg.rate_hz)
    return mark_filled(dataclasses.replace(cfg.image, mode="sequence", sequence=sequence, seed=cfg.seed,
                                           num_images=n, shard_size=n, sun_dir=sun), cfg.scenario)


def scenario_sun(scenario: str) -> tuple[float, float, float]:
    """The sun (unit, N) a run of `scenario` takes where none is set: its [eclipse] sun, else DEFAULT_SUN_C0 at
    t = 0 turned into N."""
    ecl = scenario_eclipse(scenario)
    if ecl is not None:
        return tuple(float(v) for v in ecl.sun_dir_N)
    orb = chaser_orbit(scenario_config(scenario).orbit, np.array([0.0]))
    s_C = np.asarray(DEFAULT_SUN_C0) / np.linalg.norm(DEFAULT_SUN_C0)
    return tuple(round(float(v), 9) for v in orb.R_N_from_C[0] @ s_C)


def n_frames(cfg: RunConfig) -> int:
    return int(np.floor(cfg.duration_s * cfg.rate_hz + 1e-9)) + 1


def run_config_from_json(text: str) -> RunConfig:
    run_stage_types()
    return from_dict(RunConfig, json.loads(text))


def sun_and_shadow(cfg: RunConfig, truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: sun_dir_C (N, 3) unit, eclipse (N,) bool (the chaser in the Earth's cylindrical shadow),
    nadir_C (N, 3) the Earth's centre from the chaser, m."""

    orb = chaser_orbit(orbit_config(truth.config), truth.t_s)
    sun_N = np.asarray(cfg.image.sun_dir, dtype=float)
    sun_N = sun_N / np.linalg.norm(sun_N)
    sun_C = np.einsum("nji,j->ni", orb.R_N_from_C, sun_N)
    eclipse = in_earth_shadow(orb.r_N_m, sun_N)
    nadir_C = np.zeros((len(truth.t_s), 3))
    nadir_C[:, 0] = -orb.r_m
    return sun_C, eclipse, nadir_C
