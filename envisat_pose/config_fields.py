"""A config's fields checked: the base class `Config`, validated when built, and `from_dict`, plain data into one.

Configs are frozen dataclasses (nested for sections) derived from `Config`, which validates each one when it is
built: the constructor, `dataclasses.replace` and `from_dict` alike (a config's own `validate()` checks its ranges).
`from_dict` builds one from plain data through its constructor and rejects unknown keys, wrong types and
non-finite numbers (the constructor refuses NaN and inf too). What a config fills in itself is marked (Derived,
DerivedInt, mark_filled) so that a config replaced with new inputs fills it in again. A field renamed
(`renamed_fields`) still takes its old name for one release, with a DeprecatedKeyWarning.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import types
import typing
import warnings
from typing import Any

from envisat_pose.config_errors import ConfigError, DeprecatedKeyWarning, MovedKeyError, check


class Derived(float):
    """A number a config filled in, not one a user gave: from its own other fields (filled_for None: a default
    sized to its target, say) or from a named scenario (filled_for its name: mark_filled). A float that
    `dataclasses.replace` leaves for the new config to fill in again where the inputs changed, where a plain float
    stays as given. Written to a file or a manifest it is a plain number (read back: given)."""

    def __new__(cls, value: float, filled_for: str | None = None) -> "Derived":
        out = super().__new__(cls, value)
        out._filled_for = filled_for
        return out

    def __repr__(self) -> str:
        return float.__repr__(self)

    def __reduce__(self):
        return Derived, (float(self), self._filled_for)


class DerivedInt(int):
    """Derived's whole number (a count a config filled in from its other fields: a run's worker processes)."""

    def __repr__(self) -> str:
        return int.__repr__(self)

    def __reduce__(self):
        return DerivedInt, (int(self),)


def derived(value) -> bool:
    """Whether a field is the config's to fill in: not given (None), or filled in before (Derived, DerivedInt)."""
    return value is None or isinstance(value, (Derived, DerivedInt))


UNMARKED = object()  # filled_for's answer for a value no config filled in from a scenario


def mark_filled(value: Any, scenario: str | None) -> Any:
    """value, marked as filled in from `scenario` (filled_for): a float as a Derived, a config in place (a fresh
    one: the mark stays with that object); a bool cannot be marked and is returned as it is."""
    if isinstance(value, float) and not isinstance(value, bool):
        return Derived(value, scenario)
    if isinstance(value, Config):
        object.__setattr__(value, "_filled_for", scenario)
    return value


def filled_for(value: Any) -> Any:
    """The scenario a config filled `value` in from (mark_filled), or UNMARKED for a value given or derived
    from a config's own fields."""
    return getattr(value, "_filled_for", UNMARKED) if isinstance(value, (Derived, Config)) else UNMARKED


class Config:
    """The base of every config dataclass: validated when built (the constructor, dataclasses.replace, from_dict).

    A subclass's own __post_init__ does its filling first (fields left None that take a scenario's, say), then
    calls super().__post_init__(); what it fills in is marked (Derived, DerivedInt, mark_filled), so a config
    replaced with new inputs (another scenario or target) fills it in again. validate(prefix) raises ConfigError
    naming a field under prefix: '' when built,
    so the names are the config's own ('p0_sigma'); from_dict puts the table's dotted name in front
    ('filter.p0_sigma'). Kept cheap (milliseconds): what a validate() reads (the MJCF camera, a target file) is
    cached, a weights file only looked up.
    """

    def __init_subclass__(cls, **kwargs) -> None:
        """A subclass's own __post_init__ (its filling, then super's) runs after its fields' types are checked."""
        super().__init_subclass__(**kwargs)
        own = cls.__dict__.get("__post_init__")
        if own is None:
            return

        @functools.wraps(own)
        def post_init(self) -> None:
            _tables_over_bases(self)
            _check_fields(self)
            own(self)

        cls.__post_init__ = post_init

    def __post_init__(self) -> None:
        if not _checks_in_own_post_init(type(self)):
            _check_fields(self)
        self.validate("")

    def validate(self, prefix: str = "") -> None:
        """ConfigError for a field out of its range (a config with nothing to check has nothing here)."""


