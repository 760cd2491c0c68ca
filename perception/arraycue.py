"""The solar array's end: which end of the body the image shows the array at, for the box's y and z half-turns.

The box's corners cannot tell a pose from its half-turns: about x (the long axis) the array maps onto itself, but
about y or z it goes to the other end of the body. A pose and such a twin put the same eight corners in the same
pixels and the array 14 m apart. So the image says which of them it shows wherever the array's region is in the
frame and stands out from what lies behind it (space, the Earth).

For a pose (R, t) the array's outline (geometry.load_array_outline, from the MJCF) is projected at its own end and
mirrored to the other (x -> -x in T, where a y or z twin puts it). In each region, outside the body's silhouette and
outside the other region, the share of pixels brighter than the sky (the darkest quarter of the frame outside the
target's regions: its median plus `margin` noise spreads, a MAD, at least `min_margin` grey levels) is measured;
a frame whose background is itself lit (the Earth behind the target) is not read at all. The cue says
+1 (the array is where the pose puts it) when that share is at least `occupied` at the pose's end and at most
`empty` at the other, -1 the other way round, and abstains (0) otherwise: a region too small or out of the frame,
an array edge-on, in shadow or lost in the Earth behind it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from envisat_pose.geometry import load_array_outline


@dataclass(frozen=True)
class ArrayReadingConfig:
    """min_area_px: the least area of each region (px, after the exclusions) for the cue to speak; occupied,
    empty: the shares of a region's pixels above the background that say "the array is here" / "nothing is
    here"; margin: the background's noise spreads (MAD x 1.4826) a pixel must exceed; min_margin: at least
    this many grey levels; body_dilate_px: the body's silhouette grown by this before it is excluded (its
    blurred rim); background_lit: the cue abstains when more than this share of the frame outside the target's
    regions is above the sky's level (the Earth behind the target: the dark back of an array before it reads as
    sky, the Earth's light as an array); scale: the image is measured at this fraction of its size (speed; 1 the full frame)."""

    min_area_px: float = 400.0
    occupied: float = 0.5
    empty: float = 0.05
    margin: float = 4.0
    min_margin: float = 2.0
    body_dilate_px: int = 3
    background_lit: float = 0.01
    scale: float = 0.5


def _project(points_T_m: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """(N, 2) px of points in T under the pose (R_cam_from_target, t_cam_from_target_m); None when one is not in
    front of the camera."""
    p = points_T_m @ R.T + t
    if np.any(p[:, 2] <= 1e-3):
        return None
    uv = p @ K.T
    return uv[:, :2] / uv[:, 2:3]


def _median_of_counts(values: np.ndarray, counts: np.ndarray) -> float:
    """np.median of the sample holding counts[i] copies of values[i] (values ascending): the middle value, or the
    mean of the two middle ones."""
    cum = np.cumsum(counts)
    n = int(cum[-1])
    lo, hi = (n - 1) // 2, n // 2
    a, b = values[np.searchsorted(cum, lo, side="right")], values[np.searchsorted(cum, hi, side="right")]
    return 0.5 * (float(a) + float(b))


def sky_level(hist: np.ndarray) -> tuple[float, float]:
    """The sky's level and spread from the background's grey-level histogram (256,) of a uint8 sample bg: the
    median of its darkest quarter dark = bg[bg <= np.percentile(bg, 25)] and the median absolute deviation of
    dark about it, as numpy computes them on bg (exact: grey levels are integers, and np.percentile's
    interpolation at (n - 1) / 4 never passes the next level, so dark is bg <= its level at that rank)."""
    cum = np.cumsum(hist)
    q = int(np.searchsorted(cum, (int(cum[-1]) - 1) // 4, side="right"))  # the grey level at rank floor((n-1)/4)
    levels = np.arange(q + 1, dtype=float)
    floor = _median_of_counts(levels, hist[: q + 1])
    dev = np.abs(levels - floor)
    order = np.argsort(dev, kind="stable")
    return floor, _median_of_counts(dev[order], hist[: q + 1][order])


def array_end(image: np.ndarray, K: np.ndarray, R_cam_from_target: np.ndarray, t_cam_from_target_m: np.ndarray,
              corners_T_m: np.ndarray, cfg: ArrayReadingConfig = ArrayReadingConfig()) -> tuple[int, dict]:
    """(+1, 0 or -1, details): whether the image (H, W) shows the array at the end where the pose puts it (+1), at
    the other end (-1), or cannot tell (0). corners_T_m (8, 3): the body's corners A-H in T. details: the two
    regions' areas (px of the measured image) and occupied shares, the threshold (grey levels)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"expected a grayscale frame (H, W), got shape {img.shape}")
    s = float(cfg.scale)
    small = img if s == 1.0 else cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    h, w = small.shape
    Ks = np.diag([s, s, 1.0]) @ np.asarray(K, float)
    outline = load_array_outline()
    mirrored = outline * np.array([-1.0, 1.0, 1.0])
    R, t = np.asarray(R_cam_from_target, float), np.asarray(t_cam_from_target_m, float)
    masks = []
    for pts in (outline, mirrored):
        uv = _project(pts, R, t, Ks)
        m = np.zeros((h, w), np.uint8)
        if uv is not None and np.all(np.abs(uv) < 1e6):
            cv2.fillPoly(m, [np.round(uv * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
        masks.append(m.astype(bool))
    body_uv = _project(np.asarray(corners_T_m, float), R, t, Ks)
    body = np.zeros((h, w), np.uint8)
    if body_uv is not None and np.all(np.abs(body_uv) < 1e6):
        hull = cv2.convexHull(np.round(body_uv * 16).astype(np.int32))
        cv2.fillConvexPoly(body, hull, 1, lineType=cv2.LINE_8, shift=4)
        if cfg.body_dilate_px > 0:
            k = 2 * int(cfg.body_dilate_px) + 1
            body = cv2.dilate(body, np.ones((k, k), np.uint8))
    body = body.astype(bool)
    own = masks[0] & ~masks[1] & ~body
    other = masks[1] & ~masks[0] & ~body
    rest = ~(masks[0] | masks[1] | body)
    details = {"own_area_px": int(own.sum()), "other_area_px": int(other.sum())}
    if details["own_area_px"] < cfg.min_area_px or details["other_area_px"] < cfg.min_area_px or rest.sum() < 100:
        return 0, details
    hist = np.bincount(small[rest], minlength=256)
    floor, mad = sky_level(hist)
    thr = floor + max(cfg.margin * 1.4826 * mad, cfg.min_margin)
    share_rest = float(hist[int(np.floor(thr)) + 1:].sum() / hist.sum())
    share_own = float(np.mean(small[own] > thr))
    share_other = float(np.mean(small[other] > thr))
    details.update(own_share=share_own, other_share=share_other, background_share=share_rest, threshold=thr)
    if share_rest > cfg.background_lit:  # the Earth (or anything lit) behind the target: a region's light could be it
        return 0, details
    if share_own >= cfg.occupied and share_other <= cfg.empty:
        return 1, details
    if share_other >= cfg.occupied and share_own <= cfg.empty:
        return -1, details
    return 0, details
