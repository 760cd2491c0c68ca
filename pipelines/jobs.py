"""A named scenario's job with a config file and flags over it, in one place (as dm_control's `suite.load` turns a
name into an environment): `resolve_job(kind, scenario, config_path, overrides, **fields)` returns the validated
config that `envisat KIND --scenario NAME --config FILE ...` runs.

The one way to build a job's config is its constructor: `RunConfig(scenario=NAME, runs=4)` is the job of
`envisat run --scenario NAME --runs 4` (RunConfig, TrackConfig, EstimateConfig, MonteCarloConfig: each fills
what it takes from its scenario, completes and validates itself when built). resolve_job is what a verb runs:
the constructor's arguments read from a file and flags, with tables merged key by key (a file or a flag sets
part of a table, which a constructor's argument cannot).

The layers, each over the last (job_defaults.layered_job, on config.resolve_job_config): what the job takes from
the named scenario (job_defaults.scenario_defaults: the tracker's filter under the scenario's [filter] table, its
[measurement] table, its duration and camera rate, the chaser's orbit and the gravity-gradient switch); the TOML
file at config_path; the overrides {'section.key': value} (None: not given; a dict value is merged into its
table); the fields (top-level keys). The job's scenario is the one named, whatever the file says. A campaign then
gets its scenario's Earth's-shadow outages once (campaign_config.layered_montecarlo); an estimate gets them along
its truth in run_estimate. The truth of `simulate` is datagen's ScenarioConfig. Errors name the config field
('weights', 'measurement.rate_hz'); the verbs map them onto their flags.
"""

from __future__ import annotations

from typing import Any

from envisat_pose.datagen.scenario import ScenarioConfig
from envisat_pose.pipelines.campaigns.campaign_config import layered_montecarlo
from envisat_pose.pipelines.campaigns.estimate import EstimateConfig
from envisat_pose.pipelines.common.job_defaults import layered_job
from envisat_pose.pipelines.runs.run_config import RunConfig
from envisat_pose.pipelines.runs.track import TrackConfig

_CONFIGS = {"run": RunConfig, "track": TrackConfig, "estimate": EstimateConfig}


def resolve_job(kind: str, scenario: str | None = "default", config_path: str | None = None,
                overrides: dict[str, Any] | None = None, **fields: Any):
    """What a verb runs: the config of a `kind` job ('simulate', 'estimate', 'montecarlo', 'run', 'track'), its
    constructor's arguments read from a file and flags. scenario: the named scenario (None: none, for an estimate
    of a truth file); config_path: a TOML file; overrides: dotted keys (None values skipped); fields: top-level
    keys over them. `resolve_job("run", NAME, runs=4) == RunConfig(scenario=NAME, runs=4)`."""
    if kind == "montecarlo":
        return layered_montecarlo(scenario, config_path, overrides, fields)
    if kind in _CONFIGS:
        return layered_job(_CONFIGS[kind], kind, scenario, config_path, overrides, fields)
    # simulate: the truth's tables and the scenario's name (ScenarioConfig.scenario); an unknown kind raises
    return layered_job(ScenarioConfig, kind, scenario, config_path, overrides, fields)
