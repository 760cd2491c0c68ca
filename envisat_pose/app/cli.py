"""The `envisat` command line: one entry point, one verb per job.

Each package contributes its verbs through a `register(subparsers)` function in its `cli` module; a verb's
handler takes the parsed arguments and returns an exit code. User errors (ConfigError, InputError) are
printed as one line on stderr with exit code 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from envisat_pose.config import ConfigError, InputError

# Modules that define register(subparsers); a package whose cli module is absent simply adds no verbs.
_VERB_MODULES = ("envisat_pose.app.simulate", "envisat_pose.app.generate", "envisat_pose.app.estimate")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="envisat",
        description="Relative pose of a tumbling ENVISAT: simulate, generate images, detect corners, estimate.",
    )
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    for name in _VERB_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as err:
            if err.name == name:
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ConfigError, InputError) as err:
        print(f"envisat {args.verb}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"envisat {args.verb}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
