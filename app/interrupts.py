"""SIGTERM as Ctrl-C for every verb: while a verb runs (app/cli.py's main), SIGTERM raises `Terminated`, a
KeyboardInterrupt, in the main thread, so the verb stops as on Ctrl-C (its staged outputs removed, a resumable
job's units kept) and says the same line; it exits 128 + the signal's number (130 for SIGINT, 143 for SIGTERM).
`envisat train` and `envisat view` put their own handlers over it while they run (a checkpoint first; the
viewer's group ended). A process forked from the verb's dies of SIGTERM as without it (a DataLoader worker,
which comes from a fork server, ignores it: the trainer stops it).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C's KeyboardInterrupt would be: every clean-up runs as on Ctrl-C."""


def interrupt_code(err: BaseException | None) -> int:
    """The exit code of a verb stopped by err: 143 for SIGTERM (Terminated, or a run that stopped itself on it),
    130 for Ctrl-C."""
    return 128 + signal.SIGTERM if isinstance(err, Terminated) or getattr(
        err, "signal_name", "") == "SIGTERM" else 128 + signal.SIGINT


@contextlib.contextmanager
def sigterm_as_interrupt():
    """SIGTERM raises Terminated in this process's main thread while the block runs; the old handler comes back
    after. Outside the main thread (no signal handlers there), where SIGTERM came in ignored (as Python leaves
    SIGINT ignored for a job started so) or under a handler not set from Python, the block runs as it is."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) in (
            signal.SIG_IGN, None):
        yield
        return
    pid = os.getpid()

    def terminated(signum, frame):
        if os.getpid() != pid:  # a forked child: the default action, as if this handler were not there
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTERM)
            return
        raise Terminated

    old = signal.signal(signal.SIGTERM, terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
