"""The image pieces both camera models share: the 'paper' corruptions (datagen/corrupt.py) and the space camera
(datagen/sensor.py). Fast standard-normal noise, the motion-blur streak kernel, and the box of an image's content
that a filter needs to touch.
"""

from __future__ import annotations

import cv2
import numpy as np


def _normal_table() -> np.ndarray:
    """Standard-normal quantiles at the 65536 mid-probabilities (i + 0.5) / 65536, float32 (tails to 4.3 sigma)."""
    from scipy.special import ndtri

    return ndtri((np.arange(65536) + 0.5) / 65536).astype(np.float32)


_NORMAL_TABLE = _normal_table()


def standard_normal_fast(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Standard-normal float32 noise by inverse-CDF lookup of uniform 16-bit draws: ~3x faster than
    Generator.standard_normal, quantised to 65536 levels (ample for 8-bit images). (shape) float32."""
    return _NORMAL_TABLE[rng.integers(0, 65536, size=shape, dtype=np.uint16)]


def motion_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """Normalised line kernel of a linear streak `length_px` long at `angle_deg` (image x toward y). (k, k)."""
    half = int(np.ceil(length_px / 2.0))
    k = 2 * half + 1
    n = max(2, int(np.ceil(length_px)) * 4)
    t = np.linspace(-length_px / 2.0, length_px / 2.0, n)
    a = np.radians(angle_deg)
    kernel = np.zeros((k, k), dtype=np.float64)
    # bilinear splat of points along the streak: sub-pixel lengths stay exact
    xs, ys = half + t * np.cos(a), half + t * np.sin(a)
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (np.clip(y0 + dy, 0, k - 1), np.clip(x0 + dx, 0, k - 1)), wgt)
    return (kernel / kernel.sum()).astype(np.float32)


def content_box(gray_u8: np.ndarray, reach_px: int) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1) of the non-zero pixels grown by 2 x reach_px (clipped to the image), None if all black.

    Twice the reach: within the grown box, a filter that reflects at the box's edge reflects only zeros there.
    """
    x, y, w, h = cv2.boundingRect(gray_u8)
    if w == 0 or h == 0:
        return None
    g = 2 * reach_px
    H, W = gray_u8.shape
    return max(0, y - g), min(H, y + h + g), max(0, x - g), min(W, x + w + g)
