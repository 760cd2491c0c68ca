"""The closed loop's windowed frame (pipelines/runs/loop_frames.windowed_frame): only the tracker's window is
rendered and corrupted, pasted at its place into a black frame of the full size; the window's pixels are the full
frame's there (up to the rasterizer's edge pixels, tests/datagen/test_render_window.py; the space camera's
statistics: tests/datagen/test_sensor_window.py)."""

import dataclasses
import time
from types import SimpleNamespace

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


class SlowWindowRenderer:
    """A stand-in renderer (64 px) whose render_window takes RENDER_S of wall time."""

    resolution_px, K, target_boxes = 64, np.eye(3), None

    def view_pose(self, view):
        return None

    def render_window(self, view, window):
        time.sleep(RENDER_S)
        return SimpleNamespace(gray_u8=np.zeros((window[2], window[2]), np.uint8))


RENDER_S, CAMERA_S = 0.2, 0.05  # s of wall time the stand-ins take


def test_a_windows_stage_times_are_the_renders_and_the_cameras(monkeypatch):
    """windowed_frame's (s rendering, s camera): the rendering is the renderer's time, the camera the space
    camera's (drawing its parameters and corrupting), each measured around stand-ins that sleep a known time;
    summary.json's ms per frame by stage adds these up. Bounds: each at least what it slept (sleeps overrun,
    never undershoot; no upper bound, which a loaded machine could break)."""
    from envisat_pose.datagen import corrupt
    from envisat_pose.pipelines.runs import loop_frames

    def slow_corruption(clean, window, n, params):
        time.sleep(CAMERA_S)
        return np.full((window[2], window[2]), 7, np.uint8)

    monkeypatch.setattr(loop_frames, "draw_corruption_params", lambda *a: {})
    monkeypatch.setattr(corrupt, "corruption_margin_px", lambda params: 3)
    monkeypatch.setattr(corrupt, "apply_corruption_window", slow_corruption)
    image, t_render, t_camera = windowed_frame(SlowWindowRenderer(), None, np.array([10, 12, 20]), None,
                                               np.zeros(12), np.random.default_rng(0))
    assert (image[12:32, 10:30] == 7).all() and image.sum() == 7 * 400
    assert t_render >= RENDER_S and t_camera >= CAMERA_S  # swapped, the rendering would read the camera's 0.05 s


def test_the_frame_maker_reports_a_windows_times_and_counts_it(monkeypatch):
    """FrameMaker.image of a window: the camera's seconds as windowed_frame measured them, the rest of the
    frame's wall time (the view's set-up included) as rendering; the frame counted as windowed."""
    from envisat_pose.pipelines.runs import loop_frames

    def timed_window(renderer, view, window, gcfg, x, rng):
        time.sleep(RENDER_S + CAMERA_S)
        return np.zeros((64, 64), np.uint8), RENDER_S, CAMERA_S

    monkeypatch.setattr(loop_frames, "windowed_frame", timed_window)
    monkeypatch.setattr(loop_frames, "with_appearance", lambda g, view, d, seed: (view, d))
    maker = loop_frames.FrameMaker(SlowWindowRenderer(), SimpleNamespace(earth_probability=0.0), 1, 0, 0,
                                   np.array([[0.0, -1.0, 0.0]]), np.array([[-7e6, 0.0, 0.0]]))
    x = np.zeros(12)
    x[POS] = (0.0, 50.0, 0.0)
    _, t_render, t_camera = maker.image(0, x, np.array([10, 12, 20]))
    assert t_camera == CAMERA_S and t_render >= RENDER_S
    assert maker.counts == {"frames_windowed": 1, "frames_window_remade": 0}


def window_edges(x0: int, y0: int, side: int) -> list:
    """The four edges (first and last row, first and last column) of the window (x0, y0, side) as indices."""
    rows, cols = slice(y0, y0 + side), slice(x0, x0 + side)
    return [(y0, cols), (y0 + side - 1, cols), (rows, x0), (rows, x0 + side - 1)]


def test_every_edge_row_and_column_of_a_window_is_made(scene):
    """A clean 24-px window whose four edges all cross the lit target (the first found along its lit pixels):
    on each edge the pixels the full frame shows lit are lit in the window too (a window pasted one row or column
    short leaves its last ones black, under 1 % of a 100-px window's pixels: the share test above lets it by).
    At most 20 % of an edge's lit pixels may go black (the rasterizer's edge samples: 2 % of a window's pixels)."""
    from envisat_pose.datagen.corrupt import KINDS

    renderer, view, x, gcfg = scene
    clean = dataclasses.replace(gcfg, corruption=dataclasses.replace(gcfg.corruption, **{k: "none" for k in KINDS}))
    full = renderer.render(view, labels=False).gray_u8
    side = 24
    ys, xs = np.nonzero(full[side:-side, side:-side])  # lit pixels a window's side away from the image's edges
    x0, y0 = next((u, v) for u, v in zip(xs[::7] + side // 2, ys[::7] + side // 2)
                  if all((full[e] > 0).sum() >= 5 for e in window_edges(u, v, side)))
    image, _, _ = windowed_frame(renderer, view, np.array([x0, y0, side]), clean, x, np.random.default_rng(0))
    for edge in window_edges(x0, y0, side):
        lit = full[edge] > 0
        assert (image[edge][lit] == 0).mean() <= 0.2, edge
