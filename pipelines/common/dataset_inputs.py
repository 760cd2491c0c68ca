"""What the verbs that read a generated dataset share: the --skip-damaged flag, its hint when a damaged
shard stops a run, and the line naming the shards it left out. The check itself is the core's
(envisat_pose/shard_reader.py: checked_shards); the pipelines call it with their own argument's name."""

from __future__ import annotations

import argparse
import contextlib

from envisat_pose.config import InputError
from envisat_pose.shard_reader import DamagedShardError


def add_skip_damaged_argument(p: argparse.ArgumentParser) -> None:
    """--skip-damaged, the same on every verb that reads a generated dataset."""
    p.add_argument("--skip-damaged", action="store_true",
                   help="go on without the shards that do not match the dataset's manifest.json (size, sha256), "
                   "naming them (default: a damaged shard stops the run before any output)")


@contextlib.contextmanager
def skip_hint():
    """A damaged shard found under this block (DamagedShardError: one line naming the field, the folder and the
    shard) also says how the verb goes on without it."""
    try:
        yield
    except DamagedShardError as err:
        raise InputError(f"{err}; `skip_damaged` goes on without it, `envisat dataset verify` lists every "
                         "problem") from None


def skipped_line(skipped: list[str]) -> str:
    """The line a verb prints about the damaged shards --skip-damaged left out ('' when none)."""
    return f"skipped {len(skipped)} damaged shard(s): {', '.join(skipped)}" if skipped else ""
