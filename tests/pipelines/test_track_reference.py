"""No behaviour change under refactoring (issue 50's floor): two fixed, seeded tracks (a warm closed loop that
acquires and then tracks; track_frames over a generated sequence folder, cold) give exactly the est.npz and det.npz
arrays recorded before the refactor, in tests/data/track_reference.npz, written by tests/data/make_track_reference.py
(its docstring names the tracks). Rewrite the file only for a change meant to move the estimates, and say so."""

import importlib.util
import os

import numpy as np

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data")


def maker():
    spec = importlib.util.spec_from_file_location("make_track_reference",
                                                  os.path.join(DATA, "make_track_reference.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_fixed_tracks_give_the_recorded_estimates(tmp_path):
    now = maker().reference(str(tmp_path))
    with np.load(os.path.join(DATA, "track_reference.npz"), allow_pickle=False) as z:
        recorded = {k: z[k] for k in z.files}
    assert sorted(now) == sorted(recorded)
    # the plain arrays first: a failure shows the frames where the tracks part
    for key in sorted(recorded, key=lambda k: recorded[k].dtype.kind == "U"):
        np.testing.assert_array_equal(now[key], recorded[key], err_msg=key)
    # the tracks are the ones meant: the closed loop acquires, then tracks
    assert recorded["closed/status"][0].tolist() == [0] * 4 + [1] * 9
