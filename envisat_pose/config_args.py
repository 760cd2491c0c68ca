"""A library function's arguments checked at its boundary: paths (a str or a pathlib.Path) and configs."""

from __future__ import annotations

import os
from typing import Any

from envisat_pose.config_errors import InputError


def path_arg(value: Any, field: str, optional: bool = False) -> str | None:
    """A library function's path argument as a string: a str or an os.PathLike (pathlib.Path) taken alike;
    None where optional; InputError naming the argument otherwise."""
    if value is None and optional:
        return None
    if isinstance(value, (str, os.PathLike)):
        return os.fspath(value)
    raise InputError(f"{field} = {value!r}: expected a path (a str or a pathlib.Path)")


def rrd_arg(value: Any, field: str = "rrd") -> str | None:
    """A library function's optional Rerun recording path (path_arg's): None, or a path ending in .rrd; InputError
    naming the argument otherwise (every job that writes a recording refuses alike)."""
    path = path_arg(value, field, optional=True)
    if path is not None and not path.endswith(".rrd"):
        raise InputError(f"{field} {path!r}: expected a path ending in .rrd")
    return path


def as_path_or_object(value: Any) -> Any:
    """An os.PathLike (pathlib.Path) as its string; anything else (a str, an object a function also takes in its
    place: a FrameSource, a PinholeCamera, None) as it is."""
    return os.fspath(value) if isinstance(value, os.PathLike) else value


def paths_arg(value: Any, field: str) -> list[str]:
    """A list of paths (one path alone taken as a list of one: not its characters); InputError when empty."""
    items = [value] if isinstance(value, (str, os.PathLike)) else value
    if not isinstance(items, (list, tuple)) or not items:
        raise InputError(f"{field} = {value!r}: expected one or more paths")
    return [path_arg(v, f"{field}[{i}]") for i, v in enumerate(items)]


def config_arg(value: Any, cls: type, field: str = "cfg"):
    """value when it is a cls (a library function's config argument), else InputError naming what it got."""
    if not isinstance(value, cls):
        raise InputError(f"{field}: expected a {cls.__name__}, got {type(value).__name__} ({value!r:.60})")
    return value
