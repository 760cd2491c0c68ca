"""The frames' own focal length against the camera's (pipelines/tracking/focal_check.py): keypoints projected here by
OpenCV's pinhole at a known focal length, read back through a camera that says another (the tracker's cold start
refusing such a camera: tests/pipelines/tracking/test_tracker.py)."""

import cv2
import numpy as np
import pytest

from envisat_pose.gates import chi2_bound
from envisat_pose.geometry import load_camera
from envisat_pose.pipelines.tracking.focal_check import FocalReading, focal_problems, focal_reading
from envisat_pose.pipelines.tracking.tracker_config import IntegrityConfig
from envisat_pose.target import load_target

CAM = load_camera()


def projected_window(f_true_px: float, frames: int = 20, sigma_px: float = 0.3, seed: int = 0):
    """ENVISAT's keypoints seen by a pinhole of focal length f_true_px (the MJCF camera's principal point) at 50 m
    in random attitudes, each frame's pixels with Gaussian noise sigma_px: (z (N, 8, 2), cov (N, 8, 2, 2), used)."""
    rng = np.random.default_rng(seed)
    X = np.asarray(load_target().keypoints_T_m, float)
    K = np.array([[f_true_px, 0.0, CAM.cu_px], [0.0, f_true_px, CAM.cv_px], [0.0, 0.0, 1.0]])
    z = np.stack([cv2.projectPoints(X, rng.normal(size=3), np.array([*rng.normal(0.0, 2.0, 2), 50.0]), K, None)[0][:, 0]
                  for _ in range(frames)]) + rng.normal(0.0, sigma_px, (frames, len(X), 2))
    cov = np.broadcast_to(np.eye(2) * sigma_px ** 2, z.shape + (2,)).copy()
    return z, cov, np.ones(z.shape[:2], bool), X


@pytest.mark.parametrize("camera_over_true", [1.0, 1.3, 0.75])
def test_a_window_reads_the_focal_length_that_made_its_frames(camera_over_true):
    """Frames made at f read through a camera that says f x c read the scale 1 / c (within 2 %, 0.3 px noise); the camera's own
    focal length is refused only where it is off: at c = 1 the likelihood ratio stays inside its 1-dof bound at
    1e-3 and nothing is refused."""
    z, cov, used, X = projected_window(CAM.f_px)
    reading = focal_reading(z, cov, used, X, CAM.f_px * camera_over_true, CAM.cu_px, CAM.cv_px)
    assert reading.frames == 20
    assert reading.scale == pytest.approx(1.0 / camera_over_true, rel=0.02)
    problems = focal_problems(reading, IntegrityConfig())
    if camera_over_true == 1.0:
        assert reading.lr < chi2_bound(1e-3, 1) and problems == []
    else:
        assert reading.lr > chi2_bound(IntegrityConfig().prob, 1)
        assert len(problems) == 1 and f"{reading.scale:.2f} x the camera's" in problems[0], problems


def test_a_reading_needs_six_keypoints_a_frame_and_three_frames():
    """Frames with five keypoints (pose and focal length not apart) or fewer than three frames read nothing, and
    nothing is refused."""
    z, cov, used, X = projected_window(CAM.f_px * 1.3)
    five = used.copy()
    five[:, 5:] = False
    assert focal_reading(z, cov, five, X, CAM.f_px, CAM.cu_px, CAM.cv_px) is None
    assert focal_reading(z[:2], cov[:2], used[:2], X, CAM.f_px, CAM.cu_px, CAM.cv_px) is None
    z[:, 0] = np.nan  # a missing keypoint is not read: six of eight left
    assert focal_reading(z, cov, used, X, CAM.f_px, CAM.cu_px, CAM.cv_px).scale == pytest.approx(1.3, rel=0.02)
    assert focal_problems(None, IntegrityConfig()) == []


def test_a_refusal_needs_both_a_focal_length_off_beyond_the_tolerance_and_the_evidence():
    """Off by no more than focal_tolerance (15 %), or a ratio inside its bound: no refusal; a scale at the search's
    bounds says "at least" or "at most"."""
    cfg = IntegrityConfig()
    bound = chi2_bound(cfg.prob, 1)
    assert focal_problems(FocalReading(1.14, 10.0 * bound, 20), cfg) == []
    assert focal_problems(FocalReading(0.86, 10.0 * bound, 20), cfg) == []
    assert focal_problems(FocalReading(1.14, 10.0 * bound, 20), IntegrityConfig(focal_tolerance=0.05)) != []
    assert focal_problems(FocalReading(1.3, 0.9 * bound, 20), cfg) == []
    assert focal_problems(FocalReading(0.7, 1.1 * bound, 20), cfg) != []
    assert "at least 2.00 x" in focal_problems(FocalReading(2.0 * (1 - 1e-9), 1e4, 20), cfg)[0]
    assert "at most 0.50 x" in focal_problems(FocalReading(0.5, 1e4, 20), cfg)[0]
    assert "a focal length 0.60 x" in focal_problems(FocalReading(0.6, 1e4, 20), cfg)[0]
