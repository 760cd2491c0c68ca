"""A generated dataset's own target file, as a verb that reads the target takes it: found from here (the path its
manifest records, or one given in its place) and unchanged since the dataset was generated (its sha256)."""

from __future__ import annotations

import os

from envisat_pose.config import InputError
from envisat_pose.target import DEFAULT_TARGET, resolve_target_path
from envisat_pose.target_assets import target_sha256


def check_dataset_target_file(src: str, manifest: dict, target: str | None) -> None:
    """The dataset's target file (`target`, or else the path its config records) is found from here and its
    sha256 is the one the manifest recorded: InputError in one line saying which file to give, never an error of
    a generate config built on another target."""
    given = target if target is not None else (manifest.get("config") or {}).get("target", DEFAULT_TARGET)
    if not isinstance(given, str):
        return  # not a path: the config's own check names it
    path = resolve_target_path(given)
    if not os.path.isfile(path):
        if target is None:
            raise InputError(f"src {src!r}: its target file {given!r} (the path its manifest.json records) is not "
                             "found from here: give that file with `target`")
        raise InputError(f"target {target!r}: no such file; expected the dataset's target file (MJCF)")
    record = manifest.get("target") or {}
    recorded = record.get("sha256")
    digest = target_sha256(path)
    if recorded is None or digest == recorded:
        return
    if target is None:
        raise InputError(f"src {src!r}: its target file {given!r} changed since the dataset was generated "
                         f"(sha256 {digest[:12]}..., the manifest recorded {recorded[:12]}...)")
    raise InputError(f"target {target!r}: not the target file of the dataset {src!r} (sha256 {digest[:12]}..., its "
                     f"manifest recorded {recorded[:12]}... for {record.get('name')!r}, file "
                     f"{record.get('file')!r}); expected that file, unchanged since the dataset was generated")
