"""The keypoints a frame needs (tracker.acquire.min_keypoints for a cold-start pose, tracker.roi.min_keypoints in the
region of interest) were bounded by ENVISAT's 8 corners in the config: a CubeSat's tracker (12 keypoints) could not
ask for 10, and the bound said "corners" for any target. The config now asks for at least PnP's 4 (1 in the
region of interest) and the Tracker, which knows its target, refuses more than the target's keypoints in one line
naming the key: no frame would ever hold enough."""

import pytest

from envisat_pose.config import ConfigError
from envisat_pose.geometry import load_camera
from envisat_pose.pipelines.tracking.tracker import Tracker, TrackerConfig
from envisat_pose.target import load_target

CAM = load_camera().scaled(256, 256)


def _chaser():
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.tracking.onboard import chaser_function

    return chaser_function(scenario_config("default").orbit)


def test_the_config_takes_more_than_eight_and_refuses_fewer_than_pnp_needs():
    TrackerConfig(acquire={"min_keypoints": 10}, roi={"min_keypoints": 12}).validate()
    with pytest.raises(ConfigError, match=r"acquire.min_keypoints = 3: expected at least 4 keypoints"):
        TrackerConfig(acquire={"min_keypoints": 3}).validate()
    with pytest.raises(ConfigError, match=r"roi.min_keypoints = 0: expected at least 1 keypoint"):
        TrackerConfig(roi={"min_keypoints": 0}).validate()


@pytest.mark.parametrize("section", ["acquire", "roi"])
def test_the_tracker_refuses_more_than_its_targets_keypoints(section):
    chaser = _chaser()
    with pytest.raises(ConfigError, match=rf"tracker.{section}.min_keypoints = 9: expected at most the target's 8 "
                                          r"keypoints \(more: no frame ever holds enough\)"):
        Tracker(CAM, object(), chaser, TrackerConfig(**{section: {"min_keypoints": 9}}))
    Tracker(CAM, object(), chaser, TrackerConfig(**{section: {"min_keypoints": 8}}))
    cubesat = load_target("models/cubesat_3u.xml")
    assert cubesat.num_keypoints == 12
    Tracker(CAM, object(), chaser, TrackerConfig(**{section: {"min_keypoints": 10}}), target=cubesat)
    with pytest.raises(ConfigError, match=rf"tracker.{section}.min_keypoints = 13: expected at most the target's 12"):
        Tracker(CAM, object(), chaser, TrackerConfig(**{section: {"min_keypoints": 13}}), target=cubesat)