def renamed_fields(**renamed: str) -> typing.Callable[[type], type]:
    """A class decorator over a config's @dataclass: each old field name (renamed: {old: new}) still taken for one
    release, with a DeprecatedKeyWarning naming the new one: a file's or a dict's key (from_dict, 'acquire.min_corners
    is deprecated: use acquire.min_keypoints'), a constructor's keyword and an attribute read. Both names given
    are refused, naming both (dataclasses.replace passes every field: replace with the new name)."""

    def decorate(cls: type) -> type:
        init = cls.__init__

        @functools.wraps(init)
        def __init__(self, *args, **kwargs) -> None:
            init(self, *args, **_renamed_given(cls, kwargs, f"{cls.__name__}."))

        cls.__init__ = __init__
        cls.renamed_keys = dict(renamed)  # from_dict's {old: new}
        for old, new in renamed.items():
            setattr(cls, old, property(functools.partial(_old_name_read, old=old, new=new),
                                       doc=f"Deprecated: {new}, under its old name (one release)."))
        return cls

    return decorate


def _old_name_read(obj: Any, old: str, new: str) -> Any:
    warnings.warn(f"{type(obj).__name__}.{old} is deprecated: use {type(obj).__name__}.{new}", DeprecatedKeyWarning,
                  stacklevel=2)
    return getattr(obj, new)


def _renamed_given(cls: type, data: dict, prefix: str = "", stacklevel: int = 3) -> dict:
    """data (a table's keys or a constructor's keywords) with each old name of cls.renamed_keys ({old: new},
    renamed_fields) under its new one, warned of (DeprecatedKeyWarning, '<prefix>old is deprecated: use
    <prefix>new'); ConfigError naming both where both are given. data itself where it holds no old name."""
    renamed = getattr(cls, "renamed_keys", {})
    old_given = [old for old in renamed if old in data]
    if not old_given:
        return data
    out = dict(data)
    for old in old_given:
        new = renamed[old]
        if new in out:
            raise ConfigError(f"{prefix}{old}", out[old], f"{prefix}{new} alone ({old} is its deprecated name), not "
                              f"both: {prefix}{new} = {out[new]!r} is given too")
        warnings.warn(f"{prefix}{old} is deprecated: use {prefix}{new}", DeprecatedKeyWarning, stacklevel=stacklevel)
        out[new] = out.pop(old)
    return out


def _tables_over_bases(obj: Config) -> None:
    """A table given as a dict where the config names what it lies over (its class's `table_bases`: {field:
    base(config) -> dict}, a job's scenario's table, say): its keys over that base, as a config file's table lies
    over the layers under it (pipelines/common/job_defaults.layered_job), not over its class's defaults."""
    for name, base in getattr(type(obj), "table_bases", {}).items():
        value = getattr(obj, name)
        if isinstance(value, dict):
            object.__setattr__(obj, name, {**base(obj), **value})


@functools.lru_cache(maxsize=None)
def _checks_in_own_post_init(cls: type) -> bool:
    """Whether a class between cls and Config has its own __post_init__ (wrapped by __init_subclass__ to check
    the fields first: the base's then does not check them again)."""
    return any("__post_init__" in c.__dict__ for c in cls.__mro__[:cls.__mro__.index(Config)])


@functools.lru_cache(maxsize=None)
def _field_hints(cls: type) -> tuple:
    """((name, type hint), ...) of a config class's fields; () where its hints do not resolve (names imported for
    type checking only): its fields are then left to its validate()."""
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - an unresolvable annotation: no type checks, never a failure
        return ()
    return tuple((f.name, hints[f.name]) for f in dataclasses.fields(cls) if f.name in hints)


def _check_fields(obj: Config) -> None:
    """Every field of a config built by its constructor checked against its type hint, as from_dict checks plain
    data (ConfigError naming the field: runs = 2.5, rate_hz = '1'), and put in its one form: a path (os.PathLike)
    as its string, a list or array as a tuple, a table given as a dict as its config, numpy's scalars as Python's.
    """
    for name, hint in _field_hints(type(obj)):
        value = getattr(obj, name)
        converted = _built(value, hint, name)
        if converted is not value:
            object.__setattr__(obj, name, converted)


