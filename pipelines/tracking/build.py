"""The parts a library user builds a tracker from (the public API's builders, exported from `envisat_pose`).

`tracker_camera` (the MJCF's chaser_cam, at a frame size, or a camera TOML file), `tracker_detector` (the shipped
weights by default), `chaser_from_orbit` (what the chaser knows of its own orbit: chaser_at(t_s) -> r, rdot,
theta, thetadot) and `tracker_filter` (the tracker's filter settings with a user's overrides: only the fields
given change) are what `Tracker.from_scenario` (pipelines.tracker.tracker_from_scenario) joins; each may be used
alone. They know nothing of the Tracker itself, so the tracker imports them and not the other way round.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from envisat_pose import geometry, named_scenarios
from envisat_pose.config import InputError, check, from_dict, load_toml, to_dict
from envisat_pose.datagen.scenario import OrbitConfig, scenario_config
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.pipelines.tracking.camera_file import camera_from_intrinsics
from envisat_pose.pipelines.tracking.onboard import chaser_function
from envisat_pose.pipelines.tracking.tracker_config import TRACKER_FILTER
from envisat_pose.target import other_target


def tracker_filter(overrides: FilterConfig | dict | None = None, scenario: str | None = None) -> FilterConfig:
    """The tracker's filter settings (pipelines.tracker.TRACKER_FILTER over FilterConfig's defaults, then the named
    scenario's [filter] table) with the fields a user gives: a dict sets exactly its keys; a FilterConfig sets the
    fields whose values differ from FilterConfig()'s defaults (to set a field back to FilterConfig's own default,
    give a dict)."""

    base = dict(TRACKER_FILTER)
    if scenario is not None:
        base.update(named_scenarios.scenario_tables(scenario).get("filter", {}))
    if overrides is None:
        given = {}
    elif isinstance(overrides, dict):
        given = dict(overrides)
    elif isinstance(overrides, FilterConfig):
        default = FilterConfig()
        given = {f.name: getattr(overrides, f.name) for f in dataclasses.fields(FilterConfig)
                 if getattr(overrides, f.name) != getattr(default, f.name)}
    else:
        raise InputError(f"filter_config: {overrides!r:.60}; expected a FilterConfig, a dict of its fields or None")
    merged = {**base, **{k: (to_dict(v) if dataclasses.is_dataclass(v) else v) for k, v in given.items()}}
    return from_dict(FilterConfig, merged, prefix="filter")


def tracker_camera(path: str | None = None, size_px: tuple[int, int] | None = None):
    """The tracker's camera (geometry.PinholeCamera): the MJCF's chaser_cam (read out at size_px = (width,
    height) when given: the same field of view), or a camera TOML file's pinhole (fx, fy, cx, cy, width, height).
    A file whose frames are not ideal (distortion, or fx != fy) is refused in one line naming the key: the Tracker
    takes ideal frames, and a bare pinhole would drop their undistortion (camera_file.camera_from_intrinsics
    returns the camera with its cv2.remap maps; track_frames(camera=path) applies them to every frame)."""

    if path is not None:
        cam, remap = camera_from_intrinsics(path)
        if remap is not None:
            data = load_toml(path)
            why = (f"distortion = {data['distortion']!r}" if any(data.get("distortion") or ())
                   else f"fx = {data['fx']!r}, fy = {data['fy']!r}")
            raise InputError(f"{path}: {why}: frames of this camera need undistorting, which tracker_camera cannot "
                             "carry; use camera_file.camera_from_intrinsics (the camera and its cv2.remap maps) or "
                             "track_frames(camera=path)")
        return cam
    cam = geometry.load_camera()
    if size_px is not None:
        check(_is_size(size_px), "size_px", size_px,
              f"(width, height): two whole numbers of pixels, each at least {geometry.MIN_SIDE_PX}")
    if size_px is not None and tuple(size_px) != (cam.width_px, cam.height_px):
        cam = cam.scaled(int(size_px[0]), int(size_px[1]))
    return cam


def _is_size(size_px) -> bool:
    sides = tuple(size_px) if isinstance(size_px, (tuple, list)) else ()
    return len(sides) == 2 and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool)
                                   and v >= geometry.MIN_SIDE_PX for v in sides)


def tracker_detector(weights: str | None = None, device: str = "cpu", target: str | None = None,
                     bf16: bool = False):
    """The tracker's detector of a weights file: ENVISAT's corner detector (perception.detect.Detector; weights
    None: the shipped ones; bf16: its network in bfloat16, DetectConfig.bf16) when target is None or ENVISAT's
    file, else the keypoint detector of that target's file (perception.keypoint_detect.KeypointFrameDetector: its
    weights, by default FILE_detector.safetensors beside the file, trained for that target and calibrated; bf16
    refused)."""
    if other_target(target) is None:
        from envisat_pose.perception.detect import load_detector
        from envisat_pose.perception.weights import shipped_weights_path

        return load_detector(weights or shipped_weights_path(), device=device, bf16=bf16)
    if bf16:
        raise InputError(f"bf16: ENVISAT's corner detector only; target {target!r}'s keypoint detector runs in "
                         "float32")
    from envisat_pose.perception.keypoint_detect import load_frame_detector

    if not weights:  # the target's own beside its file (the shipped upper stage's), else refused naming where
        from envisat_pose.perception.weights import default_target_weights

        weights = default_target_weights(target)
    return load_frame_detector(weights, target, device)


def scenario_orbit(scenario: str = "default"):
    """The chaser's Keplerian orbit (datagen's OrbitConfig) of a named scenario."""

    return scenario_config(scenario).orbit


def chaser_from_orbit(orbit=None, scenario: str = "default"):
    """chaser_at(t_s) -> (4,) the chaser's polar orbit (r_m, rdot_m_s, theta_rad, thetadot_rad_s) from its
    Keplerian elements (datagen's OrbitConfig, or a dict of its fields; None: the named scenario's orbit)."""

    if orbit is None:
        orbit = scenario_orbit(scenario)
    elif isinstance(orbit, dict):
        orbit = from_dict(OrbitConfig, orbit, prefix="orbit")
    return chaser_function(orbit)
