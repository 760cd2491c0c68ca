"""A written config's record of its target file: each verb whose written config names a target file (TARGET_KEYS)
records the file's sha256 beside it (with_target_sha256), as a truth records it (target.sha256), and a rerun from
that config (`--config`) refuses the file once it changed since (recorded_target_checked): another body than the
one the job ran on. Another target file given over the config's is taken as it is.
"""

from __future__ import annotations

import os
from typing import Any, Callable

from envisat_pose.config import InputError, load_toml
from envisat_pose.target import resolve_target_path
from envisat_pose.target_assets import target_sha256

# where each verb's config names its target file, and the key beside it that records the file's sha256 (a
# campaign's `target` None names none: the scenario's own; train's: another target's keypoint run alone;
# estimate's config names none at all)
TARGET_KEYS = {"simulate": ("target.file", "target.sha256"), "run": ("image.target", "image.target_sha256"),
               "track": ("target", "target_sha256"), "montecarlo": ("target", "target_sha256"),
               "generate": ("target", "target_sha256"), "train": ("target", "target_sha256")}


def _value(data: dict, dotted: str) -> Any:
    """data's value at a dotted key ('image.target'); None where it has none."""
    for key in dotted.split("."):
        if not isinstance(data, dict):
            return None
        data = data.get(key)
    return data


def _with(data: dict, dotted: str, value: Any = None, drop: bool = False) -> dict:
    """A copy of data with `value` at a dotted key (drop: the key taken out), its tables copied along the way."""
    head, _, rest = dotted.partition(".")
    if rest:
        return {**data, head: _with(dict(data.get(head) or {}), rest, value, drop)}
    return {k: v for k, v in data.items() if k != head} if drop else {**data, head: value}


def with_target_sha256(data: dict, kind: str, sha256: str | None) -> dict:
    """data (a `kind` job's config, config.to_dict) as its written config holds it: the target file's sha256 as the
    job read it (target_assets.target_sha256: its bytes and those of the files it names) beside the file it names
    (TARGET_KEYS), which a rerun from that config checks (recorded_target_checked); data as it is where it names
    no file."""
    file_key, sha_key = TARGET_KEYS[kind]
    if sha256 is None or not isinstance(_value(data, file_key), str):
        return data
    return _with(data, sha_key, sha256)


def recorded_target_checked(config_path: str | None, kind: str) -> Callable[[dict], dict]:
    """The last layer of a `kind` job read from a config file (config.resolve_job_config's complete): the target
    file's sha256 that the written config records (with_target_sha256) set aside, and, where the job takes the file
    the record names (the config's own, no other given over it), the file checked against it: InputError in one
    line when it changed since (another body than the one the job ran on then), as a truth's is. A job whose
    config names no target file (not in TARGET_KEYS) is passed on as it is."""

    def complete(data: dict) -> dict:
        if kind not in TARGET_KEYS:
            return data
        file_key, sha_key = TARGET_KEYS[kind]
        recorded = _value(data, sha_key)
        if recorded is None:
            return data
        data = _with(data, sha_key, drop=True)
        given = _value(data, file_key)
        in_file = _value(load_toml(config_path), file_key) if config_path else None
        path = resolve_target_path(given) if isinstance(given, str) else ""
        if given == in_file and os.path.isfile(path) and target_sha256(path) != recorded:
            table, _, key = sha_key.rpartition(".")
            line = f"the {key} line of its [{table}] table" if table else f"its {key} line"
            raise InputError(f"{config_path}: its target file {given!r} changed since the config was written (sha256 "
                             f"{target_sha256(path)[:12]}..., the config recorded {str(recorded)[:12]}...); to "
                             f"use the file as it is now, delete {line}")
        return data

    return complete
