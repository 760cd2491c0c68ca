"""What every bench script shares: its parser (envisat_pose.whole_flags.WholeFlagParser: whole flags only), its
--help description, the default file of its results and the provenance its JSON records.

A script imports it inside its main (`from _common import ...`): run as `python bench/NAME.py`, bench/ is the first
folder on sys.path, and a test that loads a bench module from its file path does not need it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys

from envisat_pose.provenance import git_hash
from envisat_pose.whole_flags import WholeFlagParser  # noqa: F401  (every script's parser: whole flags only)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def description(doc: str) -> str:
    """A script's --help description: its module docstring's first paragraph (whole sentences; the rest of the
    docstring, the protocol and the floors, is read in the file)."""
    return doc.strip().split("\n\n")[0]


def results_path(name: str) -> str:
    """bench/results/NAME.json of this repository, whatever the working folder: the default of a script's --out."""
    return os.path.join(ROOT, "bench", "results", f"{name}.json")


def provenance(args: argparse.Namespace | None = None) -> dict:
    """Where a result comes from, for its JSON: the source's commit (envisat_pose.provenance.git_hash: '+dirty'
    when the tree has uncommitted changes; null where no commit is known), the UTC date and time, the command
    line's arguments as typed (argv) and every parsed argument with its default (args: seeds included)."""
    commit = git_hash()
    return {"commit": None if commit == "unknown" else commit,
            "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "argv": sys.argv[1:],
            "args": None if args is None else json.loads(json.dumps(vars(args), default=str))}


def count(least: int = 1):
    """An argparse type: a whole number of at least `least` (runs, images, rounds, workers); anything else is
    argparse's one line of usage error, not a traceback later."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"{value} is below {least}")
        return value
    return parse


def positive(text: str) -> float:
    """An argparse type: a number above 0 (a duration, a rate)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0:  # NaN too
        raise argparse.ArgumentTypeError(f"{value:g} is not above 0")
    return value


def existing_file(text: str) -> str:
    """An argparse type: a path to a file that is there."""
    if not os.path.isfile(text):
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    return text


def existing_dir(text: str) -> str:
    """An argparse type: a path to a folder that is there."""
    if not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text}: no such folder")
    return text


def dataset(text: str) -> str:
    """An argparse type: a generated dataset's folder (`envisat generate`), its manifest read by the one reader."""
    from envisat_pose.config import InputError
    from envisat_pose.shard_reader import load_dataset_manifest

    try:
        load_dataset_manifest(text)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def out_file(text: str) -> str:
    """An argparse type for --out: a file path whose folder is a folder (made when absent), refused before the
    benchmark runs rather than when it writes."""
    folder = os.path.dirname(os.path.abspath(text))
    while not os.path.exists(folder):
        folder = os.path.dirname(folder)
    if os.path.isdir(text) or not os.path.isdir(folder) or not os.access(folder, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: not a file that can be written")
    return text


def write_json(path: str, data: dict, **dump) -> None:
    """`data` as JSON at `path` atomically (a temporary file beside it, then a rename: an interrupted run leaves
    the earlier file or none, never half of one), its folder made first."""
    from envisat_pose.io import atomic_write_text

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    atomic_write_text(path, json.dumps(data, **dump) + "\n")


def existing_results(path: str, check) -> dict:
    """The JSON object already at `path` that a run adds its entry to ({} when there is none), to be read before
    the benchmark runs: InputError (one line under run) when it is not JSON or `check(data)` is false (another
    bench's results, which the merge would garble)."""
    from envisat_pose.config import InputError

    if not os.path.exists(path):
        return {}
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"--out {path}: not a JSON file this bench can add to ({err})") from None
    if not isinstance(data, dict) or not check(data):
        raise InputError(f"--out {path}: not this bench's results file (a run is added to the file's own)")
    return data


def run_main(main) -> None:
    """Exit with main()'s code; a user error (the project's ConfigError, InputError: a bad scenario name, a wrong
    target file) is one line, as the envisat CLI prints it, and Ctrl-C is one line too."""
    from envisat_pose.config import ConfigError, InputError

    name = os.path.basename(sys.argv[0])
    try:
        code = main()
    except (ConfigError, InputError) as err:
        print(f"{name}: error: {err}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        code = 130
    sys.exit(code or 0)
