"""The progress of several closed-loop runs in one bar (`envisat run --runs N`): each run counts the frames it has
stepped into a small file in its own folder (FrameTally), and a thread of the job reads those files into one tqdm
bar over every run's frames (runs_bar), both at most every REPORT_INTERVAL_S, so the bar moves as the workers go
whichever way the runs are spread (this process, a process pool, a local Dask cluster: one file system).

Files rather than a queue: nothing to start or stop beside the workers (a multiprocessing Manager is one more process
for Ctrl-C to reach), and a run stopped by Ctrl-C, SIGTERM or an error leaves at most a stale count, removed with the
job's runs/ folder."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from typing import Callable, Iterator

REPORT_INTERVAL_S = 0.25  # a run writes its count, and the job reads them, at most 4 times a second
TALLY_NAME = "frames_done"  # in the run's folder (runs/run-NNNN/), removed with it


def tally_path(run_dir: str) -> str:
    """Where the run that writes run_dir counts its frames."""
    return os.path.join(run_dir, TALLY_NAME)


class FrameTally:
    """A run's frames stepped so far (n), written to path as a decimal count once REPORT_INTERVAL_S has passed since
    the last write, and by close(). Best effort: the count only feeds a progress bar, so a file system that refuses
    it (full) leaves the run to fail, or not, on its own files."""

    def __init__(self, path: str):
        self.path, self.n, self._written_s = path, 0, -float("inf")

    def advance(self) -> None:
        """One more frame stepped."""
        self.n += 1
        if time.monotonic() - self._written_s >= REPORT_INTERVAL_S:
            self.write()

    def write(self) -> None:
        """The count to the file now: whole (a new file moved over the old), so a reader never sees half of it."""
        self._written_s = time.monotonic()
        tmp = f"{self.path}.tmp"
        try:
            with open(tmp, "w", encoding="ascii") as fh:
                fh.write(str(self.n))
            os.replace(tmp, self.path)
        except OSError:
            pass

    def close(self) -> None:
        self.write()


def read_tally(path: str) -> int | None:
    """The count a FrameTally wrote to path; None where there is none yet (or it cannot be read)."""
    try:
        with open(path, encoding="ascii") as fh:
            return int(fh.read())
    except (OSError, ValueError):
        return None


class RunsBar:
    """One tqdm bar over every run's frames (len(tallies) x frames_per_run, unit frame): a thread reads the runs'
    tally files (FrameTally's) every REPORT_INTERVAL_S (poll); finished(i) counts run i whole, whatever its file
    says yet. close() stops the thread and closes the bar where it stands: at its total once every run finished."""

    def __init__(self, tallies: list[str], frames_per_run: int, desc: str):
        from tqdm import tqdm

        self.tallies, self.frames_per_run = list(tallies), frames_per_run
        self.counts, self.done = [0] * len(self.tallies), [False] * len(self.tallies)
        self.bar = tqdm(total=len(self.tallies) * frames_per_run, unit="frame", desc=desc, mininterval=0.5)
        self._lock, self._stop = threading.Lock(), threading.Event()
        self._thread = threading.Thread(target=self._watch, name="runs-progress", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.wait(REPORT_INTERVAL_S):
            self.poll()

    def poll(self) -> None:
        """The unfinished runs' counts, read from their files, into the bar."""
        for i, path in enumerate(self.tallies):
            n = None if self.done[i] else read_tally(path)
            if n is not None:
                self._count(i, min(n, self.frames_per_run))

    def finished(self, i: int) -> None:
        """Run i has returned: every one of its frames counted."""
        self.done[i] = True
        self._count(i, self.frames_per_run)

    def _count(self, i: int, n: int) -> None:
        with self._lock:  # the thread's poll and the job's finished: the bar only moves forward
            if n > self.counts[i]:
                self.bar.set_postfix_str(f"{sum(self.done)}/{len(self.done)} runs", refresh=False)
                self.bar.update(n - self.counts[i])
                self.counts[i] = n

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.bar.close()


@contextlib.contextmanager
def runs_bar(tallies: list[str] | None, frames_per_run: int, desc: str) -> Iterator[Callable[[int], None]]:
    """A RunsBar over the runs whose tally files are `tallies` while the block runs, closed however it ends (an
    error, Ctrl-C); yields its finished(i). tallies None: no bar (finished does nothing)."""
    if tallies is None:
        yield lambda i: None
        return
    bar = RunsBar(tallies, frames_per_run, desc)
    try:
        yield bar.finished
    finally:
        bar.close()
