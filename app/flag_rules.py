"""What a verb's flags may say together, checked before any work: a config error named as the user wrote it
(the flag typed, else the config file's field), flags that do not apply to the job (online training's with
shards, a noise of another measurement), and the scenario a config file names."""

from __future__ import annotations

import argparse
import re

from envisat_pose.app.common import as_flags
from envisat_pose.config import ConfigError, InputError, load_toml


def config_error_text(err: ConfigError, names: dict[str, str], argv: list[str]) -> str:
    """A ConfigError's line: 'field = value: expected ...', or where the field is one of the verb's flags and the
    user typed that flag (so the value is the flag's: flags override files and scenarios), '--flag value:
    expected ...'."""
    flag = names.get(err.field) if type(err) is ConfigError else None
    if typed(flag, argv):
        return f"{flag} {err.value!r}: expected {err.expected}"
    return str(err)


def typed(flag: str | None, argv: list[str]) -> bool:
    """Whether `flag` is a flag ('--name') the command line holds ('--name V' or '--name=V')."""
    return bool(flag) and flag.startswith("--") and any(a == flag or a.startswith(flag + "=") for a in argv)


_FIELD_IS = re.compile(r"^([\w.]+) = ")


def warning_text(message: str, names: dict[str, str], argv: list[str]) -> str:
    """A library warning's line: one about a field's value ('field = value: ...') named as config_error_text names
    an error ('--flag value: ...' where the user typed the flag), any other with its names as flags (as_flags)."""
    found = _FIELD_IS.match(message)
    if found is None:
        return as_flags(message, names)
    flag = names.get(found.group(1))
    return f"{flag} {message[found.end():]}" if typed(flag, argv) else message


def not_applying(args: argparse.Namespace, dests: tuple[str, ...], why: str) -> None:
    """InputError naming the first flag of `dests` (argparse dest names) given, where none applies: `why`."""
    given = [d for d in dests if getattr(args, d, None) not in (None, False)]
    if given:
        raise InputError(f"--{given[0].replace('_', '-')}: {why}")


def job_scenario(flag: str | None, config_path: str | None, fallback: str | None = "default",
                 required: bool = False) -> str | None:
    """A job's scenario: the --scenario typed, else its config file's top-level `scenario` (what a run's written
    config records: it reproduces the run), else `fallback` (required: an InputError instead)."""
    if flag is not None:
        return flag
    if config_path is not None:
        named = load_toml(config_path).get("scenario")
        if named is not None:
            return named  # the job's config checks it is a known name
    if required:
        raise InputError("--scenario: required: a named scenario or a scenario file (or a --config file that names "
                         "one, as a written config does)")
    return fallback


NOISE_FLAGS = {"sigma_m": ("markers3d",), "sigma_px": ("pixels", "pixels+range"), "sigma_range_m": ("pixels+range",)}


def check_noise_flags(args: argparse.Namespace, kind: str) -> None:
    """A noise flag of another kind of measurement than the job's `kind` (it would change nothing): InputError."""
    for dest, kinds in NOISE_FLAGS.items():
        if getattr(args, dest, None) is not None and kind not in kinds:
            raise InputError(f"--{dest.replace('_', '-')}: the noise of {' or '.join(kinds)} measurements; this "
                             f"job measures {kind} (--measurements)")


def training_source(args: argparse.Namespace) -> None:
    """`train`'s flags of one source of frames, args.online set for any online run (--online, --target, a resumed
    online run): --data with it refused (named as the user made it online), --workers (the shard readers) too,
    and --render-workers below 1."""
    if args.online and args.data:
        src = "--online" if "--online" in getattr(args, "argv", ()) else "--target" if args.target else "--resume"
        raise InputError(f"--data and {src}: train on shards or on rendered frames, not both")
    if args.online:
        not_applying(args, ("workers",), "a flag of training on --data's shards (their reader processes): "
                     "rendered frames come from --render-workers")
    if args.render_workers is not None and args.render_workers < 1:
        raise InputError(f"--render-workers {args.render_workers}: expected at least 1 renderer process")
