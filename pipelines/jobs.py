"""A named scenario resolved into a complete job, in one place (as dm_control's `suite.load` turns a name into an
environment): `resolve_job(kind, scenario, config_path, overrides)` returns the validated config that the verb of
the same name runs, and each job's config has it as `Cfg.from_scenario(name, ...)` (RunConfig, TrackConfig,
EstimateConfig, MonteCarloConfig; the truth of `simulate` is datagen's ScenarioConfig).

The layers, each over the last (config.resolve_job_config): the config class's defaults; what the job takes from
the named scenario (`scenario_defaults`: the tracker's filter under the scenario's [filter] table, its
[measurement] table, its duration and camera rate, the chaser's orbit and the gravity-gradient switch); the TOML
file at config_path; the overrides {'section.key': value} (None: not given; a dict value is merged into its
table). Then what the job needs before any work: the shipped detector weights where none are named (and the file
checked), a worker per run up to the cores (run), the image factory's sequence fields and the sun (run,
run_config.finish_config), the Earth's-shadow outages of a scenario with an [eclipse] table (montecarlo,
campaign_config.with_eclipse; estimate adds them along its truth in run_estimate).

Errors name the config field ('weights', 'measurement.rate_hz'); the verbs map them onto their flags.
"""

from __future__ import annotations

import os
from typing import Any

from envisat_pose import named_scenarios
from envisat_pose.config import InputError, resolve_job_config

JOBS = ("simulate", "estimate", "montecarlo", "run", "track")


def scenario_defaults(kind: str, scenario: str) -> dict:
    """What the named scenario sets of a `kind` job's config (under a config file and the overrides). Unknown
    names raise ConfigError listing the known ones."""
    from envisat_pose.pipelines.tracker import TRACKER_FILTER

    if kind not in JOBS:
        raise ValueError(f"kind {kind!r}: expected one of {', '.join(JOBS)}")
    if kind == "simulate":
        return named_scenarios.truth_part(scenario)
    data = named_scenarios.load(scenario)
    tables = {k: dict(data[k]) for k in ("measurement", "filter") if k in data}
    if kind == "estimate":
        return tables
    if kind == "montecarlo":
        return tables | ({"duration_s": data["duration_s"]} if "duration_s" in data else {})
    out: dict = {"scenario": scenario, "filter": {**TRACKER_FILTER, **tables.get("filter", {})}}
    if kind == "track":
        truth = named_scenarios.truth_part(scenario)
        return out | {"orbit": dict(truth.get("orbit", {})),
                      "gravity_gradient": bool(truth.get("target", {}).get("gravity_gradient", False))}
    if "duration_s" in data:
        out["duration_s"] = data["duration_s"]
    if "rate_hz" in tables.get("measurement", {}):  # the camera runs at the scenario's measurement rate
        out["rate_hz"] = tables["measurement"]["rate_hz"]
    return out


def resolve_job(kind: str, scenario: str | None = "default", config_path: str | None = None,
                overrides: dict[str, Any] | None = None, **fields: Any):
    """The validated config of a `kind` job ('simulate', 'estimate', 'montecarlo', 'run', 'track') for a named
    scenario (None: none, for an estimate of a truth file), a TOML file and overrides (dotted keys, None values
    skipped) with `fields` (top-level keys) over them: what `envisat KIND --scenario NAME --config FILE ...` runs."""
    flags = {**(overrides or {}), **fields}
    if scenario is None:
        if kind != "estimate":
            raise InputError(f"scenario: a {kind} job needs a named scenario")
        defaults: dict = {}
    else:
        defaults = scenario_defaults(kind, scenario)
    cls = _config_class(kind)
    if kind == "simulate":
        return resolve_job_config(cls, defaults, config_path, flags)
    if kind == "estimate":
        return resolve_job_config(cls, defaults, config_path, flags)
    flags["scenario"] = scenario  # the named scenario is the job's, whatever the file says
    if kind == "montecarlo":
        from envisat_pose.pipelines.campaign_config import with_eclipse

        return with_eclipse(resolve_job_config(cls, defaults, config_path, flags))
    if kind == "track":
        cfg = resolve_job_config(cls, defaults, config_path, flags, with_default_weights)
        check_weights(cfg.weights)
        return cfg
    from envisat_pose.pipelines.run_config import finish_config

    cfg = resolve_job_config(cls, defaults, config_path, flags, _run_complete)
    check_weights(cfg.weights)
    return finish_config(cfg)


def _config_class(kind: str) -> type:
    if kind == "simulate":
        from envisat_pose.datagen.scenario import ScenarioConfig

        return ScenarioConfig
    if kind == "estimate":
        from envisat_pose.pipelines.estimate import EstimateConfig

        return EstimateConfig
    if kind == "montecarlo":
        from envisat_pose.pipelines.campaign_config import MonteCarloConfig

        return MonteCarloConfig
    if kind == "track":
        from envisat_pose.pipelines.track import TrackConfig, stage_types

        stage_types()
        return TrackConfig
    from envisat_pose.pipelines.run_config import RunConfig, stage_types

    stage_types()
    return RunConfig


def _run_complete(data: dict) -> dict:
    """A run's values that depend on others: one worker per run, at most one per core; the shipped weights."""
    if "workers" not in data:
        runs = data.get("runs", 1)
        data["workers"] = max(1, min(runs if isinstance(runs, int) else 1, os.cpu_count() or 1))
    return with_default_weights(data)


def default_weights_path() -> str:
    """The shipped detector weights (perception.weights.shipped_weights_path); an error naming the path when absent."""
    from envisat_pose.perception.weights import shipped_weights_path

    return shipped_weights_path()


def with_default_weights(data: dict) -> dict:
    """A config dict with the shipped weights where it names none (the run and track jobs' default)."""
    if not data.get("weights"):
        data["weights"] = default_weights_path()
    return data


def check_weights(path: str) -> None:
    """InputError naming the field `weights` when the file does not exist (before any work)."""
    if not os.path.isfile(path):
        raise InputError(f"weights {path!r}: no such file")
