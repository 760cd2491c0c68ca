"""The closed loop's windowed frame (pipelines/runs/loop_frames.windowed_frame): only the tracker's window is
rendered and corrupted, pasted at its place into a black frame of the full size; the window's pixels are the full
frame's there (up to the rasterizer's edge pixels, tests/datagen/test_render_window.py; the space camera's
statistics: tests/datagen/test_sensor_window.py)."""

import dataclasses

import numpy as np
import pytest

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.datagen.render_view import View
from envisat_pose.pipelines.runs.loop_frames import windowed_frame
from envisat_pose.state import MRP, POS

RES = 256


@pytest.fixture(scope="module")
def scene():
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.datagen.render_cache import shared_renderer

    renderer = shared_renderer(RES, True)
    x = np.zeros(12)
    x[POS] = (0.5, 50.0, -1.0)
    x[MRP] = (0.1, -0.2, 0.05)
    view = View(x[POS], mrp_to_dcm(x[MRP]).T, np.array([0.6, -0.7, 0.3]), np.array([-1.0, 0.0, 0.0]), 6.9e6)
    gcfg = GenerateConfig(resolution_px=RES)
    return renderer, view, x, gcfg


def test_a_clean_window_is_the_full_frame_there_and_black_elsewhere(scene):
    from envisat_pose.datagen.corrupt import KINDS

    renderer, view, x, gcfg = scene
    clean = dataclasses.replace(gcfg, corruption=dataclasses.replace(gcfg.corruption, **{k: "none" for k in KINDS}))
    full = renderer.render(view, labels=False).gray_u8
    for window in (np.array([60, 70, 100]), np.array([-20, 200, 90])):  # inside; across two edges of the image
        image, t_render, t_camera = windowed_frame(renderer, view, window, clean, x, np.random.default_rng(0))
        x0, y0, side = window
        inside = np.zeros((RES, RES), bool)
        inside[max(y0, 0):y0 + side, max(x0, 0):x0 + side] = True
        assert image.shape == (RES, RES) and not image[~inside].any()
        differs = np.abs(image[inside].astype(int) - full[inside].astype(int)) > 0
        assert differs.mean() <= 0.03, differs.mean()
        assert t_render >= 0 and t_camera >= 0


def test_a_corrupted_window_keeps_the_frames_light(scene):
    """The space camera on the window: its mean within a few grey levels of the full frame's corrupted there (the
    same parameters, other noise draws), and black outside."""
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.datagen.factory import draw_corruption_params

    renderer, view, x, gcfg = scene
    window = np.array([40, 50, 160])
    image, _, _ = windowed_frame(renderer, view, window, gcfg, x, np.random.default_rng(5))
    rendered = renderer.render(view, labels=False)
    params = draw_corruption_params(gcfg, rendered, x, renderer.K[0, 0], renderer.target_boxes,
                                    np.random.default_rng(5))
    full = apply_corruption(rendered.gray_u8, params)
    crop = (slice(50, 210), slice(40, 200))
    assert abs(float(image[crop].mean()) - float(full[crop].mean())) < 3.0
    assert not image[:50].any() and not image[:, :40].any()
