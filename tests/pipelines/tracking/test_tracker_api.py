"""The Tracker as a user scripts it: its `target` argument (a Target or the file's path, whichever the two
constructors are given), a detector that cannot name the target's keypoints refused before any frame, and the
frame checks of Tracker.step as InputError naming the argument."""

import os

import numpy as np
import pytest

from envisat_pose import Tracker, chaser_from_orbit, load_target, tracker_camera, tracker_detector
from envisat_pose.config import InputError

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
UPPER_STAGE = os.path.join(ROOT, "models", "upper_stage.xml")
UPPER_STAGE_WEIGHTS = os.path.join(ROOT, "models", "upper_stage_detector.safetensors")


@pytest.fixture(scope="module")
def parts():
    return tracker_camera(None, size_px=(64, 64)), chaser_from_orbit(None)


def test_the_target_is_taken_as_a_target_or_its_file_by_both_constructors(parts):
    cam, chaser = parts
    det = tracker_detector(UPPER_STAGE_WEIGHTS, target=UPPER_STAGE)
    for given in (load_target(UPPER_STAGE), UPPER_STAGE):
        assert Tracker(cam, det, chaser, target=given).K == 12
        assert Tracker.from_scenario("default", UPPER_STAGE_WEIGHTS, size_px=(64, 64), target=given).K == 12
    with pytest.raises(InputError, match=r"target: .*expected a Target"):
        Tracker(cam, det, chaser, target=12)


def test_filter_settings_of_another_type_are_an_input_error_naming_filter_config(parts):
    """Both constructors take a FilterConfig, a dict of its fields or None; a list was a bare TypeError that named
    no argument."""
    cam, chaser = parts
    with pytest.raises(InputError, match=r"filter_config: \[0.1\]; expected a FilterConfig"):
        Tracker(cam, tracker_detector(None), chaser, filter_config=[0.1])
    with pytest.raises(InputError, match=r"filter_config: 'adaptive_r'; expected a FilterConfig"):
        Tracker.from_scenario("default", None, size_px=(64, 64), filter_config="adaptive_r")


def test_envisats_corner_network_is_refused_for_another_target_before_any_frame(parts):
    """It names ENVISAT's 8 corners, not the target's keypoints: taken, its first lit frame's PnP failed with an
    IndexError (12 keypoints against 8 corners)."""
    cam, chaser = parts
    with pytest.raises(InputError, match="ENVISAT's corner detector.*upper_stage"):
        Tracker(cam, tracker_detector(None), chaser, target=load_target(UPPER_STAGE))


@pytest.mark.parametrize("t_s, match", [(float("nan"), "t_s = nan"), ("1", "t_s = '1'"), (0.0, "t_s = 0.0"),
                                        (-1.0, "t_s = -1.0")])
def test_a_frame_time_refused_is_an_input_error_naming_t_s(parts, t_s, match):
    cam, chaser = parts
    tracker = Tracker(cam, tracker_detector(None), chaser)
    tracker.step(0.0, None)
    with pytest.raises(InputError, match=match):
        tracker.step(t_s, None)
    with pytest.raises(InputError, match=r"image: float64 \(64, 64\)"):
        tracker.step(1.0, np.zeros((64, 64)))
    assert tracker.step(1.0, np.zeros((64, 64), np.uint8)).t_s == 1.0  # a refused frame changed nothing


def test_a_first_frame_before_the_priors_time_is_refused_and_changes_nothing(parts):
    """Taken, it failed deep in the filter ("older than the filter state") after the tracker had kept its time, so
    every later frame before t0 failed too and the first frame interval was measured from it."""
    cam, chaser = parts
    x0 = np.r_[0.0, 50.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3, 0.0, 0.0, 0.04]
    P0 = np.diag(np.r_[[0.1] * 3, [0.01] * 3, [0.01] * 3, [0.001] * 3] ** 2)
    tracker = Tracker(cam, tracker_detector(None), chaser, prior=(x0, P0, 10.0))
    with pytest.raises(InputError, match=r"t_s = 5.0: expected a time at or after the prior's t0 = 10.0 s"):
        tracker.step(5.0, None)
    assert tracker.t_last is None
    est = tracker.step(10.0, None)
    assert est.t_s == 10.0 and np.allclose(est.x_hat[:3], x0[:3], atol=1e-6)


