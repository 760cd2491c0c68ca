"""Comparisons of a run's outputs with a recorded reference, within tolerances that hold across machines.

What passes through MuJoCo's renderer (llvmpipe's JIT follows the CPU's vector units), OpenCV, BLAS, numba or
torch differs between machines in the last bits, and a sensor-noise draw that reads a pixel's value can then take
another path through the random stream, redrawing the noise downstream. These helpers compare what a real change
would move, at tolerances that the measured spreads (in each docstring) leave room for.
"""

from __future__ import annotations

import cv2
import numpy as np

# Estimates and detections: |now - recorded| <= REL_OF_SCALE x the largest |recorded| of that column (the last axis:
# one state, one pixel axis). Measured between two machines (2026-12-02, the closed track of make_track_reference):
# at most 7.6e-6 of the column's scale (x_hat), 3.4e-6 (P's diagonal); a changed behaviour moves them by percents.
REL_OF_SCALE = 1e-4

# A noisy image: blurred with a Gaussian of BLUR_SIGMA_PX, within BLUR_TOL_DN everywhere, and raw values more than
# RAW_TOL_DN apart on at most RAW_SHARE of the pixels. Measured with the noise redrawn whole (another noise seed, the
# worst a machine can do; the ten 128 px images of test_targets' ENVISAT datasets): blurred at most 1.4 DN apart,
# raw > 2 DN on at most 0.9 % of the pixels. A target moved by one pixel shows tens of DN blurred.
BLUR_SIGMA_PX = 1.5
BLUR_TOL_DN = 3.0
RAW_TOL_DN = 2
RAW_SHARE = 0.02

# A noise-free render (depth, mask): values more than EXACT_TOL apart on at most EDGE_SHARE of the pixels (the
# rasterizer's choices at silhouettes).
EDGE_SHARE = 0.01


def assert_arrays_close(now: np.ndarray, recorded: np.ndarray, name: str) -> None:
    """Integers, booleans and strings equal; floats with NaN in the same places and the rest within REL_OF_SCALE
    of each column's scale."""
    assert now.dtype.kind == recorded.dtype.kind and now.shape == recorded.shape, \
        f"{name}: {now.dtype}{now.shape} against the recorded {recorded.dtype}{recorded.shape}"
    if recorded.dtype.kind != "f":
        np.testing.assert_array_equal(now, recorded, err_msg=name)
        return
    np.testing.assert_array_equal(np.isnan(now), np.isnan(recorded), err_msg=f"{name}: where NaN")
    if recorded.size == 0 or np.isnan(recorded).all():
        return
    columns = recorded.reshape(-1, recorded.shape[-1]) if recorded.ndim else recorded.reshape(1, 1)
    scale = np.nanmax(np.abs(columns), axis=0)
    diff = np.abs(np.nan_to_num(now - recorded)).reshape(columns.shape)
    worst = np.max(diff / np.maximum(scale, 1e-300), axis=0)
    assert np.all(diff <= REL_OF_SCALE * scale), \
        f"{name}: apart by up to {worst.max():.2e} of a column's scale (tolerance {REL_OF_SCALE:g})"


def assert_noisy_image_close(now: np.ndarray, recorded: np.ndarray, name: str) -> None:
    """A sensor image (uint8, noise drawn) against its recording: blurred within BLUR_TOL_DN, raw within RAW_TOL_DN
    on all but RAW_SHARE of the pixels."""
    assert now.shape == recorded.shape and now.dtype == recorded.dtype, name
    a, b = now.astype(np.float32), recorded.astype(np.float32)
    blurred = np.abs(cv2.GaussianBlur(a, (0, 0), BLUR_SIGMA_PX) - cv2.GaussianBlur(b, (0, 0), BLUR_SIGMA_PX))
    share = float(np.mean(np.abs(a - b) > RAW_TOL_DN))
    assert blurred.max() <= BLUR_TOL_DN, f"{name}: blurred images {blurred.max():.1f} DN apart (tolerance " \
                                         f"{BLUR_TOL_DN})"
    assert share <= RAW_SHARE, f"{name}: {share:.1%} of pixels more than {RAW_TOL_DN} DN apart (at most {RAW_SHARE:.0%})"


def assert_render_close(now: np.ndarray, recorded: np.ndarray, name: str, tol: int = 0) -> None:
    """A noise-free render (a depth map, a mask): values more than tol apart on at most EDGE_SHARE of the pixels."""
    assert now.shape == recorded.shape and now.dtype == recorded.dtype, name
    share = float(np.mean(np.abs(now.astype(np.int64) - recorded.astype(np.int64)) > tol))
    assert share <= EDGE_SHARE, f"{name}: {share:.2%} of pixels differ by more than {tol} (at most {EDGE_SHARE:.0%})"
