"""The compute threads a job runs with, given back when it ends: a library call leaves the caller's torch and
OpenCV thread counts as it found them (a later call in the same process then computes as in a fresh one)."""

from __future__ import annotations

from contextlib import contextmanager


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
