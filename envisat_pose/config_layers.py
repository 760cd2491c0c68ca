"""A config's layers: TOML files read and written, tables merged key by key, and `resolve_job_config`, which
builds one job's config from its defaults, then a TOML file, then command-line overrides."""

from __future__ import annotations

import dataclasses
import json
import re
import tomllib
from typing import Any, Callable

from envisat_pose.config_errors import InputError
from envisat_pose.config_fields import from_dict


def load_toml(path: str, what: str = "config file") -> dict:
    """Read a TOML file; a missing or malformed file is an InputError naming the file (as `what`: "config file",
    or the argument that gave it, such as "camera") and the problem."""
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(f"{what} {path!r} does not exist") from None
    except IsADirectoryError:
        raise InputError(f"{what} {path!r} is a directory, expected a TOML file") from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"{what} {path!r} is not valid TOML: {err}{_toml_line(path, str(err))}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{what} {path!r} cannot be read: {err}") from None


def _toml_line(path: str, message: str) -> str:
    """'; line N reads ...' for tomllib's message naming line N (a key given twice: 'Cannot overwrite a value')."""
    at = re.search(r"\(at line (\d+), column \d+\)", message)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read().splitlines()[int(at.group(1)) - 1].strip() if at else ""
    except (OSError, UnicodeDecodeError, IndexError):
        return ""
    return f"; line {at.group(1)} reads {text[:80]!r}" if text else ""



def to_dict(obj: Any) -> dict:
    """A config as plain JSON-able data."""
    return json.loads(json.dumps(dataclasses.asdict(obj)))


def to_json(obj: Any) -> str:
    """A config as a JSON string (the `config_json` written next to every output)."""
    return json.dumps(dataclasses.asdict(obj), sort_keys=True)


def to_toml(data: dict, prefix: str = "") -> str:
    """A small TOML writer for configs (tables of numbers, strings, booleans and lists)."""
    scalars, tables = [], []
    for key, value in data.items():
        if isinstance(value, dict):
            tables.append((key, value))
        elif value is None:
            scalars.append(f"# {key} = (unset)")
        else:
            scalars.append(f"{key} = {json.dumps(value)}")
    text = "\n".join(scalars) + ("\n" if scalars else "")
    for key, value in tables:
        name = f"{prefix}{key}"
        text += f"\n[{name}]\n" + to_toml(value, prefix=name + ".")
    return text


def deep_update(base: dict, update: dict) -> dict:
    """Recursive dict merge: values of `update` win; tables merge key by key."""
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_update(out[key], value)
        else:
            out[key] = value
    return out


def flatten(data: dict, prefix: str = "") -> dict:
    """{'a.b': value} of a nested dict (tables key by key; the inverse of set_dotted's paths)."""
    out: dict = {}
    for key, value in data.items():
        out.update(flatten(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return out


def set_dotted(data: dict, dotted: str, value: Any) -> dict:
    """Return a copy of `data` with `a.b.c` set to value (used for command-line overrides)."""
    parts = dotted.split(".")
    update: dict = {}
    node = update
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value
    return deep_update(data, update)


def resolve_job_config(cls: type, defaults: dict, config_path: str | None, flags: dict[str, Any],
                       complete: Callable[[dict], dict] | None = None, prefix: str = "") -> Any:
    """The layers of a config: the dataclass `cls` built (by `from_dict`, through its constructor) from its
    defaults, then `defaults`, then the TOML file at config_path (if any), then the flags {'section.key': value}
    (None values are flags not given); tables merge key by key, so a file or a flag sets part of a table. The
    loader of the verbs without a named scenario (generate, detect, calibrate, train) and of the layers under
    `pipelines.jobs.resolve_job`, which is what the verbs of a scenario's job run.

    complete(data) -> data, if given, runs on the merged data before it is built (a job's named scenario set
    over whatever the file says, say). prefix: where the config sits in a larger one,
    for the error messages ('sweep').
    """
    data = deep_update({}, defaults)
    if config_path:
        data = deep_update(data, load_toml(config_path))
    for key, value in flags.items():
        if value is not None:
            data = set_dotted(data, key, value)
    if complete is not None:
        data = complete(data)
    return from_dict(cls, data, prefix=prefix)
