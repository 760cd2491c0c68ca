"""The keypoint detector as the Tracker takes one (perception/keypoint_detect.KeypointFrameDetector): K rows named by
channel, a keypoint reported only where its visibility, its peak score and its calibrated sigma allow, its
covariance sigma_k^2 I; in a region of interest the network looks at that window alone."""

import os
import sys

import numpy as np
import pytest

from envisat_pose.config import InputError
from envisat_pose.perception.keypoint_detect import (
    KeypointDetector,
    KeypointFrameDetector,
    load_frame_detector,
)
from envisat_pose.target import load_target

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from keypoint_cases import untrained_weights  # noqa: E402

# the repository's models folder, by this file's place: the tests run from any working folder
MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "models")
UPPER = os.path.join(MODELS, "upper_stage.xml")


class Scripted(KeypointDetector):
    """A KeypointDetector whose network answers from a script (the boxes it was asked about are kept)."""

    def __init__(self, answer: dict):
        self.answer, self.boxes = answer, []
        self.cfg = type("Cfg", (), {"visible_threshold": 0.5, "coarse_threshold": 0.2, "crop_margin": 1.4})()
        self.model = type("Model", (), {"target": {"name": "t", "sha256": "ab"}})()
        self.keypoint_names = ("a", "b", "c")

    def network(self, image, box):
        self.boxes.append(tuple(int(v) for v in box))
        return dict(self.answer)

    def detect(self, image):
        self.boxes.append("whole")
        return {**self.answer, "crop_px": np.array([0, 0, 64])}


def test_reported_keypoints_and_their_covariance():
    answer = {"keypoints_px": np.array([[10.0, 12.0], [30.0, 31.0], [40.0, 41.0]]),
              "score": np.array([0.9, 0.9, 0.1]), "visible_prob": np.array([0.9, 0.2, 0.9])}
    det = KeypointFrameDetector(Scripted(answer), np.array([1.5, 2.0, 1.0]))
    fd = det.detect(np.zeros((64, 64), np.uint8), np.eye(3))
    # a: reported; b: the visibility head says hidden; c: its peak score is below the threshold
    np.testing.assert_array_equal(fd.visible, [True, False, False])
    np.testing.assert_allclose(fd.corners_px[0], [10.0, 12.0])
    assert np.isnan(fd.corners_px[1:]).all()
    np.testing.assert_allclose(fd.cov_px[0], np.eye(2) * 1.5 ** 2)
    assert fd.alt_probability == 0.5 and fd.corners_px.shape == (3, 2)
    uncalibrated = KeypointFrameDetector(Scripted(answer), np.array([np.nan, 2.0, 1.0]))
    assert not uncalibrated.detect(np.zeros((64, 64), np.uint8)).visible.any()  # a's sigma unknown: not given


def test_a_region_of_interest_is_looked_at_alone():
    answer = {"keypoints_px": np.zeros((3, 2)), "score": np.ones(3), "visible_prob": np.ones(3)}
    net = Scripted(answer)
    fd = KeypointFrameDetector(net, np.ones(3)).detect(np.zeros((64, 64), np.uint8), np.eye(3),
                                                       roi_px=np.array([8, 4, 32]))
    assert net.boxes == [(8, 4, 32)]
    np.testing.assert_array_equal(fd.crop_px, [8, 4, 32])


def test_loading_needs_calibrated_weights_of_the_target(tmp_path):
    target = load_target(UPPER)
    raw = untrained_weights(tmp_path / "raw.safetensors", UPPER)
    calibrated = untrained_weights(tmp_path / "cal.safetensors", UPPER, sigma_px=2.0)
    with pytest.raises(InputError, match="no calibrated pixel covariance"):
        load_frame_detector(raw, UPPER)
    # three keypoints with a sigma: the cold start's PnP (4 points) could never run; refused in one line
    import json

    from envisat_pose.perception.weights import with_metadata
    from envisat_pose.perception.weights_keys import SIGMA_KEY

    few = str(tmp_path / "few.safetensors")
    with_metadata(raw, few, {SIGMA_KEY: json.dumps([1.0, 1.0, 1.0] + [None] * (target.num_keypoints - 3))})
    with pytest.raises(InputError, match=r"only 3 of 12 keypoints calibrated; .* needs 4 for PnP"):
        load_frame_detector(few, UPPER)
    det = load_frame_detector(calibrated, UPPER)
    assert det.trained_for["sha256"] == target.sha256 and det.num_keypoints == 12
    fd = det.detect(np.zeros((128, 128), np.uint8), np.eye(3))
    assert fd.corners_px.shape == (12, 2) and fd.cov_px.shape == (12, 2, 2)
