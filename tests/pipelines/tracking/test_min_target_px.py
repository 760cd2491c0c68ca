"""A tracker whose integrity.min_target_px no state can meet under its camera's focal length never tracked, without
a word: the box (twice its radius) spans at most 2 f px, at its closest range (its own radius: nearer, the camera is
inside it), and a larger min_target_px puts the range bound f 2 radius / min_target_px inside the box, so every
cold start's fit is refused as out of range. Refused now in one line naming the key, its value and 2 f: by the
Tracker, by `envisat run`'s config (the MJCF camera at image.resolution_px) and by `envisat track` (its camera file
or the MJCF's) before anything is written. A min_target_px below 2 f is taken (it can track, near enough)."""

import dataclasses

import numpy as np
import pytest

from envisat_pose.app.cli import main
from envisat_pose.config import ConfigError
from envisat_pose.geometry import load_camera
from envisat_pose.pipelines.tracking import integrity as ig
from envisat_pose.pipelines.tracking.tracker import Tracker, TrackerConfig
from envisat_pose.state import POS

CAM_256 = load_camera().scaled(256, 256)  # f = 477.7 px: 2 f = 955.4 px


def test_at_or_above_twice_the_focal_length_no_state_passes_the_range_bound():
    """Why it is refused: at min_target_px = 2 f every state, even one just outside the box, is beyond the range
    bound; just below 2 f a state near the box passes."""
    radius, P = 13.0, np.eye(12) * 1e-6
    cfg = TrackerConfig().integrity
    x = np.zeros(12)
    for min_px, near_ok in ((2.0 * CAM_256.f_px, False), (0.99 * 2.0 * CAM_256.f_px, True)):
        at = dataclasses.replace(cfg, min_target_px=min_px)
        passes = []
        for range_m in radius * np.array([1.001, 1.005, 2.0, 10.0, 100.0]):
            x[POS] = [0.0, range_m, 0.0]  # along the boresight of the MJCF camera (its depth is the range)
            passes.append(not any("range" in p for p in ig.state_problems(x, P, CAM_256, radius, at)))
        assert any(passes) == near_ok, (min_px, passes)


def test_the_tracker_refuses_a_min_target_px_its_camera_never_shows():
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.tracking.onboard import chaser_function

    chaser = chaser_function(scenario_config("default").orbit)
    with pytest.raises(ConfigError, match=r"integrity.min_target_px = 1000.0: expected a size below 955.4 px: the "
                                          r"box's apparent size at its closest range, its own radius \(.* m\), is "
                                          r"2 f = 955.4 px under the camera's focal length f = 477.7 px"):
        Tracker(CAM_256, object(), chaser, TrackerConfig(integrity={"min_target_px": 1000.0}))
    Tracker(CAM_256, object(), chaser, TrackerConfig(integrity={"min_target_px": 950.0}))  # can track, near
    Tracker(load_camera(), object(), chaser, TrackerConfig(integrity={"min_target_px": 1000.0}))  # f 1911 px


def test_a_run_config_is_refused_at_its_image_size():
    from envisat_pose.pipelines.runs.run_config import RunConfig

    with pytest.raises(ConfigError, match=r"tracker.integrity.min_target_px = 1000.0: expected a size below 955.4 px"):
        RunConfig(duration_s=5.0, image={"resolution_px": 256}, tracker={"integrity": {"min_target_px": 1000.0}})
    RunConfig(duration_s=5.0, image={"resolution_px": 256}, tracker={"integrity": {"min_target_px": 950.0}})
    RunConfig(duration_s=5.0, tracker={"integrity": {"min_target_px": 1000.0}})  # at 1024 px: 2 f = 3822 px
    RunConfig(duration_s=5.0, image={"resolution_px": 16})  # the default 8 px at the smallest image: 2 f = 59.7 px


def test_track_refuses_it_with_the_camera_file_before_any_frame_is_read(tmp_path, capsys):
    import cv2

    src = tmp_path / "seq"
    src.mkdir()
    for i in range(4):
        assert cv2.imwrite(str(src / f"img_{i}.png"), np.zeros((32, 32), np.uint8))
    cam = tmp_path / "cam.toml"
    cam.write_text("fx = 100.0\nfy = 100.0\ncx = 15.5\ncy = 15.5\nwidth = 32\nheight = 32\n")
    cfg = tmp_path / "job.toml"
    for min_px, said in ((200.0, "tracker.integrity.min_target_px = 200.0: expected a size below 200 px"),
                         (199.0, "4 frame(s); the tracker's cold start needs")):  # taken: the next refusal's
        cfg.write_text(f"[tracker.integrity]\nmin_target_px = {min_px}\n")
        code = main(["track", "--images", str(src), "--rate-hz", "1", "--camera", str(cam), "--config", str(cfg),
                     "--out", str(tmp_path / "never"), "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and said in err[0], err
        assert not (tmp_path / "never").exists()
