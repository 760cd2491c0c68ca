"""The state's layout helpers against direct computations."""

import numpy as np

from envisat_pose.state import BLOCK_SLICES, BLOCKS, N_STATE, block_sums, nees_window_diverged


def test_blocks_tile_the_state_and_block_sums_add_within_each():
    covered = np.concatenate([np.arange(N_STATE)[s] for s in BLOCK_SLICES])
    assert covered.tolist() == list(range(N_STATE)) and len(BLOCKS) == len(BLOCK_SLICES) == 4
    v = np.arange(2 * N_STATE, dtype=float).reshape(2, N_STATE)
    np.testing.assert_array_equal(block_sums(v), [[3, 12, 21, 30], [39, 48, 57, 66]])


def brute_force_divergence(nees, window, settle, factor):
    """Every window of `window` steps ending at step settle or later, one by one."""
    out = []
    for run in nees:
        bad = False
        for end in range(max(settle, window - 1), len(run)):
            w = run[end - window + 1:end + 1]
            bad |= (not np.isfinite(w).all()) or w.mean() > factor * 12
        out.append(bad)
    return np.array(out)


def test_the_nees_window_monitor_equals_a_window_by_window_check():
    rng = np.random.default_rng(0)
    nees = rng.chisquare(12, size=(40, 60))
    nees[3, 50:55] = 400.0  # a late burst
    nees[5, 2:6] = 400.0  # a burst before the settle steps: ignored
    nees[7, 30] = np.nan
    for window, settle, factor in ((5, 10, 3.0), (10, 0, 1.5), (60, 0, 2.0), (70, 0, 2.0)):
        got = nees_window_diverged(nees, window, settle, factor)
        np.testing.assert_array_equal(got, brute_force_divergence(nees, window, settle, factor))
    got = nees_window_diverged(nees, 5, 10, 3.0)
    assert got[3] and not got[5] and got[7]