def test_a_frame_too_long_after_the_track_loses_it_without_predicting_across(parts):
    """A frame 1e300 s after the prior (a typo in a timestamps file, a clock's wrap): the filter's propagation
    asked numpy for an array of that many steps (ValueError: Maximum allowed dimension exceeded), and a gap of
    1e8 s took minutes for the one frame. The track is lost instead, saying why, and the tracker goes on."""
    cam, chaser = parts
    x0 = np.r_[0.0, 50.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3, 0.0, 0.0, 0.04]
    P0 = np.diag(np.r_[[0.1] * 3, [0.01] * 3, [0.01] * 3, [0.001] * 3] ** 2)
    tracker = Tracker(cam, tracker_detector(None), chaser, prior=(x0, P0, 10.0))
    assert tracker.planned_window(1e300) is None
    est = tracker.step(1e300, None)
    assert est.status == "lost" and est.events == ("lost: 1e+300 s since the track's last frame, beyond the 1000000 s "
                                                   "a track is predicted over",)
    assert tracker.state is None and tracker.step(2e300, np.zeros((64, 64), np.uint8)).status == "acquiring"
    tracker = Tracker(cam, tracker_detector(None), chaser, prior=(x0, P0, 10.0))
    est = tracker.step(10.0 + 3600.0, None)  # an hour's gap: predicted across, as before (and judged)
    assert np.isfinite(est.x_hat).all() and not any("predicted over" in e for e in est.events), est.events


BOX_XML = ('<mujoco model="box5"><worldbody><body name="target"><inertial pos="0 0 0" mass="100" '
           'diaginertia="30 40 50"/><geom name="hull" type="box" size="1 0.7 0.5" rgba="0.7 0.7 0.7 1"/>'
           + "".join(f'<site name="kp_{i}" pos="{x} {y} {z}"/>' for i, (x, y, z) in
                     enumerate([(1, 0.7, 0.5), (1, -0.7, 0.5), (-1, -0.7, 0.5), (-1, 0.7, -0.5), (0.3, 0.2, 0.5)]))
           + "</body></worldbody></mujoco>")


@pytest.fixture(scope="module")
def box5(tmp_path_factory):
    path = tmp_path_factory.mktemp("box5") / "box5.xml"
    path.write_text(BOX_XML)
    return load_target(str(path))


class Scripted:
    """Answers every frame with what `answer(K)` makes (a detector of the user's own, recording no target)."""

    def __init__(self, answer):
        self.answer = answer

    def detect(self, image, K, roi_px=None, **priors):
        return self.answer()


def found(K=5, **fields):
    from envisat_pose.perception.detect import FrameDetection

    z = np.tile([[30.0, 32.0]], (K, 1)) + np.arange(K)[:, None]
    base = dict(corners_px=z, cov_px=np.tile(np.eye(2), (K, 1, 1)), confidence=np.ones(K), visible=np.ones(K, bool),
                alt_corners_px=np.full((K, 2), np.nan), alt_probability=0.5, ambiguous=False,
                crop_px=np.array([0.0, 0.0, 64.0]), candidates_px=np.zeros((0, 2)))
    return FrameDetection(**{**base, **fields})


@pytest.mark.parametrize("answer, match", [
    (lambda: found(K=8), r"corners_px: shape \(8, 2\); expected \(5, 2\).*ENVISAT's 8 corners"),
    (lambda: found(corners_px=np.zeros((5, 3))), r"corners_px: shape \(5, 3\); expected \(5, 2\)"),
    (lambda: found(cov_px=np.ones((5, 2))), r"cov_px: shape \(5, 2\); expected \(5, 2, 2\)"),
    (lambda: found(visible=np.ones(4, bool)), r"visible: shape \(4,\); expected \(5,\)"),
    (lambda: found(cov_px=np.zeros((5, 2, 2))), r"cov_px\[0\]: .*expected a symmetric positive-definite"),
    (lambda: found(cov_px=-np.tile(np.eye(2), (5, 1, 1))), r"cov_px\[0\]: .*positive-definite .*5 keypoint"),
    (lambda: None, r"detector.detect returned NoneType; expected .*FrameDetection.missing\(crop, 5\)"),
])
def test_a_detectors_answer_the_tracker_cannot_read_is_refused_naming_the_field(box5, parts, answer, match):
    """A detector of the user's own that answers with another keypoint count (ENVISAT's 8 corners for a
    5-keypoint target), arrays of the wrong shape or a found keypoint with a zero or negative covariance is refused
    at the frame, naming the field and what was expected, and the frame is not taken (the same time is taken
    again). Before: an IndexError in the cold start's PnP, a broadcast ValueError, a LinAlgError in the filter,
    or corners (K, 3) and None never used, acquiring forever without a word."""
    cam, chaser = parts
    tracker = Tracker(cam, Scripted(answer), chaser, target=box5)
    assert tracker.K == 5
    image = np.zeros((64, 64), np.uint8)
    with pytest.raises(InputError, match=match):
        tracker.step(0.0, image)
    tracker.detector = Scripted(lambda: found(visible=np.array([1, 1, 0, 1, 1], bool)))
    assert tracker.step(0.0, image).status == "acquiring"  # the refused frame was not taken: its time is free
    # a keypoint not found may carry any covariance, NaN or none
    tracker.detector = Scripted(lambda: found(visible=np.array([1, 1, 0, 1, 1], bool),
                                              cov_px=np.where(np.arange(5)[:, None, None] == 2, 0.0, np.eye(2))))
    assert tracker.step(1.0, image).measured.tolist() == [True, True, False, True, True]
