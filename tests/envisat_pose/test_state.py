"""The state's layout helpers against direct computations."""

import numpy as np

from envisat_pose.state import BLOCK_SLICES, BLOCKS, N_STATE, block_sums, nees_window_diverged, nees_window_judged


def test_blocks_tile_the_state_and_block_sums_add_within_each():
    covered = np.concatenate([np.arange(N_STATE)[s] for s in BLOCK_SLICES])
    assert covered.tolist() == list(range(N_STATE)) and len(BLOCKS) == len(BLOCK_SLICES) == 4
    v = np.arange(2 * N_STATE, dtype=float).reshape(2, N_STATE)
    np.testing.assert_array_equal(block_sums(v), [[3, 12, 21, 30], [39, 48, 57, 66]])


def brute_force_divergence(nees, window, settle, factor):
    """Every window of `window` steps ending at step settle or later, one by one; a run with none whose last step
    is at or after settle: its steps from max(settle - window + 1, 0) on, as one shortened window."""
    out = []
    for run in nees:
        bad = False
        for end in range(max(settle, window - 1), len(run)):
            w = run[end - window + 1:end + 1]
            bad |= (not np.isfinite(w).all()) or w.mean() > factor * 12
        start = max(settle - window + 1, 0)
        if len(run) - start < window and len(run) - 1 >= settle:
            w = run[start:]
            bad = (not np.isfinite(w).all()) or w.mean() > factor * 12
        out.append(bad)
    return np.array(out)


def rule_before_short_runs(nees_rt, window, settle_steps, factor):
    """nees_window_diverged as it was before short runs were judged (commit 3c7681a): the long runs' reference."""
    e = np.asarray(nees_rt, dtype=float)[:, max(settle_steps - window + 1, 0):]
    if e.shape[1] < window:
        return np.zeros(e.shape[0], dtype=bool)
    c = np.cumsum(np.concatenate([np.zeros((e.shape[0], 1)), e], axis=1), axis=1)
    with np.errstate(invalid="ignore"):  # inf - inf past the infinite NEES below, as the rule had it
        window_sums = c[:, window:] - c[:, :-window]
    return (window_sums > factor * N_STATE * window).any(axis=1) | ~np.isfinite(e).all(axis=1)


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


def test_a_long_runs_flags_are_the_rule_before_short_runs_were_judged():
    """A run holding a whole window from max(settle - window + 1, 0): the same flags as before, on the same draws
    (diverged bursts, a NaN, a consistent NEES), whatever the window and settle steps."""
    rng = np.random.default_rng(4)
    nees = rng.chisquare(12, size=(30, 120))
    nees[::4, 70:90] *= 40.0
    nees[9, 100] = np.inf
    for window, settle in ((30, 60), (1, 0), (5, 10), (30, 0), (30, 29), (60, 60), (120, 0), (61, 60)):
        assert nees.shape[1] - max(settle - window + 1, 0) >= window
        for factor in (1.2, 10.0):
            np.testing.assert_array_equal(nees_window_diverged(nees, window, settle, factor),
                                          rule_before_short_runs(nees, window, settle, factor))


def test_a_run_too_short_for_a_window_is_judged_on_the_steps_it_has():
    """25 steps, a 30-step window from step 0, settle 20: a wildly diverged run (NEES 1e6, as 100 x P0's initial
    error gave) is flagged, a consistent one (chi-square, 12 dof) is not; before, neither was, without a word."""
    rng = np.random.default_rng(2)
    nees = rng.chisquare(12, size=(3, 25))
    nees[0] = 1e6
    nees[2, 24] = np.nan
    assert nees_window_judged(25, 20)
    assert nees_window_diverged(nees, 30, 20, 10.0).tolist() == [True, False, True]
    # its mean against the same factor: 10 x 12 on the mean of the 25 steps, not a single step's value
    nees[1, 3] = 10.0 * 12 * 25 / 2
    assert not nees_window_diverged(nees[1:2], 30, 20, 10.0)[0] and nees_window_diverged(nees[1:2], 30, 20, 2.0)[0]


def test_a_run_that_ends_before_the_settle_steps_is_not_judged():
    """41 steps (40 s at 1 Hz) against the default 60 settle steps: no flag is possible and nees_window_judged says
    so, for the callers to count the runs apart (filtering.estimator.unjudged_runs)."""
    from envisat_pose.filtering.estimator import FilterConfig, unjudged_runs

    nees = np.full((2, 41), 1e6)
    assert not nees_window_judged(41, 60) and nees_window_judged(61, 60) and not nees_window_judged(60, 60)
    assert not nees_window_diverged(nees, 30, 60, 10.0).any()
    cfg = FilterConfig()
    assert unjudged_runs(np.array([False, True]), 41, cfg).tolist() == [True, False]  # a flagged run is judged
    assert not unjudged_runs(np.array([False, False]), 61, cfg).any()
