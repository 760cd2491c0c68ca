"""The errors of a config or an argument, and `check`, the one-line range check every config's validate() uses.

A ConfigError names the field, the value and what was expected (`rate_hz = 0.0: expected a positive rate in
Hz`); the CLI prints it, and an InputError (a missing file, say), without a traceback.
"""

from __future__ import annotations

from typing import Any


class ConfigError(ValueError):
    """A user error in a config or argument: the CLI prints it without a traceback."""

    def __init__(self, field: str, value: Any, expected: str):
        self.field, self.value, self.expected = field, value, expected
        super().__init__(f"{field} = {value!r}: expected {expected}")


class MovedKeyError(ConfigError):
    """A key of an older layout of a config: one line naming it and its new home ('tracker.gate_raw: moved to
    tracker.gate.raw')."""

    def __init__(self, field: str, value: Any, new_field: str):
        super().__init__(field, value, f"the key {new_field}")
        self.args = (f"{field}: moved to {new_field}",)

    def __str__(self) -> str:
        return self.args[0]


class DeprecatedKeyWarning(FutureWarning):
    """A config key under its old name, taken for one release (config_fields.renamed_fields): 'acquire.min_corners
    is deprecated: use acquire.min_keypoints'. A FutureWarning, Python's category for a deprecation its end users
    must see: the key is written in their config files, and Python shows no DeprecationWarning outside __main__
    (the verbs print it as a warning line)."""


class TargetFileWarning(UserWarning):
    """What loading a target file says once (joints latched, a keypoint no view sees): the job's own process says
    it as it checks its config; the worker processes that load the file again leave it out (envisat_pose.pools,
    the online trainer's renderers), so a job with N workers says it once, as its one warning line."""


class InputError(ValueError):
    """A user error that is not about one config field (a missing or unreadable file, say)."""


def check(cond: bool, field: str, value: Any, expected: str) -> None:
    """Raise ConfigError(field, value, expected) unless cond holds."""
    if not cond:
        raise ConfigError(field, value, expected)
