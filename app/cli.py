"""The `envisat` command line: one entry point, one verb per job.

Each module of the app layer named below adds its verbs with a `register(subparsers)` function; a verb's
handler takes the parsed arguments and returns an exit code. Stage modules are imported inside the handlers,
so a verb loads only what it uses (`estimate --truth` never loads MuJoCo). SIGTERM stops a verb as Ctrl-C does
(the same line; exit 143, Ctrl-C's 130: app/interrupts.py). User errors (ConfigError,
InputError) are printed as one line on stderr with exit code 2, never as a traceback; warnings as one line
each ("envisat VERB: warning: ...").
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from envisat_pose.app.common import EVERY_VERB, as_flags
from envisat_pose.app.flag_rules import config_error_text, warning_text
from envisat_pose.app.interrupts import interrupt_code, sigterm_as_interrupt
from envisat_pose.config import ConfigError, InputError
from envisat_pose.datagen.gl_check import check_gl_platform
from envisat_pose.whole_flags import WholeFlagParser

# The app modules that define register(subparsers), in the order their verbs are listed.
_VERB_MODULES = ("envisat_pose.app.simulate", "envisat_pose.app.generate", "envisat_pose.app.dataset",
                 "envisat_pose.app.estimate", "envisat_pose.app.montecarlo", "envisat_pose.app.report", "envisat_pose.app.scenarios",
                 "envisat_pose.app.train", "envisat_pose.app.detect", "envisat_pose.app.calibrate",
                 "envisat_pose.app.evaluate", "envisat_pose.app.view", "envisat_pose.app.run", "envisat_pose.app.track",
                 "envisat_pose.app.adapt", "envisat_pose.app.demo")


def build_parser() -> argparse.ArgumentParser:
    parser = WholeFlagParser(
        prog="envisat",
        description="Relative pose of a tumbling spacecraft (ENVISAT, or any target given as an MJCF file): simulate, "
        "generate labelled images, train and run a detector, estimate, track your own frames.",
    )
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    for name in _VERB_MODULES:
        importlib.import_module(name).register(sub)
    parser.verb_parsers = sub.choices  # each verb's own parser: its usage for a flag it does not take
    return parser


def main(argv: list[str] | None = None) -> int:
    with sigterm_as_interrupt():  # SIGTERM stops a verb as Ctrl-C does (app/interrupts.py)
        return run_verb(argv)


def run_verb(argv: list[str] | None) -> int:
    try:  # the verbs' modules load numpy, scipy and the rest: Ctrl-C there is an interrupt, not a traceback
        parser = build_parser()
    except KeyboardInterrupt as stop:
        print("envisat: interrupted", file=sys.stderr)
        return interrupt_code(stop)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # in the verb's own usage, not the top level's (`envisat demo --target X` said `envisat [-h] VERB`)
        parser.verb_parsers[args.verb].error(f"unrecognized arguments: {' '.join(unknown)}")
    args.argv = list(sys.argv[1:] if argv is None else argv)  # the command as typed (a run's record)

    def one_line(message, category, filename, lineno, file=None, line=None):  # the library's names as flags
        text = warning_text(str(message), {**EVERY_VERB, **getattr(args, "flag_names", {})}, args.argv)
        print(f"envisat {args.verb}: warning: {text}", file=sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = one_line
            code = int(args.func(args) or 0)
            sys.stdout.flush()  # a buffered stdout (a pipe, no PYTHONUNBUFFERED) meets a gone reader here, not at exit
            return code
    except (ConfigError, InputError) as err:
        names = {**EVERY_VERB, **getattr(args, "flag_names", {})}
        text = config_error_text(err, names, args.argv) if isinstance(err, ConfigError) else as_flags(str(err), names)
        print(f"envisat {args.verb}: error: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        print(f"envisat {args.verb}: interrupted{interrupt_hint(args)}", file=sys.stderr)
        return interrupt_code(stop)
    except BrokenPipeError:  # the reader went away (`envisat ... | head`): stop quietly, as `cat` does
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python's own flush of stdout at exit would raise again
        return 141
    except Exception as err:  # after the kinds above: a closed pipe is not an interrupt
        if disk_full(err):  # a full disk or a file-size limit: one line, not a traceback (outputs stay whole)
            kept = " (what is written is kept)" if getattr(args, "resumable", False) else ""
            print(f"envisat {args.verb}: error: {disk_full(err)}; free some space and run the same command "
                  f"again{kept}", file=sys.stderr)
            return 1
        if gl_refused(err):  # MuJoCo's own import refuses a MUJOCO_GL it does not know: one line, as ours
            print(f"envisat {args.verb}: error: {gl_refused(err)}", file=sys.stderr)
            return 2
        if not after_interrupt(err):
            raise
        # Ctrl-C landed inside an import (MuJoCo's, torch's): the cleanup's own import of the half-loaded module
        # then fails; the user asked to stop, and is told so
        print(f"envisat {args.verb}: interrupted{interrupt_hint(args)}", file=sys.stderr)
        return interrupt_code(after_interrupt(err))


def interrupt_hint(args: argparse.Namespace) -> str:
    """What an interrupted verb's line adds: a resumable job's way on (its `resumable` default: the same command
    again finishes what it wrote), nothing for the others (their outputs are staged: nothing was written)."""
    return "; run the same command again to finish it (what is written is kept)" if getattr(
        args, "resumable", False) else ""


def disk_full(err: BaseException) -> str:
    """The line for a write refused for want of room (ENOSPC, EDQUOT, EFBIG: a full disk, a quota, `ulimit -f`),
    naming the file where the error does; '' for any other error. Every output is written atomically, so what
    such a stop leaves is the earlier files, whole."""
    import errno

    if not (isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)):
        return ""
    where = f" writing {err.filename!r}" if err.filename else ""
    return f"{err.strerror or err}{where}"


def gl_refused(err: BaseException) -> str:
    """The line for MuJoCo's import refusing the MUJOCO_GL set (a RuntimeError naming the variable): the value and
    the platforms that render here (datagen/gl_check.py); '' for any other error."""
    if not (isinstance(err, RuntimeError) and "environment variable MUJOCO_GL" in str(err)):
        return ""
    try:
        check_gl_platform()
    except InputError as refused:
        return str(refused)
    return str(err)


def after_interrupt(err: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt being handled when err was raised (in its context or cause chain), or None."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


if __name__ == "__main__":
    sys.exit(main())
