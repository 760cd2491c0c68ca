"""No behaviour change under refactoring: two fixed, seeded tracks (a warm closed loop that acquires and then
tracks; track_frames over a generated sequence folder, cold) give the est.npz and det.npz arrays recorded in
tests/data/track_reference.npz, written by tests/data/make_track_reference.py (its docstring names the tracks and
the recording's history), within the cross-machine tolerances of tests/data/compare.py: integers, flags and
statuses equal, floats to 1e-4 of each column's scale. Rewrite the file only for a change meant to move the
estimates, and say so."""

import importlib.util
import os
import sys

import numpy as np
import pytest

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "data")
sys.path.insert(0, DATA)
from compare import REL_OF_SCALE, assert_arrays_close  # noqa: E402


def maker():
    spec = importlib.util.spec_from_file_location("make_track_reference",
                                                  os.path.join(DATA, "make_track_reference.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def recorded() -> dict[str, np.ndarray]:
    with np.load(os.path.join(DATA, "track_reference.npz"), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_the_fixed_tracks_give_the_recorded_estimates(tmp_path):
    now, before = maker().reference(str(tmp_path)), recorded()
    assert sorted(now) == sorted(before)
    # the statuses first: a failure shows the frames where the tracks part
    for key in sorted(before, key=lambda k: (not k.endswith("status"), k)):
        assert_arrays_close(now[key], before[key], key)
    # the tracks are the ones meant: the closed loop acquires, then tracks
    assert before["closed/est/status"][0].tolist() == [0] * 4 + [1] * 9


def test_the_tolerance_sees_a_small_change():
    """A change of the estimates by 1e-3 of a state's scale (a fraction of what a changed filter moves), or one
    status flipped, fails the comparison."""
    before = recorded()
    x = before["closed/est/x_hat"]
    moved = x.copy()
    moved[0, -1, 1] += 1e-3 * np.nanmax(np.abs(x[..., 1]))
    assert_arrays_close(x + 0.1 * REL_OF_SCALE * np.nan_to_num(np.abs(x)), x, "within")
    with pytest.raises(AssertionError, match="scale"):
        assert_arrays_close(moved, x, "x_hat")
    status = before["closed/est/status"].copy()
    status[0, 4] = 0
    with pytest.raises(AssertionError):
        assert_arrays_close(status, before["closed/est/status"], "status")
