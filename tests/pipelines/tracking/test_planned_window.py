"""Tracker.planned_window's rule (the closed loop renders the window alone where it gives one): None while the
claim is unconfirmed, even with one hypothesis (a warm start: ENVISAT's array cue reads the whole confirming
frames), and for the frame after one whose window held too few keypoints (its detection fell back to the whole
frame, which a window alone would show black), then windows again; a window of no pixels is refused. Scripted
detectors on the default scenario's MuJoCo truth (tests/pipelines/tracking/test_tracker.py's)."""

import dataclasses
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_tracker import NoisyTruthDetector, chaser_lookup, frame_image  # noqa: E402

from envisat_pose.geometry import load_camera
from envisat_pose.pipelines.tracking.tracker import Tracker, TrackerConfig
from envisat_pose.pipelines.tracking.tracker_config import ArrayCueConfig

NO_CUE = TrackerConfig(array_cue=ArrayCueConfig(enabled=False))


class ShortWindow(NoisyTruthDetector):
    """Finds nothing inside the region of interest at frame `short_at` (the whole frame it finds as always)."""

    short_at: int | None = None

    def detect(self, image, K, roi_px=None, **kw):
        fd = super().detect(image, K, roi_px, **kw)
        if roi_px is not None and int(image[0, 0]) * 256 + int(image[0, 1]) == self.short_at:
            return dataclasses.replace(fd, visible=np.zeros(8, bool))
        return fd


def test_after_a_window_that_held_too_few_keypoints_the_next_frame_is_whole(truth_600):
    det = ShortWindow(truth_600, seed=3)
    tracker = Tracker(load_camera(), det, chaser_lookup(truth_600), NO_CUE)
    windows, ests = [], []
    for k in range(60):
        t = float(truth_600.t_s[k])
        windows.append(tracker.planned_window(t))
        ests.append(tracker.step(t, frame_image(k), windows[-1]))
        if det.short_at is None and "confirmed" in ests[-1].events:
            det.short_at = k + 4
    s = det.short_at
    assert s is not None and s + 2 < 60 and windows[s] is not None
    assert ests[s].roi_px is None  # frame s was detected whole in the end
    assert windows[s + 1] is None  # so frame s + 1 is made whole
    assert windows[s + 2] is not None  # and windows come back once a frame is seen whole


def test_a_warm_start_plans_no_window_until_its_claim_is_confirmed(truth_600):
    """A prior at the truth, tight enough that the region of interest is on from the first frame: one
    hypothesis, yet whole frames until 'confirmed' (and windows after)."""
    x0 = truth_600.x[0].copy()
    P0 = np.diag(np.r_[[1e-4] * 3, [1e-6] * 3, [1e-6] * 3, [1e-8] * 3])
    tracker = Tracker(load_camera(), NoisyTruthDetector(truth_600, seed=3), chaser_lookup(truth_600), NO_CUE,
                      prior=(x0, P0, float(truth_600.t_s[0])))
    windows, confirmed_at = [], None
    for k in range(1, 30):
        t = float(truth_600.t_s[k])
        windows.append((k, tracker.planned_window(t)))
        est = tracker.step(t, frame_image(k))
        if confirmed_at is None and "confirmed" in est.events:
            confirmed_at = k
    assert confirmed_at is not None and confirmed_at > 1
    assert all(w is None for k, w in windows if k <= confirmed_at)
    assert all(w is not None for k, w in windows if k > confirmed_at)
    with pytest.raises(ValueError, match="window_px"):  # a window of no pixels is refused, not taken as made
        tracker.step(float(truth_600.t_s[30]), frame_image(30), np.array([10, 10, 0]))
