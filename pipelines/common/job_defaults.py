"""What a job's config takes from a named scenario, below the job configs (which fill themselves from it when
built) and below pipelines/jobs.py (which layers a file and flags over it).

`scenario_defaults`: the tracker's filter under the scenario's [filter] table, its [measurement] table, its
duration and camera rate, the chaser's orbit and the gravity-gradient switch; `fill_from_scenario`: a config's
fields left None filled from it when the config is built; `layered_job`: the config built from the scenario's
part, a TOML file and flags (what `resolve_job` runs); `default_weights_path`, `weights_file` and `check_weights`:
the shipped detector weights where none are named (another target's: its own beside its file,
`target_weights`), the file a name gives, and the file checked; `weights_name`
and `job_record`: the weights and a job's config as outputs record them (no path of this machine). Errors name
the config field ('weights', 'measurement.rate_hz').
"""

from __future__ import annotations

import filecmp
import os
import warnings
from typing import Any, Callable

from envisat_pose import named_scenarios
from envisat_pose.config import (
    UNMARKED,
    InputError,
    field_value,
    filled_for,
    load_toml,
    mark_filled,
    resolve_job_config,
    to_dict,
)
from envisat_pose.pipelines.tracking.tracker_config import TRACKER_FILTER
from envisat_pose.target import DEFAULT_TARGET, other_target
from envisat_pose.written_target import recorded_target_checked

JOBS = ("simulate", "estimate", "montecarlo", "run", "track")
SHIPPED_WEIGHTS = "models/detector.safetensors"  # the shipped weights as outputs name them (weights_name)


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


def scenario_table(kind: str, name: str) -> Callable[[Any], dict]:
    """A config's `table_bases` entry (config_fields._tables_over_bases): table `name` as cfg.scenario sets it for a
    `kind` job (scenario_defaults), under the keys a dict given for it sets."""
    return lambda cfg: dict(scenario_defaults(kind, cfg.scenario).get(name, {}))


def fill_from_scenario(cfg: Any, kind: str, fallbacks: dict[str, Callable[[], Any]]) -> list[str]:
    """What a job's constructor takes from its scenario: each field of cfg named in fallbacks and left None takes
    what cfg.scenario sets for a `kind` job (scenario_defaults: the layer layered_job puts under the file and
    the flags), or fallbacks[name]() where the scenario sets nothing; a field given explicitly is kept. So
    `Cfg(scenario=NAME, ...)` is the job `resolve_job(KIND, NAME, ...)` builds. The values filled in are marked
    (config.mark_filled), so a config built from one of another scenario (`dataclasses.replace(cfg,
    scenario=...)`) fills them in again (_filled_for_another). Called from a frozen config's __post_init__ (its
    stage types resolvable first); returns the names it filled."""
    missing = [name for name in fallbacks if getattr(cfg, name) is None] + _filled_for_another(cfg, kind, fallbacks)
    if not missing:
        return []
    values = scenario_defaults(kind, cfg.scenario)
    for name in missing:
        value = field_value(type(cfg), name, values[name]) if name in values else fallbacks[name]()
        object.__setattr__(cfg, name, mark_filled(value, cfg.scenario))
    return missing


def _filled_for_another(cfg: Any, kind: str, fallbacks: dict[str, Callable[[], Any]]) -> list[str]:
    """The fields of cfg that a config of another scenario filled in: each value marked as filled from another
    scenario, and where there is one, a switch (a bool cannot be marked) equal to what that scenario sets. A
    value taken from another scenario's config into this one is such a value too: pass a copy of a table
    (`dataclasses.replace(other.filter)`) or `float(other.duration_s)` to give it."""
    marks = {name: filled_for(getattr(cfg, name)) for name in fallbacks}
    stale = [name for name, mark in marks.items() if mark is not UNMARKED and mark != cfg.scenario]
    if not stale:
        return []
    before = scenario_defaults(kind, marks[stale[0]])
    for name in fallbacks:
        value = getattr(cfg, name)
        if isinstance(value, bool) and value == (before[name] if name in before else fallbacks[name]()):
            stale.append(name)
    return stale


def layered_job(cls: type, kind: str, scenario: str | None, config_path: str | None,
                overrides: dict[str, Any] | None, fields: dict[str, Any], base: dict | None = None,
                apart: tuple[str, ...] = ()) -> Any:
    """The config `cls` of a `kind` job built from layers, each over the last: `base` (tables the job always
    gives, {} by default), what the named scenario sets (scenario_defaults), the TOML file at config_path, the
    overrides {'section.key': value} (None: not given; a dict value merges into its table) and the fields
    (top-level keys). The job's scenario is `scenario`, whatever the file says; the target file's sha256 that a
    written config records is set aside, the file checked against it (written_target.recorded_target_checked: a
    rerun from the config refuses the file once it changed). Built by from_dict through the
    constructor, which completes and validates it; the implementation of pipelines.jobs.resolve_job (and of the
    deprecated `Cfg.from_scenario`). The fields the scenario alone set (no file key or flag under them) are
    marked as filled from it (config.mark_filled), as the constructor marks what it fills in: a replace with
    another scenario fills them in again, whichever way the config was built. apart: the file's tables that
    another part of the job reads, not `cls` (a montecarlo file's [sweep]: pipelines.campaigns.sweep.sweep_for)."""

    def named(data: dict) -> dict:
        data = {key: value for key, value in data.items() if key not in apart}
        return recorded_target_checked(config_path, kind)({**data, "scenario": scenario})

    defaults = {**(base or {}), **scenario_defaults(kind, scenario)}
    flags = {**(overrides or {}), **fields}
    cfg = resolve_job_config(cls, defaults, config_path, flags, named)
    touched = {key.split(".")[0] for key, value in flags.items() if value is not None}
    if config_path:
        data = load_toml(config_path)
        warn_other_scenario(data.get("scenario"), scenario, config_path)
        touched |= set(data)
    for name in set(defaults) - touched - {"scenario"}:
        object.__setattr__(cfg, name, mark_filled(getattr(cfg, name), scenario))
    return cfg


