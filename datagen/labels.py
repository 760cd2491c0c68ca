"""Labels of a rendered view: projected corners, visibility (the Target's ray casts), pose, depth encoding.

Camera frame K: x right, y down, z along the boresight (OpenCV). Pixels: OpenCV convention, pixel centres at
integer coordinates, (u, v) = (column, row). Target frame T as in geometry.py.
"""

from __future__ import annotations

import numpy as np

DEPTH_MAX_CODE = 65535


def project_px(points_K_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection (u, v) = (f x / z + c_u, f y / z + c_v). (..., 3) m -> (..., 2) px."""
    p = np.asarray(points_K_m, dtype=float)
    return p[..., :2] / p[..., 2:3] * np.diag(K)[:2] + K[:2, 2]


def in_frame(corners_px: np.ndarray, z_m: np.ndarray, resolution_px: int) -> np.ndarray:
    """Corners in front of the camera whose projection falls on the image area [-0.5, N - 0.5)^2. (8,) bool."""
    lo, hi = -0.5, resolution_px - 0.5
    inside = np.all((corners_px >= lo) & (corners_px < hi), axis=-1)
    return inside & (z_m > 0)


def encode_depth(depth_m: np.ndarray, depth_scale_m: float) -> np.ndarray:
    """16-bit depth: round(depth / scale), 0 stays background, clipped to [1, 65535] on the target. (H, W)."""
    code = np.zeros(depth_m.shape, dtype=np.uint16)
    fg = depth_m > 0  # only the target's pixels carry depth (a few percent of the image)
    code[fg] = np.clip(np.rint(depth_m[fg].astype(np.float64) / depth_scale_m), 1, DEPTH_MAX_CODE)
    return code


def label_names_keypoints(label: dict) -> bool:
    """Whether a label names its keypoints (keypoint_names, keypoints_px): written for a Target whose
    labels_name_keypoints; else the shard contract's corners_px with A-H implied (ENVISAT's, make_label)."""
    return "keypoint_names" in label


def label_points_noun(label: dict) -> str:
    """What text calls a label's points: "keypoints" where it names them (label_names_keypoints), "corners"."""
    return "keypoints" if label_names_keypoints(label) else "corners"


def _round_list(a: np.ndarray, ndigits: int) -> list:
    """A JSON-ready nested list with values rounded (stable text, no float noise in the last digit)."""
    return np.round(np.asarray(a, dtype=float), ndigits).tolist()


def make_label(corners_K_m: np.ndarray, unoccluded: np.ndarray, K: np.ndarray, R_K_from_T: np.ndarray,
               t_K_from_T_m: np.ndarray, x: np.ndarray, depth_scale_m: float, corruption: dict, seed: int,
               scene: dict, keypoint_names: tuple[str, ...] | None = None) -> dict:
    """The shard contract's label of one image (design.md) as plain JSON data.

    corners_px (8, 2) OpenCV convention; visible (8,): unoccluded (K,) (the Target's exact ray casts,
    Target.visible) and in the image; in_frame (8,); x (12,) the paper's state; another target (keypoint_names
    given, K of them): keypoint_names (K,) and keypoints_px (K, 2) in place of corners_px, visible and in_frame (K,);
    K (3, 3); R_cam_from_target (3, 3), t_cam_from_target_m (3,) in K (the label's names for R_K_from_T and
    t_K_from_T_m, the arguments); depth_scale_m; corruption; seed.
    `scene` (extra) records the sun, eclipse and Earth backdrop of the view.
    """
    n = int(round(2 * K[0, 2] + 1))  # the square image's size: principal point at (n - 1) / 2
    corners_px = project_px(corners_K_m, K)
    z_m = corners_K_m[:, 2]
    frame = in_frame(corners_px, z_m, n)
    visible = np.asarray(unoccluded, bool) & frame
    points = {"corners_px": _round_list(corners_px, 4)} if keypoint_names is None else \
        {"keypoint_names": list(keypoint_names), "keypoints_px": _round_list(corners_px, 4)}
    return {
        **points,
        "visible": visible.tolist(),
        "in_frame": frame.tolist(),
        "x": _round_list(x, 12),
        "K": _round_list(K, 9),
        "R_cam_from_target": _round_list(R_K_from_T, 12),
        "t_cam_from_target_m": _round_list(t_K_from_T_m, 9),
        "depth_scale_m": float(depth_scale_m),
        "corruption": corruption,
        "seed": int(seed),
        "scene": scene,
    }
