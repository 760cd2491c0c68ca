"""The compute threads a job runs with, given back when it ends: a library call leaves the caller's torch and
OpenCV thread counts as it found them (a later call in the same process then computes as in a fresh one)."""

from __future__ import annotations

import threading
from contextlib import contextmanager

from envisat_pose.pools import usable_cores


def default_torch_threads() -> int:
    """torch's CPU threads where a job is given none: torch's own count (its default follows the CPU affinity), no
    more than the usable cores (a cgroup CPU quota, which torch does not read; 64 threads on 2 cores made a
    training step 11x slower than 2 threads)."""
    import torch

    return max(1, min(torch.get_num_threads(), usable_cores()))


# per library ("torch", "cv2"): the caller's count before the first block in force, and the blocks in force, in
# the order they began ([requested count, ...]); a lock, as jobs in a thread pool enter and leave them at once
_IN_FORCE: dict[str, tuple[int, list[list[int]]]] = {}
_IN_FORCE_LOCK = threading.Lock()


@contextmanager
def compute_threads(torch_n: int | None = None, cv2_n: int | None = None):
    """torch's CPU threads set to torch_n and OpenCV's to cv2_n inside the block (None: left as they are), each
    restored on every way out (torch is imported only where a count is given for it). Blocks that overlap (jobs
    in a thread pool; one nested in another) give back the count of the latest block still in force, and the
    last one out the caller's count from before the first: a block does not restore the count another block set."""
    knobs = []
    if torch_n is not None:
        import torch

        knobs.append(("torch", torch.get_num_threads, torch.set_num_threads, [torch_n]))
    if cv2_n is not None:
        import cv2

        knobs.append(("cv2", cv2.getNumThreads, cv2.setNumThreads, [cv2_n]))
    entered = []  # the knobs in force: a count refused (torch's 0) leaves no block behind, the others given back
    try:
        with _IN_FORCE_LOCK:
            for knob in knobs:
                name, get_threads, set_threads, block = knob
                before, blocks = _IN_FORCE[name] if name in _IN_FORCE else (get_threads(), [])
                _IN_FORCE[name] = (before, blocks + [block])
                entered.append(knob)
                set_threads(block[0])
        yield
    finally:
        with _IN_FORCE_LOCK:
            for name, _, set_threads, block in entered:
                before, blocks = _IN_FORCE[name]
                blocks = [b for b in blocks if b is not block]
                if blocks:
                    _IN_FORCE[name] = (before, blocks)
                else:
                    del _IN_FORCE[name]
                set_threads(blocks[-1][0] if blocks else before)