def warn_other_scenario(in_file: Any, scenario: str | None, config_path: str) -> None:
    """A warning where a config file names another scenario than the job's (a --scenario over a run's written
    config, say): the file's other tables apply, its scenario does not."""
    if in_file is not None and in_file != scenario:
        import warnings

        job = f"runs scenario {scenario!r}" if scenario is not None else "takes no named scenario"
        warnings.warn(f"{config_path}: its scenario = {in_file!r} is not this job's; the job {job} with the file's "
                      "other settings", stacklevel=3)


def default_weights_path() -> str:
    """The shipped detector weights (perception.weights.shipped_weights_path); an error naming the path when absent.
    The first call imports torch (the weights' module)."""
    from envisat_pose.perception.weights import shipped_weights_path

    return shipped_weights_path()


def models_folder() -> str:
    """The package's models folder (package data envisat_pose.models: the shipped weights and target files)."""
    import importlib.resources

    return str(importlib.resources.files("envisat_pose.models"))


def weights_file(given: str) -> str:
    """The file a `weights` value names, as a target file is found (envisat_pose.target.resolve_target_path): "" and
    SHIPPED_WEIGHTS are the shipped weights (default_weights_path; a different file of that relative name in the
    working folder gets a warning saying how to name it); any other path is taken as it is (relative to the working
    folder), or, when no such file exists and it starts with 'models/', the package's models folder's."""
    if not given or given == SHIPPED_WEIGHTS:
        path = default_weights_path()
        if given and os.path.isfile(given) and not filecmp.cmp(given, path, shallow=False):
            warnings.warn(f"weights {given!r} are the shipped weights; the other file of that name in this folder is "
                          f"not used: give it as {os.path.join('.', given)!r}", stacklevel=2)
        return path
    if not os.path.exists(given) and given.startswith("models/"):
        packaged = os.path.join(models_folder(), given[len("models/"):])
        if os.path.exists(packaged):
            return packaged
    return given


def weights_name(path: str) -> str:
    """A weights file as an output records it: a file of the package's models folder (the shipped weights:
    SHIPPED_WEIGHTS) as 'models/FILE', which weights_file finds on any machine (no path of this one); any other by
    its path as given."""
    real = os.path.realpath(path)
    if os.path.dirname(real) == os.path.realpath(models_folder()):
        return "models/" + os.path.basename(real)
    return path


def check_weights(path: str, target: str = DEFAULT_TARGET) -> None:
    """InputError naming the field `weights` when the file does not exist, holds the detector of another target
    than `target` (the job's MJCF file; one line naming both: perception.weights.check_weights_target), or, for
    another target than ENVISAT, was never calibrated (the tracker weighs each keypoint by its calibrated sigma:
    perception.keypoint_detect.require_calibrated). The header only, with torch imported, before any work."""
    if not os.path.isfile(path):
        raise InputError(f"weights {path!r}: no such file")
    from envisat_pose.perception.weights import check_weights_target  # torch

    check_weights_target(path, target, named=weights_name(path))  # a package file as models/FILE: no machine path
    if other_target(target) is not None:
        from envisat_pose.perception.keypoint_detect import require_calibrated

        require_calibrated(path, target)


def job_weights(weights: str, target: str = DEFAULT_TARGET) -> str:
    """A job's weights file as its config holds it (weights_file): "" is the target's default (target_weights:
    ENVISAT's shipped corner network, another target's own detector beside its file), and the file is checked
    (check_weights) before any work."""
    path = weights_file(target_weights(weights, target))
    check_weights(path, target)
    return path


def job_record(cfg: Any) -> dict:
    """A job's config as its outputs record it (to_dict): its weights named by weights_name (the shipped ones as
    SHIPPED_WEIGHTS, no path of this machine), which the job's config takes back."""
    data = to_dict(cfg)
    data["weights"] = weights_name(data["weights"])
    return data


def target_weights(weights: str, target: str) -> str:
    """The `weights` value a job of `target` (its MJCF file as given) runs: the one given, else the target's
    default: ENVISAT's shipped weights ("") for ENVISAT, another target's own detector beside its file
    (perception.weights.default_target_weights; refused in one line where none fits it)."""
    if weights or other_target(target) is None:
        return weights
    from envisat_pose.perception.weights import default_target_weights  # torch

    return default_target_weights(target)
