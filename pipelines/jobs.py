"""A named scenario resolved into a complete job, in one place (as dm_control's `suite.load` turns a name into an
environment): `resolve_job(kind, scenario, config_path, overrides)` returns the validated config that the verb of
the same name runs, and each job's config has it as `Cfg.from_scenario(name, ...)` (RunConfig, TrackConfig,
EstimateConfig, MonteCarloConfig; the truth of `simulate` is datagen's ScenarioConfig).

The layers, each over the last (config.resolve_job_config): the config class's defaults; what the job takes from
the named scenario (pipelines/common/job_defaults.py's `scenario_defaults`: the tracker's filter under the scenario's [filter] table, its
[measurement] table, its duration and camera rate, the chaser's orbit and the gravity-gradient switch); the TOML
file at config_path; the overrides {'section.key': value} (None: not given; a dict value is merged into its
table). Then what the job needs before any work: the shipped detector weights where none are named (and the file
checked), a worker per run up to the cores (run), the image factory's sequence fields and the sun (run,
run_config.finish_config), the Earth's-shadow outages of a scenario with an [eclipse] table (montecarlo,
campaign_config.with_eclipse; estimate adds them along its truth in run_estimate).

The config classes resolve themselves from the layers of pipelines/common/job_defaults.py, below them and below this
module, which alone knows every job by its name. Errors name the config field ('weights', 'measurement.rate_hz'); the verbs map them onto their flags.
"""

from __future__ import annotations

from typing import Any

from envisat_pose.config import resolve_job_config
from envisat_pose.datagen.scenario import ScenarioConfig
from envisat_pose.pipelines.campaigns.campaign_config import MonteCarloConfig
from envisat_pose.pipelines.campaigns.estimate import EstimateConfig
from envisat_pose.pipelines.common.job_defaults import JOBS, scenario_defaults
from envisat_pose.pipelines.runs.run_config import RunConfig
from envisat_pose.pipelines.runs.track import TrackConfig


def resolve_job(kind: str, scenario: str | None = "default", config_path: str | None = None,
                overrides: dict[str, Any] | None = None, **fields: Any):
    """The validated config of a `kind` job ('simulate', 'estimate', 'montecarlo', 'run', 'track') for a named
    scenario (None: none, for an estimate of a truth file), a TOML file and overrides (dotted keys, None values
    skipped) with `fields` (top-level keys) over them: what `envisat KIND --scenario NAME --config FILE ...` runs.
    Each job but simulate is its config class's `from_scenario`."""
    if kind in JOBS and kind != "simulate":
        return _config_class(kind).from_scenario(scenario, config_path, overrides, **fields)

    defaults = scenario_defaults(kind, scenario)  # the truth's tables; no scenario or an unknown kind raises
    return resolve_job_config(ScenarioConfig, defaults, config_path, {**(overrides or {}), **fields})


def _config_class(kind: str) -> type:
    if kind == "estimate":
        return EstimateConfig
    if kind == "montecarlo":
        return MonteCarloConfig
    if kind == "track":
        return TrackConfig

    return RunConfig
