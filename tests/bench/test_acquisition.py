"""bench/acquisition.py's bookkeeping on synthetic trials (no rendering): a wrong first track is a failure and a
false lock, a trial that never tracks is a failure (not dropped), a refused trial is counted apart; the draws of a
bin follow the root seed and the bin, whatever other bins run."""

import importlib.util
import os

import numpy as np

from envisat_pose.pipelines.runs.scoring import frame_errors, run_record
from envisat_pose.status import ACQUIRING, COASTING, TRACKING

HERE = os.path.dirname(os.path.abspath(__file__))
T = 90
RANGE_M = 30.0


def load_bench():
    path = os.path.join(HERE, "..", "..", "bench", "acquisition.py")
    spec = importlib.util.spec_from_file_location("acquisition_bench", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def trial(first_track: int | None, wrong_frames: slice = slice(0, 0)) -> dict:
    """A flown trial: acquiring until first_track (None: all along), then tracking; 1 m and 10 deg off on
    wrong_frames (claimed as coasting on their first one)."""
    t = np.arange(T, dtype=float)
    x_true = np.zeros((T, 12))
    x_true[:, 1] = RANGE_M
    x_hat = x_true.copy()
    x_hat[wrong_frames, 0] += 1.0  # 1 m at 30 m: beyond 2 % (0.6 m)
    x_hat[wrong_frames, 6] += np.tan(np.radians(10.0) / 4)
    status = np.full(T, ACQUIRING)
    if first_track is not None:
        status[first_track:] = TRACKING
        if wrong_frames.stop > wrong_frames.start:
            status[wrong_frames.start] = COASTING if wrong_frames.start > first_track else TRACKING
    P = np.broadcast_to(np.eye(12) * 1e-4, (T, 12, 12))
    rec = run_record(t, frame_errors(x_true, x_hat, P), status, np.ones(T, bool))
    return {"refused": None, "record": rec}


def test_a_bin_counts_failures_false_locks_and_refusals():
    bench = load_bench()
    trials = [trial(20), trial(30, slice(50, 55)), trial(10, slice(10, 20)), trial(None),
              trial(70), {"refused": "relative.rho0_C_m: ... 1.72 m from geom 'array'"}]
    b = bench.bin_summary(trials)
    assert b["trials"] == 6 and b["refused_keepout"] == 1 and b["flown"] == 5
    # correct first tracks: at 20, 30 (a later excursion), 70 s; the one at 10 s is wrong, one never tracks
    assert b["success"] == 3 and b["success_rate"] == 3 / 5
    assert b["success_within_60_s"] == 2  # the one at 70 s is late
    assert b["false_locks"] == 2 and b["false_lock_s"] == 5.0 + 10.0
    assert b["never_tracked"] == 1 and b["without_correct_track"] == 1
    # first correct tracks at 20, 30, 20 (after the wrong one), 70 s
    assert b["time_to_first_correct_track_median_s"] == 25.0 and b["time_to_first_correct_track_max_s"] == 70.0


def test_a_bins_draws_follow_its_seed_not_the_other_bins():
    bench = load_bench()
    a = bench.bin_seeds(0, 30.0, "stress", 3)
    b = bench.bin_seeds(0, 30.0, "stress", 5)[:3]
    assert [s.generate_state(2).tolist() for s in a] == [s.generate_state(2).tolist() for s in b]
    c = bench.bin_seeds(0, 40.0, "stress", 3)
    d = bench.bin_seeds(1, 30.0, "stress", 3)
    states = {tuple(s.generate_state(2).tolist()) for s in a + c + d}
    assert len(states) == 9


def test_a_crashed_trial_is_counted_apart():
    bench = load_bench()
    b = bench.bin_summary([trial(20), {"refused": None, "error": "MemoryError: ..."}])
    assert b["flown"] == 1 and b["errors"] == 1 and b["refused_keepout"] == 0 and b["success_rate"] == 1.0
