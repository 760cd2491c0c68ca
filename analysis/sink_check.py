"""Where a recording goes (a light module: no rerun import), checked before a job makes anything."""

from __future__ import annotations

from envisat_pose.config import InputError


def check_sink(sink: str) -> tuple[str, str, str]:
    """A recording sink's (kind, ':', argument): InputError naming `sink` unless it is 'save:PATH', 'spawn' or
    'connect:URL' (a job checks it before any work)."""
    kind, sep, arg = sink.partition(":") if isinstance(sink, str) else ("", "", "")
    if kind not in ("save", "spawn", "connect") or (kind == "save" and not arg):
        raise InputError(f"sink {sink!r}: expected 'save:PATH', 'spawn' or 'connect:URL'")
    return kind, sep, arg
