"""The square chaser-camera image's pixel geometry: the pinhole intrinsics, metric depth from MuJoCo's depth
buffer, the pixel box of projected points, a window clipped to the image and the near-plane window cropped to a
box. Plain numpy."""

from __future__ import annotations

import math

import numpy as np


def depth_from_buffer(raw: np.ndarray, znear_m: float, zfar_m: float) -> np.ndarray:
    """Metric depth along the boresight from MuJoCo's reversed-Z depth buffer values in [0, 1].

    Same mapping as mujoco.Renderer (float32 frustum coefficients, float64 arithmetic). (H, W) -> (H, W) m.
    """
    zfar, znear = np.float32(zfar_m), np.float32(znear_m)
    c_coef = -(zfar + znear) / (zfar - znear)
    d_coef = -(np.float32(2) * zfar * znear) / (zfar - znear)
    c_coef = np.float32(-0.5) * c_coef - np.float32(0.5)
    d_coef = np.float32(-0.5) * d_coef
    return d_coef / (raw.astype(np.float64) + c_coef)


def projected_bbox_px(points_K_m: np.ndarray, K: np.ndarray, resolution_px: int, znear_m: float,
                      pad_px: int = 3) -> tuple[int, int, int, int] | None:
    """Pixel box (u0, v0, u1, v1), inclusive, that holds the projections of points_K_m (N, 3), clipped to the
    image; the whole image when a point is behind the near plane; None when the box misses the image."""
    n = resolution_px
    if np.any(points_K_m[:, 2] <= znear_m):
        return 0, 0, n - 1, n - 1
    uv = (points_K_m @ K.T)[:, :2] / points_K_m[:, 2:3]
    u0, v0 = np.floor(uv.min(axis=0)).astype(int) - pad_px
    u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + pad_px
    if u1 < 0 or v1 < 0 or u0 > n - 1 or v0 > n - 1:
        return None
    return max(u0, 0), max(v0, 0), min(u1, n - 1), min(v1, n - 1)


def crop_frustum(box: tuple[int, int, int, int], resolution_px: int, bottom: float, top: float
                 ) -> tuple[float, float, float, float]:
    """Near-plane window (center, half-width, bottom, top) of the pixel box (u0, v0, u1, v1) of a square
    image whose full window spans [bottom, top] vertically and horizontally (MuJoCo's mjvGLCamera frustum)."""
    u0, v0, u1, v1 = box
    s = (top - bottom) / resolution_px  # near-plane size of one pixel
    left, right = bottom + u0 * s, bottom + (u1 + 1) * s
    return 0.5 * (left + right), 0.5 * (right - left), top - (v1 + 1) * s, top - v0 * s


def intrinsics(resolution_px: int, fovy_deg: float) -> np.ndarray:
    """Pinhole K (3, 3) of a square image, OpenCV convention (pixel centres at integer coordinates).

    f = (H / 2) / tan(fovy / 2) px; principal point ((W - 1) / 2, (H - 1) / 2), e.g. 511.5 at 1024 px.
    """
    f = 0.5 * resolution_px / math.tan(math.radians(fovy_deg) / 2.0)
    c = 0.5 * (resolution_px - 1)
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


def window_box_px(window_px: tuple[int, int, int], resolution_px: int) -> tuple[int, int, int, int] | None:
    """The pixel box (u0, v0, u1, v1), inclusive, of the square window (x0, y0, side) px clipped to the square
    image of resolution_px; None when the window misses the image. ValueError (one line) for side < 1."""
    x0, y0, side = (int(v) for v in window_px)
    if side < 1:
        raise ValueError(f"window (x0, y0, side) = {tuple(window_px)} px: side must be at least 1 px")
    u0, v0 = max(x0, 0), max(y0, 0)
    u1, v1 = min(x0 + side, resolution_px) - 1, min(y0 + side, resolution_px) - 1
    if u1 < u0 or v1 < v0:
        return None
    return u0, v0, u1, v1
