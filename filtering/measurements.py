"""Measurement models of a target's K keypoints ("corners"), visibility prediction and the selection of measured ones.

The keypoints are the target's (envisat_pose.target.Target.keypoints_T_m, (K, 3) in T); without one, ENVISAT's
corners A-H of models/envisat.xml via envisat_pose.geometry (K = 8), the filter's default.
Three kinds (per keypoint i, v_i its position in T):
- "markers3d": z_i = rho + Gamma^T v_i, the corner relative to the chaser in C, m (3 per corner);
- "pixels": (u, v) of the corner in the chaser camera, px (2 per corner);
- "pixels+range": (u, v, range_m), range the distance from the camera to the corner, m (3 per corner).

The camera is the one of models/envisat.xml (`envisat_pose.geometry.load_camera()`, a PinholeCamera): fixed on
the chaser at pos_C_m, a point in C is v_K = R_K_from_C (v_C - pos_C_m) in the camera frame K (x right, y down,
z boresight), and the guarded pinhole `envisat_pose.geometry.project_K` maps it to pixels,
u = f x_K / z_K + c_u, v = f y_K / z_K + c_v (pixel centres at integer coordinates); a point behind the camera is
never mirrored into the image. The range of pixels+range is measured from the camera centre.

Measurements travel as per-keypoint arrays: z (..., K, m), mask (..., K) bool (which keypoints were measured), and
per-keypoint covariances (..., K, m, m). A filter flattens them to (..., K m).
"""

from __future__ import annotations

import math

import numpy as np

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.geometry import PinholeCamera, load_camera, load_geometry, project_K, visible_corners
from envisat_pose.state import MRP, POS

KINDS = ("markers3d", "pixels", "pixels+range")
# corners that fix a pose by themselves: three 3D points not on a line; four pixels (three leave P3P's up to four
# poses); a pixel with its range fixes its point in 3D, as a marker
POSE_CORNERS = {"markers3d": 3, "pixels": 4, "pixels+range": 3}
MIN_DEPTH_M = 1e-3  # project_K's guard: a corner closer than this along the boresight (or behind) stays outside


def dim_per_corner(kind: str) -> int:
    """Number of measured components per corner: 3, 2 or 3."""
    return {"markers3d": 3, "pixels": 2, "pixels+range": 3}[kind]


def corners_C_m(x: np.ndarray, corners_T_m: np.ndarray | None = None) -> np.ndarray:
    """Keypoint positions relative to the chaser in C: rho + Gamma^T v_i, m. (..., 12) -> (..., K, 3).

    corners_T_m: (K, 3) the keypoints in T, m (default: ENVISAT's corners A-H, K = 8)."""
    v_T = load_geometry().corners_T_m if corners_T_m is None else corners_T_m
    G = mrp_to_dcm(x[..., MRP])
    # (Gamma^T v)_j = sum_i G_ij v_i
    return x[..., None, POS] + v_T @ G


def chaser_T_m_from_state(x: np.ndarray) -> np.ndarray:
    """The chaser's position in T, c_T = -Gamma rho, m. (..., 12) -> (..., 3)."""
    return -np.einsum("...ij,...j->...i", mrp_to_dcm(x[..., MRP]), x[..., POS])


def predicted_visible(x: np.ndarray, table=None) -> np.ndarray:
    """Which keypoints the state says the chaser sees, from c_T = -Gamma rho (chaser_T_m_from_state).

    table: None for ENVISAT's box (the exact face test of geometry.visible_corners, K = 8), or a target's fast
    visibility table (envisat_pose.target.VisibilityTable: its `lookup`). (..., 12) -> (..., K) bool."""
    c_T = chaser_T_m_from_state(x)
    return visible_corners(c_T) if table is None else table.lookup(c_T)


