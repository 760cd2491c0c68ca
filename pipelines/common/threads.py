"""The compute threads a job runs with, given back when it ends: a library call leaves the caller's torch and
OpenCV thread counts as it found them (a later call in the same process then computes as in a fresh one)."""

from __future__ import annotations

from contextlib import contextmanager

from envisat_pose.pools import usable_cores


def default_torch_threads() -> int:
    """torch's CPU threads where a job is given none: torch's own count (its default follows the CPU affinity), no
    more than the usable cores (a cgroup CPU quota, which torch does not read; 64 threads on 2 cores made a
    training step 11x slower than 2 threads)."""
    import torch

    return max(1, min(torch.get_num_threads(), usable_cores()))


@contextmanager
def compute_threads(torch_n: int | None = None, cv2_n: int | None = None):
    """torch's CPU threads set to torch_n and OpenCV's to cv2_n inside the block (None: left as they are), each
    restored on every way out (torch is imported only where a count is given for it)."""
    restore = []
    if torch_n is not None:
        import torch

        restore.append((torch.set_num_threads, torch.get_num_threads()))
        torch.set_num_threads(torch_n)
    if cv2_n is not None:
        import cv2

        restore.append((cv2.setNumThreads, cv2.getNumThreads()))
        cv2.setNumThreads(cv2_n)
    try:
        yield
    finally:
        for set_threads, n in restore:
            set_threads(n)