def _built(value: Any, hint: Any, field: str) -> Any:
    """One constructor argument checked against its hint (_check_fields): a built config and the types from_dict
    makes are taken as they are; plain data goes through _convert; what no hint describes passes."""
    if type(value) is hint or _plain(value, hint):  # the common case, at a dict lookup's cost
        if value != value or (type(value) is tuple and any(v != v for v in value)):  # NaN: no field means it
            raise ConfigError(field, value, "a number (not NaN)")
        if _infinite(value):  # nor inf, as a file's from_dict refuses it (a written config could not hold it)
            raise ConfigError(field, value, "a finite number")
        return value
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        if any(dataclasses.is_dataclass(a) and isinstance(value, a) for a in args):
            return value
    elif dataclasses.is_dataclass(hint):
        return value if isinstance(value, hint) else _convert(value, hint, field)
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if isinstance(value, (bool, str)):
        pass
    elif type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        value = value.tolist()  # numpy's scalars as Python's, an array (a tuple field's) as a list
    if hint in (int, float, bool, str) or origin in (tuple, typing.Literal, typing.Union, types.UnionType) or \
            dataclasses.is_dataclass(hint):
        out = _convert(value, hint, field, finite=False)
        if (type(out) is float and out != out) or (type(out) is tuple and any(v != v for v in out)):
            raise ConfigError(field, value, "a number (not NaN)")  # numpy's NaN, converted: as Python's above
        if _infinite(out):
            raise ConfigError(field, value, "a finite number")
        return value if out == value and type(out) is type(value) else out
    return value


def _infinite(value: Any) -> bool:
    """Whether value is an infinite float or a tuple holding one (a list field's items, a window's ends)."""
    if type(value) is tuple:
        return any(_infinite(v) for v in value)
    return isinstance(value, float) and math.isinf(value)


@functools.lru_cache(maxsize=None)
def _plain_types(hint: Any) -> frozenset:
    """The Python types a value of `hint` may have as it is (float takes an int too; Optional adds None; a
    tuple of one element type: its elements'); empty where the hint needs a closer look."""
    if hint in (int, bool, str):
        return frozenset({hint})
    if hint is float:
        return frozenset({float, int})
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType) and len(args) == 2 and type(None) in args:
        inner = _plain_types(next(a for a in args if a is not type(None)))
        return inner | {type(None)} if inner else frozenset()
    return frozenset()


def _plain(value: Any, hint: Any) -> bool:
    """Whether value is of hint's plain types (_plain_types), a tuple field's elements included."""
    if type(value) is tuple and typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if args and args[-1] is Ellipsis and len(args) == 2:
            ok = _plain_types(args[0])
            return bool(ok) and all(type(v) in ok for v in value)
        return len(args) == len(value) and all(type(v) in _plain_types(a) for v, a in zip(value, args))
    return type(value) in _plain_types(hint) or (type(value) is Derived and float in _plain_types(hint)) or (
        type(value) is DerivedInt and int in _plain_types(hint))



