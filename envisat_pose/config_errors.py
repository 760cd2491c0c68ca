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


class InputError(ValueError):
    """A user error that is not about one config field (a missing or unreadable file, say)."""


def check(cond: bool, field: str, value: Any, expected: str) -> None:
    """Raise ConfigError(field, value, expected) unless cond holds."""
    if not cond:
        raise ConfigError(field, value, expected)
