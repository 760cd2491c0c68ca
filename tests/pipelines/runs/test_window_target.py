"""The closed loop of another target than ENVISAT renders only the window its tracker looks at (RunConfig.render_window,
on by default; pipelines/runs/loop_frames.py), and the tracker sees in it what it sees in whole frames.

The shipped upper stage, default scenario, 50 s of 512-px frames, seed 4. The detector is a stand-in that reads pixels: it names the
MuJoCo truth's visible keypoints of the frame (the tracker's frame time gives the index; nothing else of the truth
reaches the tracker) where the frame shows light within 3 px of them, with 0.5 px of noise drawn per frame. A window
that left out part of the target (a wrong offset, too small a side) would show black there, the keypoints would go
missing and the track with them. Independent reference: the same loop with every frame whole (--full-frames)."""

import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "perception"))
from keypoint_cases import untrained_weights  # noqa: E402

from envisat_pose.geometry import load_camera
from envisat_pose.perception.detect import FrameDetection
from envisat_pose.pipelines.jobs import resolve_job
from envisat_pose.pipelines.runs import closed_loop
from envisat_pose.pipelines.tracking.tracker import Tracker

# the repository's models folder, by this file's place: the tests run from any working folder
MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))),
                      "models")
UPPER = os.path.join(MODELS, "upper_stage.xml")
SIGMA_PX = 0.5
RES = 512  # px, square frames
LIGHT_DN = 8  # a keypoint is shown where some pixel within 3 px is at least this bright


class PixelReadingDetector:
    """Names the truth's visible keypoints of frame `k` (set before each step) that the image shows lit."""

    def __init__(self, truth, resolution_px: int):
        self.truth, self.k = truth, 0
        self.K = truth.corners_px.shape[1]
        # the truth's keypoints are projected at the MJCF camera's size: here at the frames'
        self.uv = closed_loop.rescale_px(truth.corners_px, load_camera(), closed_loop.run_camera(resolution_px))
        self.shown = {}  # frame -> (K,) keypoints found lit

    def detect(self, image, K, roi_px=None, **priors):
        k, uv = self.k, self.uv[self.k]
        seen = self.truth.visible[k] & self.truth.in_frame[k]
        lit = np.zeros(self.K, bool)
        for i in np.flatnonzero(seen):
            u, v = np.round(uv[i]).astype(int)
            patch = image[max(v - 3, 0):v + 4, max(u - 3, 0):u + 4]
            lit[i] = patch.size > 0 and int(patch.max()) >= LIGHT_DN
        self.shown[k] = lit
        rng = np.random.default_rng(k)
        z = np.where(lit[:, None], uv + rng.normal(0.0, SIGMA_PX, (self.K, 2)), np.nan)
        cov = np.where(lit[:, None, None], np.eye(2) * SIGMA_PX ** 2, np.nan)
        return FrameDetection(z, cov, lit * 0.9, lit, np.full_like(z, np.nan), 0.5, False,
                              np.array([0.0, 0.0, float(image.shape[0])]), z[lit])


def run(tmp_path, monkeypatch, weights, whole: bool):
    cfg = resolve_job("run", "default", overrides={"duration_s": 50.0, "seed": 4, "workers": 1, "weights": weights,
                                                   "image.resolution_px": RES,
                                                   "image.target": UPPER, "render_window": not whole})
    det = PixelReadingDetector(closed_loop.run_truth(cfg), RES)
    step = Tracker.step

    def stepping(self, t_s, image, window_px=None):
        det.k = int(round(t_s * cfg.rate_hz))
        return step(self, t_s, image, window_px)

    monkeypatch.setattr(Tracker, "step", stepping)
    monkeypatch.setattr(closed_loop, "tracker_detector", lambda *a, **kw: det)
    out = tmp_path / ("whole" if whole else "window")
    closed_loop.run_closed_loop(cfg, str(out), progress=False, sink=None)
    return json.loads((out / "summary.json").read_text()), det.shown


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return untrained_weights(tmp_path_factory.mktemp("window_target") / "upper.safetensors", UPPER, sigma_px=SIGMA_PX)


def test_another_targets_loop_tracks_on_the_windows_it_renders(tmp_path, monkeypatch, weights):
    window, shown_w = run(tmp_path, monkeypatch, weights, whole=False)
    whole, shown_f = run(tmp_path, monkeypatch, weights, whole=True)
    assert window["run0"]["frames_windowed"] >= 15 and whole["run0"]["frames_windowed"] == 0
    for s in (window["scores"], whole["scores"]):
        assert s["first_track_correct"] == 1 and s["false_lock_s"] == 0.0
    windowed = [k for k in shown_w if k > 0 and k in shown_f]
    # the keypoints the window shows lit are the whole frame's, up to the noise of a dim one
    differ = sum(int((shown_w[k] != shown_f[k]).sum()) for k in windowed)
    assert differ <= 0.01 * sum(int(shown_f[k].sum()) for k in windowed), differ
