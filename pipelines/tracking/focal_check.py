"""Whether a window's frames agree with the camera's focal length, read from the frames themselves.

The images of a known 3D shape fix the focal length as well as the pose: under perspective the target's near and far
keypoints scale differently, which a pose alone cannot mimic once six or more keypoints off one plane are seen. A
camera file whose focal length is off by a factor s makes every pose's range off by about s (the scale ambiguity
a frame's pose does not resolve by itself), so a track built on it is wrong with nothing else in the images to say
so: the NIS stays near its usual level (docs/history.md, 2026-12-06, eighth session: 25 % long was claimed 120 s).

`focal_reading` profiles the window's whitened reprojection chi-square over the focal scale s (each frame's pose
found again by OpenCV's PnP at each s, the window's keypoints and covariances as the cold start's fit kept them) and
reads s_hat at its minimum and the likelihood ratio chi2(1) - chi2(s_hat), about chi-square with one degree of
freedom where the camera is right and the covariances hold (about: the poses are PnP's unweighted least squares,
not the whitened ones; measured with the right camera, at most 18.3 over 84 windows: docs/design.md). `focal_problems` turns a reading into the cold start's
refusal: s_hat off by more than IntegrityConfig.focal_tolerance with the ratio beyond its 1-dof bound at the
integrity tests' false-alarm probability (IntegrityConfig.prob).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.gates import chi2_bound

MIN_POINTS = 6  # keypoints a frame needs to speak of the focal length (the DLT's six: pose and focal length apart)
MIN_FRAMES = 3  # frames with MIN_POINTS a reading needs
SCALE_BOUNDS = (0.5, 2.0)  # the focal scales searched (a reading at a bound means "at least that far off")
_GRID = 9  # the coarse grid over log s before the golden-section search
_TOL_LOG = 1e-3  # the search's tolerance in log s (0.1 %)


@dataclass(frozen=True)
class FocalReading:
    """scale: the focal length the frames read over the camera's (s_hat); lr: chi2(1) - chi2(s_hat), the whitened
    likelihood ratio of the camera's focal length against the frames' own; frames: the frames read."""

    scale: float
    lr: float
    frames: int


def _frame_chi2(obj_m: np.ndarray, img_px: np.ndarray, info: np.ndarray, K: np.ndarray) -> float:
    """The whitened chi-square of one frame's keypoints (obj_m (n, 3) in T, img_px (n, 2), info (n, 2, 2) the
    inverse covariances) about the PnP pose (SQPnP, then Levenberg-Marquardt) through intrinsics K; inf where PnP
    fails or puts the target behind the camera."""
    import cv2

    try:
        good, rvec, tvec = cv2.solvePnP(obj_m, img_px, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not good:
            return float("inf")
        rvec, tvec = cv2.solvePnPRefineLM(obj_m, img_px, K, None, rvec, tvec)
    except cv2.error:
        return float("inf")
    if not (np.isfinite(tvec).all() and tvec[2, 0] > 0):
        return float("inf")
    r = img_px - cv2.projectPoints(obj_m, rvec, tvec, K, None)[0][:, 0]
    return float(np.einsum("ki,kij,kj->", r, info, r))


def focal_reading(z_px: np.ndarray, cov_px: np.ndarray, used: np.ndarray, keypoints_T_m: np.ndarray,
                  f_px: float, cu_px: float, cv_px: float) -> FocalReading | None:
    """The focal scale the window reads (module doc). z_px (N, K, 2) the frames' named keypoints (NaN where
    missing), cov_px (N, K, 2, 2) their covariances, used (N, K) bool the keypoints to read (the fit's kept ones),
    keypoints_T_m (K, 3) in T; the camera's pinhole f_px, (cu_px, cv_px). None where fewer than MIN_FRAMES frames
    hold MIN_POINTS usable keypoints."""
    z_px, cov_px = np.asarray(z_px, float), np.asarray(cov_px, float)
    ok = np.asarray(used, bool) & np.isfinite(z_px).all(-1) & np.isfinite(cov_px).all((-1, -2))
    frames = []
    for n in np.flatnonzero(ok.sum(axis=1) >= MIN_POINTS):
        m = ok[n]
        try:
            info = np.linalg.inv(cov_px[n, m])
        except np.linalg.LinAlgError:
            continue
        frames.append((np.ascontiguousarray(keypoints_T_m[m], dtype=np.float64),
                       np.ascontiguousarray(z_px[n, m], dtype=np.float64), info))
    if len(frames) < MIN_FRAMES:
        return None

    def chi2(log_s: float) -> float:
        f = f_px * float(np.exp(log_s))
        K = np.array([[f, 0.0, cu_px], [0.0, f, cv_px], [0.0, 0.0, 1.0]])
        return sum(_frame_chi2(obj, img, info, K) for obj, img, info in frames)

    log_s, c_min = _minimize(chi2, *np.log(SCALE_BOUNDS))
    c_one = chi2(0.0)
    lr = c_one - c_min if np.isfinite(c_one) else float("inf")
    return FocalReading(float(np.exp(log_s)), float(max(lr, 0.0)), len(frames))


def _minimize(fun, lo: float, hi: float) -> tuple[float, float]:
    """(argmin, min) of a one-dimensional fun over [lo, hi]: the best of a coarse grid, then a golden-section search
    between its neighbours to _TOL_LOG."""
    grid = np.linspace(lo, hi, _GRID)
    values = np.array([fun(u) for u in grid])
    i = int(np.argmin(values))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, _GRID - 1)]
    best_u, best_v = float(grid[i]), float(values[i])
    g = (np.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = fun(c), fun(d)
    while b - a > _TOL_LOG:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = fun(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = fun(d)
    for u, v in ((c, fc), (d, fd)):
        if v < best_v:
            best_u, best_v = float(u), float(v)
    return best_u, best_v


def focal_problems(reading: FocalReading | None, cfg) -> list[str]:
    """Why a window's frames refuse the camera's focal length (empty where they do not, or cannot say: no
    reading): the scale they read is off by more than cfg.focal_tolerance (IntegrityConfig) and the likelihood
    ratio is beyond its 1-dof chi-square bound at cfg.prob."""
    if reading is None:
        return []
    bound = chi2_bound(cfg.prob, 1)
    if abs(reading.scale - 1.0) <= cfg.focal_tolerance or reading.lr <= bound:
        return []
    lo, hi = SCALE_BOUNDS
    at = "at least " if reading.scale >= hi * (1.0 - 1e-6) else "at most " if reading.scale <= lo * (1.0 + 1e-6) else ""
    return [f"the frames read a focal length {at}{reading.scale:.2f} x the camera's (likelihood ratio "
            f"{reading.lr:.0f} > {bound:.0f} over {reading.frames} frames; the range would be as far off): check the "
            "camera's focal length (fx, fy) against the frames'"]
