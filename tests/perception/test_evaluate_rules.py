"""The scoring rules of perception/evaluate.py on hand-built frames, each at its edge: a hit is within the radius,
the radius included; a swap is a corner near another's label and not near its own; on ambiguous frames the
alternative naming is taken only with more hits, or as many and a smaller summed error."""

import numpy as np

from envisat_pose.perception.evaluate import better_naming, hits, pck, swaps

K = 8


def frame(seed=0):
    """One frame: eight labels 40-600 px apart (well beyond any radius here), all usable."""
    rng = np.random.default_rng(seed)
    true = (np.arange(K)[:, None] * [70.0, 50.0] + 40.0 + rng.uniform(0, 5, (K, 2)))[None]
    return true, np.ones((1, K), bool)


def test_a_hit_is_within_the_radius_the_radius_included():
    true, usable = frame()
    pred = true.copy()
    pred[0, 0, 0] += 2.0  # exactly at r = 2
    pred[0, 1, 1] -= 2.0 + 1e-9  # just beyond
    got = hits(pred, true, usable, 2.0)[0]
    assert got.tolist() == [True, False] + [True] * 6
    assert pck(pred, true, usable, 2.0) == 7 / 8


def test_a_corner_near_another_label_is_a_swap_only_when_not_near_its_own():
    true, usable = frame()
    true[0, 1] = true[0, 0] + [3.0, 0.0]  # labels of corners 0 and 1 only 3 px apart
    pred = true.copy()
    pred[0, 0] = true[0, 0] + [1.0, 0.0]  # near its own label (1 px) and near 1's (2 px): no swap
    pred[0, 2] = true[0, 3] + [0.5, 0.0]  # corner 2 named where 3 is, far from its own: a swap
    got = swaps(pred, true, usable, 5.0)[0]
    assert got.tolist() == [False, False, True, False, False, False, False, False]


def test_the_alternative_naming_is_taken_only_with_more_hits_or_as_many_and_less_error():
    true, usable = frame()
    ambiguous = np.array([True])
    primary, alt = true + 1.0, true + 1.5  # as many hits (8 each), the primary's summed error smaller
    chosen, used = better_naming(primary, alt, ambiguous, true, usable)
    assert not used[0] and np.array_equal(chosen, primary)
    chosen, used = better_naming(alt, primary, ambiguous, true, usable)  # the other way round: the smaller one
    assert used[0] and np.array_equal(chosen, primary)
    worse = primary.copy()
    worse[0, :2] += 50.0  # two misses
    chosen, used = better_naming(worse, alt, ambiguous, true, usable)  # more hits: taken, whatever the error
    assert used[0]
    chosen, used = better_naming(worse, alt, np.array([False]), true, usable)  # not ambiguous: never
    assert not used[0] and np.array_equal(chosen, worse)