def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _convert(value: Any, hint: Any, field: str, finite: bool = True) -> Any:
    """Check and convert one value against its type hint (finite: a float must be finite, as in a file)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        tables = [a for a in args if dataclasses.is_dataclass(a)]
        if isinstance(value, dict) and len(tables) == 1:  # an optional table: its own errors, by their dotted key
            return _convert(value, tables[0], field)
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, field, finite)
            except ConfigError as err:
                errors.append(err.expected)
        raise ConfigError(field, value, " or ".join(errors + (["nothing (omit it)"] if type(None) in args else [])))
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigError(field, value, f"a table of {', '.join(f.name for f in dataclasses.fields(hint))}")
        return from_dict(hint, value, prefix=field)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(field, value, "true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise ConfigError(field, value, "an integer")
        # a whole float beyond TOML's 64-bit integers (1e300 for a count) is no count a job can hold: as an int it
        # had 301 digits, and a bound computed from it (2 ** depth) ran out of memory before any check answered
        check(not isinstance(value, float) or abs(value) < 2.0**63, field, value,
              "an integer within TOML's 64 bits (|n| < 2^63)")
        return int(value)
    if hint is float:
        if not _is_number(value):
            raise ConfigError(field, value, "a number")
        if finite and not math.isfinite(float(value)):
            raise ConfigError(field, value, "a finite number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(field, value, "a string")
        return value
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(field, value, _list_expected(args))
        if args and args[-1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{field}[{i}]", finite) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(field, value, f"a list of {len(args)} values")
        return tuple(_convert(v, a, f"{field}[{i}]", finite) for i, (v, a) in enumerate(zip(value, args)))
    if typing.get_origin(hint) is typing.Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise ConfigError(field, value, "one of " + ", ".join(repr(a) for a in allowed))
        return value
    return value


_ITEM_WORDS = {int: "integers", float: "numbers", str: "strings", bool: "true/false values"}


def _list_expected(args: tuple) -> str:
    """What a tuple field takes, in a config error's words: 'a list of integers' (tuple[int, ...]), 'a list of 3
    numbers' (tuple[float, float, float]), 'a list of 2 values' (mixed items)."""
    items = set(args[:-1] if args and args[-1] is Ellipsis else args)
    word = _ITEM_WORDS.get(next(iter(items)), "values") if len(items) == 1 else "values"
    return f"a list of {word}" if args and args[-1] is Ellipsis else f"a list of {len(args)} {word}"


def field_value(cls: type, name: str, value: Any) -> Any:
    """value checked and converted for the field `name` of the dataclass cls, as from_dict converts it (a table
    into its dataclass, an int into a float field's float)."""
    return _convert(value, typing.get_type_hints(cls)[name], name)


def from_dict(cls: type, data: dict, prefix: str = "") -> Any:
    """Build the dataclass `cls` from `data` over its defaults: the types checked here, then its constructor (a
    Config validates itself; its ConfigError named under prefix, 'filter.p0_sigma'); a table the class lays over
    a base of its own (`table_bases`) is left to the constructor, so a job's nested table (adapt's [track]) lies
    over its scenario's as the job's own constructor and resolve_job lay it. A dataclass that is not a Config (a
    test's own) is validated here with `validate(prefix)`, if it has one."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    data = _renamed_given(cls, data, f"{prefix}." if prefix else "")
    moved = getattr(cls, "moved_keys", {})  # {old key: "section.key"} of a config that was regrouped
    for key in data:
        where = f"{prefix}.{key}" if prefix else key
        if key in moved and not isinstance(data[key], dict):
            raise MovedKeyError(where, data[key], f"{prefix}.{moved[key]}" if prefix else moved[key])
        if key not in names:
            raise ConfigError(where, data[key], "a known key: " + ", ".join(sorted(names)))
    kwargs = {}
    bases = getattr(cls, "table_bases", {})
    for f in dataclasses.fields(cls):
        where = f"{prefix}.{f.name}" if prefix else f.name
        if f.name in bases and isinstance(data.get(f.name), dict):
            # a table the config lays over its base (a job's scenario's): handed to the constructor as given, which
            # lays it there and builds it (_tables_over_bases), not built here over its class's defaults
            kwargs[f.name] = data[f.name]
        elif f.name in data:
            kwargs[f.name] = _convert(data[f.name], hints[f.name], where)
    try:
        obj = cls(**kwargs)
    except ConfigError as err:
        raise _under(prefix, err) from None
    validate = getattr(obj, "validate", None)
    if validate is not None and not isinstance(obj, Config):
        validate(prefix)
    return obj


def _under(prefix: str, err: ConfigError) -> ConfigError:
    """A constructor's ConfigError with its field named under the table's dotted prefix ('filter.p0_sigma')."""
    if not prefix or type(err) is not ConfigError:
        return err
    return ConfigError(f"{prefix}.{err.field}", err.value, err.expected)
