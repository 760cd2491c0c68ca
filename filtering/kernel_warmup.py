"""Having the fused filter's compiled code ready before the first frame needs it.

numba loads a kernel's cached machine code (or compiles it, on a machine without the cache) on the kernel's first
call with a given set of argument types: about 0.6 s for filtering/fast.py's kernels, measured alone, more beside
a busy loop. A tracker pays it at its first tracked frame, in the middle of its run. `load_kernels` makes those
first calls on dummy data of the same types (one predict and one update of two runs on the setup's own
measurement model, visibility rule and keypoints), so the real ones find the code loaded; `load_in_background`
does it on a thread, beside whatever else the caller is starting (the renderer, the detector, the first frames:
torch and MuJoCo release the GIL). Nothing of a filter's state is touched: the dummy step's result is dropped.
"""

from __future__ import annotations

import threading

import numpy as np

from envisat_pose.filtering.estimator import FilterSetup, Measurement, filter_step, init_state, predict_to
from envisat_pose.filtering.measurements import dim_per_corner
from envisat_pose.filtering.step_update import uses_fused_kernel

DUMMY_RANGE_M = 50.0  # the dummy runs' target distance (any finite state would do: numba dispatches on types)


def load_kernels(setup: FilterSetup) -> None:
    """One predict and one update of two dummy runs with setup (its kernel's code loaded; nothing kept)."""
    cfg, R, K = setup.cfg, 2, setup.num_keypoints
    m = dim_per_corner(setup.kind)
    chaser = np.array([7.0e6, 0.0, 0.0, 1.0e-3])
    x0 = np.zeros((R, 12))
    x0[:, 1] = -DUMMY_RANGE_M
    state = init_state(x0, cfg.P0, 0.0, chaser, cfg)
    z = np.zeros((R, K, m))
    meas = Measurement(1.0, chaser, z, np.ones((R, K), dtype=bool), np.broadcast_to(np.eye(m), (R, K, m, m)))
    filter_step(state, meas, setup, prior=predict_to(state, 1.0, setup))


def load_in_background(setup: FilterSetup) -> threading.Thread | None:
    """load_kernels(setup) on a thread (started; returned), or None where setup's filter runs no fused kernel (the
    numpy reference, or sigma_chart 'rotation' or 'screw', which the numpy filter runs:
    step_update.uses_fused_kernel). A failure there is not the caller's: the first real step loads the code as
    before. Not a daemon: a process that ends first waits for it (on a machine without numba's cache, the compile
    it would have waited for at its first step) rather than leave LLVM compiling while the interpreter shuts
    down."""
    if not uses_fused_kernel(setup.cfg):
        return None

    def run() -> None:
        try:
            load_kernels(setup)
        except Exception:  # noqa: BLE001 - the real step meets the same error, where it can be reported
            pass

    thread = threading.Thread(target=run, name="filter-kernels")
    thread.start()
    return thread
