"""Named scenarios: the documented TOML files of the package `envisat_pose.scenarios` (the repository's
`scenarios/` folder), listed and read with importlib.resources.

A scenario file holds a one-line `description`, the truth's keys (tables orbit, target, relative; duration_s,
dt_s, max_physics_dt_s, keepout_margin_m: datagen.scenario.ScenarioConfig validates their contents) and optional
tables for the jobs that use the truth: [measurement] and [filter] (the defaults of `estimate` and `montecarlo`
under the user's --config and flags), [sweep] (the filter rates of a rate sweep) and [eclipse] (the sun direction
from which the Earth's shadow is computed). `base = "NAME"` starts from another scenario's tables. A user's own
scenario is a file of the same layout, named by its path (ending in .toml) wherever a scenario name is taken.
Every problem is one ConfigError line naming the file, the key, the value and what was expected.
"""

from __future__ import annotations

import copy
import functools
import importlib.resources
import os
import tomllib

from envisat_pose.config import ConfigError, check, deep_update

PACKAGE = "envisat_pose.scenarios"
# the truth's keys (datagen.scenario.ScenarioConfig's fields but the seed, which is the job's)
TRUTH_KEYS = ("orbit", "target", "relative", "duration_s", "dt_s", "max_physics_dt_s", "keepout_margin_m")
JOB_TABLES = ("measurement", "filter", "sweep", "eclipse")
MAX_BASE_DEPTH = 8


def names() -> list[str]:
    """The known scenario names, sorted (the stems of the package's *.toml files)."""
    return sorted(_files())


@functools.lru_cache(maxsize=1)
def _files() -> dict[str, str]:
    """{name: TOML text} of every scenario file shipped in the package."""
    root = importlib.resources.files(PACKAGE)
    return {e.name[:-5]: e.read_text(encoding="utf-8") for e in root.iterdir() if e.name.endswith(".toml")}


@functools.lru_cache(maxsize=64)
def _parsed(text: str) -> dict:
    """A scenario file's TOML text parsed (cached by the text: a config's build reads its scenario several
    times; callers get a deep copy)."""
    return tomllib.loads(text)


def is_file(name: str) -> bool:
    """Whether `name` is a user's scenario file (a path ending in .toml) rather than a shipped name."""
    return isinstance(name, str) and name.endswith(".toml")


def known(name: str) -> bool:
    """Whether `name` is a shipped scenario or a scenario file that exists (check_name's rule, as a test)."""
    return isinstance(name, str) and (os.path.isfile(name) if is_file(name) else name in _files())


def check_name(name: str) -> None:
    """ConfigError listing the known names unless `name` is one of them or a scenario file that exists."""
    if is_file(name):
        check(os.path.isfile(name), "scenario", name, "a scenario file that exists (a TOML file of the shipped "
              "scenarios' layout: `envisat scenarios --show default`), or one of " + ", ".join(names()))
        return
    check(isinstance(name, str) and name in _files(), "scenario", name,
          "one of " + ", ".join(names()) + ", or a scenario file NAME.toml")


def _text(name: str) -> str:
    if not is_file(name):
        return _files()[name]
    try:
        with open(name, encoding="utf-8") as fh:
            return fh.read()
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError("scenario", name, f"a readable UTF-8 TOML file ({err})") from None


def scenario_tables(name: str) -> dict:
    """The full tables of a named scenario, its `base` chain resolved (without `base`), validated by table name."""
    return _load(name, 0)


def _load(name: str, depth: int) -> dict:
    check_name(name)
    where = f"scenario {name}" if is_file(name) else f"scenario {name} ({name}.toml)"
    try:
        data = copy.deepcopy(_parsed(_text(name)))
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(where, "...", f"valid TOML ({err})") from None
    allowed = ("description", "base") + TRUTH_KEYS + JOB_TABLES
    for key, value in data.items():
        check(key in allowed, f"{where}: {key}", value, "a known key: " + ", ".join(allowed))
    check(isinstance(data.get("description"), str) and data["description"].strip() != "", f"{where}: description",
          data.get("description"), "a one-line description of the case")
    for key in ("orbit", "target", "relative") + JOB_TABLES:
        if key in data:
            check(isinstance(data[key], dict), f"{where}: {key}", data[key], "a table")
    base = data.pop("base", None)
    if base is None:
        return data
    check(depth < MAX_BASE_DEPTH, f"{where}: base", base, f"a chain of at most {MAX_BASE_DEPTH} bases (a cycle?)")
    check(base != name, f"{where}: base", base, "another scenario's name")
    inherited = _load(base, depth + 1)
    inherited.pop("description", None)
    return deep_update(inherited, data)


def truth_part(name: str) -> dict:
    """The truth's keys of a named scenario (overrides of ScenarioConfig's defaults)."""
    return {k: v for k, v in scenario_tables(name).items() if k in TRUTH_KEYS}


def table(name: str, key: str) -> dict:
    """One of the job tables (measurement, filter, sweep, eclipse) of a named scenario; {} if it has none."""
    assert key in JOB_TABLES, key
    return dict(scenario_tables(name).get(key, {}))


def descriptions() -> list[tuple[str, str]]:
    """(name, one-line description) of every scenario, sorted by name."""
    return [(n, " ".join(scenario_tables(n)["description"].split())) for n in names()]