def to_camera_K(points_C_m: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """Points in C (..., 3) m -> the camera frame K (..., 3) m: R_K_from_C (v_C - pos_C_m)."""
    return (points_C_m - camera.pos_C_m) @ camera.R_K_from_C.T


def project(points_C_m: np.ndarray, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Guarded pinhole projection of points in C. (..., 3) m -> pixels (..., 2) px and depth z_K (...,) m.

    A point behind the camera lands far outside the image on its own side (project_K), never mirrored.
    """
    p_K = to_camera_K(points_C_m, camera)
    return project_K(p_K, camera, MIN_DEPTH_M), p_K[..., 2]


def measure(x: np.ndarray, kind: str, camera: PinholeCamera | None = None,
            corners_T_m: np.ndarray | None = None) -> np.ndarray:
    """Noise-free measurement of all K keypoints from the state. (..., 12) -> (..., K, m), m = dim_per_corner(kind).

    camera: the chaser camera (default: load_camera(), the MJCF's chaser_cam); unused for markers3d.
    corners_T_m: (K, 3) the keypoints in T, m (default: ENVISAT's corners A-H).
    """
    pts = corners_C_m(x, corners_T_m)
    if kind == "markers3d":
        return pts
    camera = camera or load_camera()
    uv, _ = project(pts, camera)
    if kind == "pixels":
        return uv
    if kind == "pixels+range":
        return np.concatenate([uv, np.linalg.norm(pts - camera.pos_C_m, axis=-1, keepdims=True)], axis=-1)
    raise ValueError(f"unknown measurement kind {kind!r}; expected one of {KINDS}")


def corners_in_frame(x: np.ndarray, camera: PinholeCamera | None = None,
                     corners_T_m: np.ndarray | None = None) -> np.ndarray:
    """Which keypoints project inside the image and in front of the camera. (..., 12) -> (..., K) bool.

    corners_T_m: (K, 3) the keypoints in T, m (default: ENVISAT's corners A-H)."""
    camera = camera or load_camera()
    uv, z_K = project(corners_C_m(x, corners_T_m), camera)
    return (z_K > 0) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= camera.width_px - 0.5) \
        & (uv[..., 1] >= -0.5) & (uv[..., 1] <= camera.height_px - 0.5)


def corner_cov(kind: str, sigma_m: float, sigma_px: float, sigma_range_m: float) -> np.ndarray:
    """Per-corner noise covariance (m, m) of a kind: sigma_m^2 I (m^2), sigma_px^2 I (px^2), range sigma_range_m."""
    if kind == "markers3d":
        return sigma_m**2 * np.eye(3)
    if kind == "pixels":
        return sigma_px**2 * np.eye(2)
    return np.diag([sigma_px**2, sigma_px**2, sigma_range_m**2])


def limit_markers(mask: np.ndarray, max_markers: int | None) -> np.ndarray:
    """Keep at most `max_markers` measured keypoints per step: the first ones in the target's keypoint order (A..H
    for ENVISAT); None keeps all.

    The rule is deterministic and label-based, like a tracker that locks on named markers (the paper's
    3-marker case): any three distinct box corners are never collinear, so the pose stays observable.
    mask: (..., K) bool -> (..., K) bool.
    """
    if max_markers is None or max_markers >= mask.shape[-1]:
        return mask
    return mask & (np.cumsum(mask, axis=-1) <= max_markers)


def random_failures(mask: np.ndarray, failure_prob: float, rng: np.random.Generator) -> np.ndarray:
    """Drop each measured keypoint independently with probability failure_prob. (..., K) bool."""
    if failure_prob <= 0.0:
        return mask
    return mask & (rng.random(mask.shape) >= failure_prob)


def measured_probability(mask: np.ndarray, failure_prob: float, max_markers: int | None) -> np.ndarray:
    """The probability that each keypoint of `mask` is measured after `random_failures` then `limit_markers`:
    keypoint j survives with 1 - failure_prob and is kept when fewer than max_markers of the m_j measurable
    keypoints before it survived (a binomial tail). failure_prob 0 gives limit_markers(mask) as 0/1.
    mask: (..., K) bool -> (..., K) float, the weights of the PCRLB's expected measurement information."""
    mask = np.asarray(mask, dtype=bool)
    keep = 1.0 - float(failure_prob)
    before = np.cumsum(mask, axis=-1) - mask  # m_j: measurable keypoints ahead of keypoint j
    if max_markers is None or max_markers >= mask.shape[-1]:
        return mask * keep
    m = np.arange(mask.shape[-1] + 1)
    tail = np.array([sum(math.comb(int(n), i) * keep ** i * (1.0 - keep) ** (n - i)
                         for i in range(min(n, max_markers - 1) + 1)) for n in m])  # P(< max_markers of n survive)
    return mask * keep * tail[before]


def outage_mask(t_s: np.ndarray, outages_s: tuple[tuple[float, float], ...]) -> np.ndarray:
    """True at the times inside any outage window [start, end) (an eclipse: no corner measured). (T,) bool."""
    out = np.zeros(t_s.shape, dtype=bool)
    for start, end in outages_s:
        out |= (t_s >= start) & (t_s < end)
    return out


def add_noise(z: np.ndarray, cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """z + e with e ~ N(0, cov) per keypoint. z (..., K, m), cov broadcastable to (..., K, m, m)."""
    cov = np.asarray(cov, dtype=float)
    if cov.ndim == 2:  # one covariance for all: one factor (the same numbers as factoring every copy of it)
        L = np.linalg.cholesky(cov)
    else:
        L = np.linalg.cholesky(np.broadcast_to(cov, z.shape + (z.shape[-1],)))
    e = rng.standard_normal(z.shape)
    return z + np.einsum("...ij,...j->...i", L, e)


def swap_corners(z: np.ndarray, steps: np.ndarray, i: int, j: int) -> np.ndarray:
    """A mis-association fault: corners i and j exchange their measurements at the given steps.

    z: (T, K, m) or (R, T, K, m); steps: (T,) bool. Returns a copy.
    """
    z = z.copy()
    zi = z[..., steps, i, :].copy()
    z[..., steps, i, :] = z[..., steps, j, :]
    z[..., steps, j, :] = zi
    return z


def from_detections(corners_px: np.ndarray, cov_px: np.ndarray, visible: np.ndarray,
                    confidence: np.ndarray | None = None, min_confidence: float = 0.0):
    """The detector's output (design.md, Detections) as filter input for the "pixels" kind.

    corners_px (..., K, 2) px, cov_px (..., K, 2, 2) px^2, visible (..., K) bool, confidence (..., K) in [0, 1].
    Returns z (..., K, 2), mask (..., K) bool (visible, confident enough, finite, with a finite covariance),
    R_c (..., K, 2, 2) with unit covariance where a corner is not used (never read).
    """
    z = np.asarray(corners_px, dtype=float)
    cov = np.asarray(cov_px, dtype=float)
    mask = np.asarray(visible, dtype=bool) & np.isfinite(z).all(-1) & np.isfinite(cov).all((-1, -2))
    if confidence is not None:
        mask &= np.asarray(confidence) >= min_confidence
    R_c = np.where(mask[..., None, None], cov, np.eye(2))
    return np.where(mask[..., None], z, 0.0), mask, R_c


OFF_LINE_SHARE = 1e-3  # keypoints "on one line": their second singular value within this share of their first


def pose_fixed(keypoints_T_m: np.ndarray, mask: np.ndarray, min_points: int = 3) -> np.ndarray:
    """Whether the measured keypoints fix the target's whole pose, step by step: min_points or more of them
    (POSE_CORNERS of the measurement kind: 3 markers, 4 pixels) not on one line (one or two keypoints, or any
    number on a line, leave the rotation about that line unmeasured). keypoints_T_m (K, 3) in T (a rigid body's
    keypoints span the same in any frame); mask (T, K) bool the measured ones. Returns (T,) bool: at least
    min_points measured, whose spread about their mean has a second singular value above OFF_LINE_SHARE times its
    first."""
    mask = np.asarray(mask, dtype=bool)
    w = mask[..., None].astype(float)
    n = np.maximum(w.sum(axis=-2, keepdims=True), 1.0)
    mean = (w * keypoints_T_m).sum(axis=-2, keepdims=True) / n
    s = np.linalg.svd(w * (keypoints_T_m - mean), compute_uv=False)  # (T, 3), descending
    return (mask.sum(axis=-1) >= max(int(min_points), 3)) & (s[..., 1] > OFF_LINE_SHARE * s[..., 0])
