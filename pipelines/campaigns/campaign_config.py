"""The config of a Monte Carlo campaign (`envisat montecarlo`, pipelines/campaigns/campaign.py) and what it resolves to
before any work: the truth's scenario (truth_scenario), the filter's rate checked against it (check_filter_rate) and
a scenario's Earth's-shadow outages (with_eclipse)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from envisat_pose.config import Config, ConfigError, check, filled_for, mark_filled
from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.filtering.montecarlo import MeasurementConfig, filter_stride
from envisat_pose.pipelines.campaigns.estimate import check_init_error_scale, eclipse_outages, with_outages
from envisat_pose.pipelines.common.job_defaults import fill_from_scenario, layered_job
from envisat_pose.target import load_target


@dataclass(frozen=True)
class MonteCarloConfig(Config):
    """One campaign, complete and validated when built: `MonteCarloConfig(scenario=NAME, runs=4)` is the job of
    `envisat montecarlo --scenario NAME --runs 4` (pipelines.jobs.resolve_job adds a config file and flags). The
    results' bytes depend on every field (block_runs fixes the order of the sums).

    scenario: named truth scenario. target: the target's MJCF file (None: the scenario's; the filter measures its
    keypoints with its inertia, the bound likewise). duration_s: simulated time, s. runs: Monte Carlo runs. seed: root seed (the
    truth's initial attitude and run r's draws, SeedSequence(seed, spawn_key=(r,))). block_runs: runs per task.
    settle_s: the statistics of summary.json use the steps at or after t0 + settle_s (None: half the duration,
    at most 600 s). sample_runs: the first runs whose errors are kept for the figures' grey curves. duration_s,
    measurement and filter left None take the scenario's when the config is made (job_defaults.fill_from_scenario:
    its duration, [measurement] and [filter] tables, else 1800 s and the classes' defaults; the measurement with
    the scenario's Earth's-shadow outages along this truth, with_eclipse). A measurement given is kept as it is
    (resolve_job adds the outages to the one a file and flags make: with_eclipse once). init_error_scale: each
    run's initial error is drawn from N(0, init_error_scale^2 P0) while the filter is told P0 (1: consistent).
    """

    scenario: str = "default"
    duration_s: float | None = None
    runs: int = 100
    seed: int = 0
    block_runs: int = 125
    settle_s: float | None = None
    sample_runs: int = 20
    target: str | None = None
    measurement: MeasurementConfig | None = None
    filter: FilterConfig | None = None
    init_error_scale: float = 1.0

    def __post_init__(self) -> None:
        if filled_for(self.measurement) == self.scenario:  # its outages follow this truth (duration, seed, target)
            object.__setattr__(self, "measurement", None)
        eclipse = "measurement" in fill_from_scenario(self, "montecarlo", MONTECARLO_FALLBACKS)
        super().__post_init__()
        if eclipse:  # the scenario's measurement, with its outages along the (validated) truth
            windows = eclipse_outages(self.scenario, truth_scenario(self))
            object.__setattr__(self, "measurement", mark_filled(with_outages(self.measurement, windows), self.scenario))

    @classmethod
    def from_scenario(cls, name: str = "default", config_path: str | None = None, overrides: dict | None = None,
                      **fields) -> "MonteCarloConfig":
        """Deprecated (goes in the next release): MonteCarloConfig(scenario=NAME, ...), or
        pipelines.jobs.resolve_job("montecarlo", NAME, config_path, overrides, ...) for a config file and dotted
        flags; this is the latter."""
        warnings.warn("MonteCarloConfig.from_scenario is deprecated and goes in the next release: use "
                      "MonteCarloConfig(scenario=NAME, ...) (or pipelines.jobs.resolve_job for a config file)",
                      DeprecationWarning, stacklevel=2)
        return layered_montecarlo(name, config_path, overrides, fields)

    def validate(self, prefix: str = "") -> None:
        check(0 < self.duration_s < math.inf, "duration_s", self.duration_s, "a positive, finite duration in seconds")
        check(1 <= self.runs <= 1_000_000, "runs", self.runs, "a number of runs from 1 to 1000000")
        check(0 <= self.seed < 2**63, "seed", self.seed, "a non-negative integer seed")
        check(1 <= self.block_runs <= 10_000, "block_runs", self.block_runs, "an integer from 1 to 10000")
        check(self.settle_s is None or 0 <= self.settle_s < self.duration_s, "settle_s", self.settle_s,
              f"a time in [0, duration_s = {self.duration_s:g}) s")
        check(0 <= self.sample_runs <= 200, "sample_runs", self.sample_runs, "an integer from 0 to 200")
        check_init_error_scale(self.init_error_scale, self.filter.p0_sigma)
        if self.target is not None:
            load_target(self.target, "target")  # a bad file: one line before any work
        rate = self.measurement.rate_hz  # the statistics need a filter step at or after the settle time
        last_s = math.floor(self.duration_s * rate + 1e-9) / rate
        if self.settle_s is not None:
            check(self.settle_time_s <= last_s, "settle_s", self.settle_s, f"a time at or before the last filter step, "
                  f"{last_s:g} s ({rate:g} Hz over duration_s = {self.duration_s:g})")
        check(self.settle_time_s <= last_s, "duration_s", self.duration_s, f"a duration whose filter steps ({rate:g} "
              f"Hz) reach past its settle time {self.settle_time_s:g} s (half of it, at most 600 s)")
        # max_markers within the truth's target's keypoints, before a folder is made
        self.measurement.check_keypoints(len(load_target(truth_scenario(self).target.file).keypoint_names))

    @property
    def settle_time_s(self) -> float:
        return float(self.settle_s) if self.settle_s is not None else min(600.0, 0.5 * self.duration_s)

    @property
    def n_blocks(self) -> int:
        return -(-self.runs // self.block_runs)

    def block_range(self, b: int) -> tuple[int, int]:
        """Runs [start, stop) of block b."""
        return b * self.block_runs, min(self.runs, (b + 1) * self.block_runs)


# what a campaign takes where its scenario sets nothing
MONTECARLO_FALLBACKS = {"duration_s": lambda: 1800.0, "measurement": MeasurementConfig, "filter": FilterConfig}


def layered_montecarlo(scenario: str, config_path: str | None, overrides: dict | None, fields: dict):
    """The campaign of pipelines.jobs.resolve_job("montecarlo", ...): the layers (job_defaults.layered_job; the
    measurement always given there, the scenario's table under the file's and the flags') and the scenario's
    Earth's-shadow outages added to it once (with_eclipse), as the plain constructor adds them to the
    scenario's measurement. The file's [sweep] table (a rate sweep's written config) is the sweep's
    (pipelines.campaigns.sweep.sweep_for), not the campaign's."""
    import dataclasses

    try:
        cfg = layered_job(MonteCarloConfig, "montecarlo", scenario, config_path, overrides, fields,
                          base={"measurement": {}}, apart=("sweep",))
    except ConfigError as err:
        if err.field != "target" or not isinstance(err.value, dict):
            raise
        # a simulate-style [target] table: the campaign's target is a file path; the table is a scenario file's
        raise ConfigError("target", err.value, f"{err.expected}; a [target] table belongs in a scenario file, "
                          "given as `--scenario FILE.toml` (or the MJCF file alone as `--target FILE.xml`)") from None
    if filled_for(cfg.measurement) == cfg.scenario:  # the scenario's table alone: filled in, outages and all
        return dataclasses.replace(cfg)
    return with_eclipse(cfg)


def with_eclipse(cfg: MonteCarloConfig) -> MonteCarloConfig:
    """cfg with its scenario's Earth's-shadow windows (if it has an [eclipse] table) appended to the outages
    (pipelines.estimate.eclipse_outages), but for those already among them (with_outages: a rerun of a written
    montecarlo.config.toml, which holds them, gets them once)."""
    import dataclasses

    windows = eclipse_outages(cfg.scenario, truth_scenario(cfg))
    return dataclasses.replace(cfg, measurement=with_outages(cfg.measurement, windows))


def truth_scenario(cfg: MonteCarloConfig):
    """The validated ScenarioConfig of the campaign's truth (the filter's rate above 1 Hz refines its step)."""

    overrides: dict = {"seed": cfg.seed, "duration_s": cfg.duration_s}
    if cfg.target is not None:
        overrides["target"] = {"file": cfg.target}
    if cfg.measurement.rate_hz > 1.0:
        overrides["dt_s"] = 1.0 / cfg.measurement.rate_hz
    return scenario_config(cfg.scenario, **overrides)


def check_filter_rate(cfg: MonteCarloConfig, scenario) -> None:
    """The filter's period must be a whole number of the truth's sample steps (before any work)."""

    try:
        filter_stride(np.array([0.0, scenario.dt_s]), cfg.measurement.rate_hz)
    except ValueError as err:
        raise ConfigError("measurement.rate_hz", cfg.measurement.rate_hz, str(err)) from None


def campaign_target_record(cfg: MonteCarloConfig) -> dict:
    """The campaign's target as its summaries record it: its name (the MJCF model's), sha256 and keypoint names
    (not the path as given: a resume may name the same file from another folder)."""
    given = truth_scenario(cfg).target.file
    return {k: v for k, v in load_target(given).record(given).items() if k != "file"}


def runs_words(n: int) -> str:
    """'1 run', '2 runs': a count of Monte Carlo runs as the verbs' lines and the figures' titles say it."""
    return f"{n} run" if n == 1 else f"{n} runs"


def campaign_title(cfg: MonteCarloConfig, runs: str) -> str:
    """The head of a campaign's figure titles: the target's name (its MJCF model), the scenario, `runs` (e.g. '100
    runs'), the measurement and its noise."""
    m = cfg.measurement
    noise = f"{m.sigma_m:g} m" if m.kind == "markers3d" else f"{m.sigma_px:g} px"
    target = load_target(truth_scenario(cfg).target.file).name
    return f"{target}, scenario {cfg.scenario}: {runs}, {m.kind} at {noise}"
