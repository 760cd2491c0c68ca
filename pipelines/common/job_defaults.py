"""What a job's config takes from a named scenario, and what a job needs before any work: the layers under the
config file and the flags that each job config's `from_scenario` resolves (pipelines/jobs.py's resolve_job runs
them by the job's name).

`scenario_defaults`: the tracker's filter under the scenario's [filter] table, its [measurement] table, its
duration and camera rate, the chaser's orbit and the gravity-gradient switch; `with_default_weights` and
`check_weights`: the shipped detector weights where none are named, and the file checked; `run_complete`: a worker
per run up to the cores. Errors name the config field ('weights', 'measurement.rate_hz').
"""

from __future__ import annotations

import os
from typing import Any, Callable

from envisat_pose import named_scenarios
from envisat_pose.config import InputError, field_value
from envisat_pose.pipelines.tracking.tracker_config import TRACKER_FILTER

JOBS = ("simulate", "estimate", "montecarlo", "run", "track")


def scenario_defaults(kind: str, scenario: str) -> dict:
    """What the named scenario sets of a `kind` job's config (under a config file and the overrides). Unknown
    names raise ConfigError listing the known ones; no scenario (None) is an InputError but for an estimate (of a
    truth file), which then takes nothing from one."""
    if scenario is None:
        if kind != "estimate":
            raise InputError(f"scenario: a {kind} job needs a named scenario")
        return {}
    if kind not in JOBS:
        raise ValueError(f"kind {kind!r}: expected one of {', '.join(JOBS)}")
    if kind == "simulate":
        return named_scenarios.truth_part(scenario)
    data = named_scenarios.scenario_tables(scenario)
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


def fill_from_scenario(cfg: Any, kind: str, fallbacks: dict[str, Callable[[], Any]]) -> None:
    """The plain constructor's half of one job: each field of cfg named in fallbacks and left None takes what
    cfg.scenario sets for a `kind` job (scenario_defaults: the layer `from_scenario` puts under the file and the
    flags), or fallbacks[name]() where the scenario sets nothing. So `Cfg(scenario=NAME)` and
    `Cfg.from_scenario(NAME)` are one job; a field given explicitly is kept. Called from a frozen config's
    __post_init__ (its stage types resolvable first)."""
    missing = [name for name in fallbacks if getattr(cfg, name) is None]
    if not missing:
        return
    values = scenario_defaults(kind, cfg.scenario)
    for name in missing:
        value = field_value(type(cfg), name, values[name]) if name in values else fallbacks[name]()
        object.__setattr__(cfg, name, value)


def run_complete(data: dict) -> dict:
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
