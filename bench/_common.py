"""What every bench script shares: its --help description, the default file of its results and the provenance its
JSON records.

A script imports it inside its main (`from _common import ...`): run as `python bench/NAME.py`, bench/ is the first
folder on sys.path, and a test that loads a bench module from its file path does not need it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys

from envisat_pose.pipelines.detector.train import git_hash

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def description(doc: str) -> str:
    """A script's --help description: its module docstring's first paragraph (whole sentences; the rest of the
    docstring, the protocol and the floors, is read in the file)."""
    return doc.strip().split("\n\n")[0]


def results_path(name: str) -> str:
    """bench/results/NAME.json of this repository, whatever the working folder: the default of a script's --out."""
    return os.path.join(ROOT, "bench", "results", f"{name}.json")


def provenance(args: argparse.Namespace | None = None) -> dict:
    """Where a result comes from, for its JSON: the source's commit (pipelines.detector.train.git_hash: '+dirty'
    when the tree has uncommitted changes; null where no commit is known), the UTC date and time, the command
    line's arguments as typed (argv) and every parsed argument with its default (args: seeds included)."""
    commit = git_hash()
    return {"commit": None if commit == "unknown" else commit,
            "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "argv": sys.argv[1:],
            "args": None if args is None else json.loads(json.dumps(vars(args), default=str))}
