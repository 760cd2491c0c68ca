"""One validated config per job: defaults, then a TOML file, then command-line overrides.

Every problem raises ConfigError naming the field, the value and what was expected, before any work starts. The
names live in modules of one job each, and are all importable from here, as they always were:

- config_errors: ConfigError, MovedKeyError, InputError, DeprecatedKeyWarning (a renamed key's old name), and
  `check` (a validate()'s one-line range check);
- config_fields: the base class `Config` (validated when built: the constructor, `dataclasses.replace` and
  `from_dict` alike), the type checks of its fields, `from_dict` and `field_value`, `renamed_fields` (a field's
  old name kept one release), and the marks of what a config filled in itself (Derived, DerivedInt, derived,
  mark_filled, filled_for, UNMARKED);
- config_layers: TOML read (`load_toml`) and written (`to_toml`, `to_dict`, `to_json`), tables merged
  (`deep_update`, `set_dotted`, `flatten`), and `resolve_job_config`, the layers of one job's config;
- config_args: a library function's arguments checked (`path_arg`, `paths_arg`, `rrd_arg`, `config_arg`,
  `as_path_or_object`).
"""

from __future__ import annotations

from envisat_pose.config_args import as_path_or_object, config_arg, path_arg, paths_arg, rrd_arg
from envisat_pose.config_errors import ConfigError, DeprecatedKeyWarning, InputError, MovedKeyError, check
from envisat_pose.config_fields import (
    UNMARKED,
    Config,
    Derived,
    DerivedInt,
    derived,
    field_value,
    filled_for,
    from_dict,
    mark_filled,
    renamed_fields,
)
from envisat_pose.config_layers import (
    deep_update,
    flatten,
    load_toml,
    resolve_job_config,
    set_dotted,
    to_dict,
    to_json,
    to_toml,
)

__all__ = [
    "UNMARKED", "Config", "ConfigError", "DeprecatedKeyWarning", "Derived", "DerivedInt", "InputError", "MovedKeyError",
    "as_path_or_object", "check", "config_arg", "deep_update", "derived", "field_value", "filled_for", "flatten",
    "from_dict", "load_toml", "mark_filled", "path_arg", "paths_arg", "renamed_fields", "resolve_job_config", "rrd_arg",
    "set_dotted", "to_dict", "to_json", "to_toml",
]
