"""One factory label in the conventions of the formats the field trains on (docs/formats.md states each one):
SPEED+ (SPNv2 and its descendants), COCO keypoints, BOP, Ultralytics YOLO-pose. Pure functions of a label
(datagen/labels.py: camera frame K = OpenCV's, x right, y down, z along the boresight; pixel centres at integer
coordinates) and of the image's mask; nothing here reads or writes a file.
"""

from __future__ import annotations

import math

import numpy as np

from envisat_pose.attitude import rotmat_to_quat

FORMATS = ("speedplus", "coco", "bop", "yolo-pose")
VISIBLE, HIDDEN, OUTSIDE = 2, 1, 0  # COCO's (and YOLO-pose's) visibility codes
JPEG_QUALITY = 95
OKS_SIGMA = 0.025  # per-keypoint OKS sigma written for YOLO-pose and suggested for COCO (docs/formats.md)
DIAMETER_CHUNK_PAIRS = 1 << 16  # distances model_diameter_mm computes at once (512 kB of float64: in cache)


def keypoints_px(label: dict) -> list:
    """(K, 2) the label's keypoints, px: `keypoints_px` (any target) or ENVISAT's `corners_px`."""
    return label["keypoints_px"] if "keypoints_px" in label else label["corners_px"]


def visibility_codes(label: dict) -> np.ndarray:
    """(K,) int: 2 visible (the label's ray-cast flag), 1 in the frame but hidden, 0 outside the frame (or
    behind the camera)."""
    in_frame = np.asarray(label["in_frame"], dtype=bool)
    visible = np.asarray(label["visible"], dtype=bool) & in_frame
    return np.where(visible, VISIBLE, np.where(in_frame, HIDDEN, OUTSIDE))


def pose_cam_from_target(label: dict) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_from_target (3, 3), t_cam_from_target_m (3,)): x_cam = R x_T + t, camera frame OpenCV's."""
    return np.asarray(label["R_cam_from_target"], dtype=float), np.asarray(label["t_cam_from_target_m"], dtype=float)


def quat_wxyz(R: np.ndarray) -> list[float]:
    """The unit quaternion of rotation matrix R, scalar first, Hamilton's product, R active (v' = R v), w >= 0."""
    return [float(c) for c in rotmat_to_quat(R)]


# --- boxes ----------------------------------------------------------------------------------------------------

def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x_min, y_min, x_max, y_max) pixel indices of the target's pixels (mask > 0), inclusive; None: none."""
    cols = np.flatnonzero(mask.any(axis=0))
    if cols.size == 0:
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1])


def outline_box(vertices_px: np.ndarray, width: int, height: int, clip: bool) -> tuple[int, int, int, int] | None:
    """The pixel indices whose centres the projected outline spans, (x_min, y_min, x_max, y_max) inclusive:
    ceil of the smallest and floor of the largest coordinate; clipped to the image when `clip` (None when
    nothing is left). vertices_px: (V, 2) projections of the points in front of the camera."""
    if len(vertices_px) == 0:
        return None
    x0, y0 = np.ceil(vertices_px.min(axis=0)).astype(int)
    x1, y1 = np.floor(vertices_px.max(axis=0)).astype(int)
    if clip:
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
    if x1 < x0 or y1 < y0:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def project_points_px(points_T_m: np.ndarray, label: dict) -> np.ndarray:
    """Pinhole projection of points of T with the label's pose and K, keeping those in front of the camera."""
    R, t = pose_cam_from_target(label)
    K = np.asarray(label["K"], dtype=float)
    p = points_T_m @ R.T + t
    p = p[p[:, 2] > 1e-6]
    return p[:, :2] / p[:, 2:3] * np.diag(K)[:2] + K[:2, 2]


# --- SPEED+ ---------------------------------------------------------------------------------------------------

def speedplus_entry(filename: str, label: dict) -> dict:
    """A SPEED+ label: q_vbs2tango_true (scalar first) with x_cam = R(q) x_body + r, r_Vo2To_vbs_true in metres."""
    R, t = pose_cam_from_target(label)
    return {"filename": filename, "q_vbs2tango_true": quat_wxyz(R), "r_Vo2To_vbs_true": [float(v) for v in t]}


def speedplus_camera(K: np.ndarray, width: int, height: int, pixel_pitch_m: float) -> dict:
    """SPEED+'s camera.json: sizes, pixel pitch and focal lengths in metres, the intrinsic matrix, no distortion,
    the horizontal field of view in degrees."""
    K = np.asarray(K, dtype=float)
    return {"Nu": int(width), "Nv": int(height), "ppx": pixel_pitch_m, "ppy": pixel_pitch_m,
            "fx": float(K[0, 0]) * pixel_pitch_m, "fy": float(K[1, 1]) * pixel_pitch_m,
            "ccx": float(K[0, 2]), "ccy": float(K[1, 2]), "cameraMatrix": K.tolist(), "distCoeffs": [0.0] * 5,
            "horizontalFOV": math.degrees(2 * math.atan(0.5 * width / float(K[0, 0])))}


# --- COCO keypoints -------------------------------------------------------------------------------------------

def coco_keypoints(label: dict) -> list[float]:
    """[x1, y1, v1, ...]: the label's pixel coordinates (centres at integers), x = y = 0 where v = 0."""
    codes = visibility_codes(label)
    out: list[float] = []
    for (u, v), code in zip(keypoints_px(label), codes):
        out += [float(u), float(v), int(code)] if code else [0.0, 0.0, 0]
    return out


def coco_bbox(box: tuple[int, int, int, int]) -> list[float]:
    """[x, y, w, h] over whole pixels (pixel i covers [i, i + 1]: COCO's box edges)."""
    x0, y0, x1, y1 = box
    return [float(x0), float(y0), float(x1 - x0 + 1), float(y1 - y0 + 1)]


def coco_skeleton(pairs) -> list[list[int]]:
    """Keypoint index pairs (E, 2), 0-based (Target.skeleton), as COCO's 1-based `skeleton`."""
    return [[int(a) + 1, int(b) + 1] for a, b in pairs]


# --- YOLO-pose ------------------------------------------------------------------------------------------------

def yolo_row(label: dict, box: tuple[int, int, int, int], width: int, height: int, class_id: int = 0) -> str:
    """One object's row: class, box centre and size, then x y v per keypoint, all normalized by the image's size
    (x = u / W, the label's pixel coordinate, as Ultralytics converts COCO) and clamped to [0, 1] (Ultralytics
    drops an image with a negative label value; a keypoint in the frame, u in [-0.5, W - 0.5), moves at most
    0.5 px); outside the frame `0 0 0`."""
    x0, y0, x1, y1 = box
    vals = [(x0 + x1 + 1) / 2 / width, (y0 + y1 + 1) / 2 / height, (x1 - x0 + 1) / width, (y1 - y0 + 1) / height]
    codes = visibility_codes(label)
    kps = []
    for (u, v), code in zip(keypoints_px(label), codes):
        kps += [_unit_text(u / width), _unit_text(v / height), str(int(code))] if code else ["0", "0", "0"]
    return " ".join([str(class_id), *(_unit_text(x) for x in vals), *kps])


def _unit_text(x: float) -> str:
    """x clamped to [0, 1], 7 decimals."""
    return f"{min(max(float(x), 0.0), 1.0):.7f}"


# --- BOP ------------------------------------------------------------------------------------------------------

def bop_gt(label: dict, obj_id: int = 1) -> dict:
    """scene_gt.json's entry: cam_R_m2c row-major, cam_t_m2c in millimetres."""
    R, t = pose_cam_from_target(label)
    return {"cam_R_m2c": [float(v) for v in R.reshape(-1)], "cam_t_m2c": [float(v) * 1000.0 for v in t],
            "obj_id": int(obj_id)}


def bop_camera(label: dict, depth_scale_mm: float | None) -> dict:
    """scene_camera.json's entry: cam_K row-major (and depth_scale, mm per depth unit, when depth ships)."""
    entry = {"cam_K": [float(v) for v in np.asarray(label["K"], dtype=float).reshape(-1)]}
    if depth_scale_mm is not None:
        entry["depth_scale"] = float(depth_scale_mm)
    return entry


def bop_box(box: tuple[int, int, int, int] | None) -> list[int]:
    """BOP's [x, y, w, h] of pixel indices (w = x_max - x_min, as the BOP toolkit's calc_2d_bbox), or -1s."""
    if box is None:
        return [-1, -1, -1, -1]
    x0, y0, x1, y1 = box
    return [x0, y0, x1 - x0, y1 - y0]


def bop_gt_info(mask: np.ndarray, outline_px: np.ndarray, truncated_px: int = 0) -> dict:
    """scene_gt_info.json's entry from the factory's mask: the target is the scene's one object, so its silhouette
    in the image is its visible one (px_count_visib = px_count_valid = the mask's pixels); px_count_all adds
    truncated_px, the silhouette's pixels beyond the image (truncated_px_count: the toolkit's calc_gt_info counts
    them), so visib_fract < 1 for a target the image cuts; bbox_obj spans the projected model, also where it leaves
    the image, bbox_visib the mask."""
    h, w = mask.shape
    n = int(np.count_nonzero(mask))
    total = n + int(truncated_px)
    return {"bbox_obj": bop_box(outline_box(outline_px, w, h, clip=False)), "bbox_visib": bop_box(mask_box(mask)),
            "px_count_all": total, "px_count_valid": n, "px_count_visib": n,
            "visib_fract": n / total if total else 0.0}


NEAR_M = 1e-3  # the near plane the silhouette's triangles are clipped at


def truncated_px_count(points_T_m: np.ndarray, faces: np.ndarray, label: dict, width: int, height: int) -> int:
    """The model's silhouette pixels outside the width x height image but on the BOP toolkit's canvas (its
    calc_gt_info renders 3 W x 3 H, the image in the middle, and counts the whole silhouette there in
    px_count_all): pixel centres (integers) that a projected triangle covers, the triangles clipped at the near
    plane z = NEAR_M. points_T_m (V, 3), faces (F, 3) vertex indices. Memory: the triangles' rows, no canvas."""
    R, t = pose_cam_from_target(label)
    K = np.asarray(label["K"], dtype=float)
    tris = (np.asarray(points_T_m, dtype=float) @ R.T + t)[np.asarray(faces, dtype=int).reshape(-1, 3)]
    front = (tris[:, :, 2] >= NEAR_M).all(axis=1)
    cut = [piece for tri in tris[~front] for piece in _clip_near(tri)]
    tris = np.concatenate([tris[front], np.reshape(cut, (-1, 3, 3))])
    uv = tris[:, :, :2] / tris[:, :, 2:3] * np.diag(K)[:2] + K[:2, 2]  # (M, 3, 2)
    rows, left, right = _row_runs(uv, width, height)
    in_rows = (rows >= 0) & (rows < height)  # the image's rows: only what lies left or right of it counts
    rows = np.concatenate([rows, rows[in_rows]])
    left = np.concatenate([left, np.maximum(left[in_rows], width)])
    right = np.concatenate([np.where(in_rows, np.minimum(right, -1), right), right[in_rows]])
    keep = left <= right
    stride = 3 * width + 2  # a row's runs as one number line, rows apart: the union in one sorted pass
    lo = (rows[keep] + height) * stride + left[keep] + width
    hi = (rows[keep] + height) * stride + right[keep] + width
    order = np.argsort(lo, kind="stable")
    lo, hi = lo[order], hi[order]
    reach = np.concatenate([[-1], np.maximum.accumulate(hi)[:-1]])  # the union so far ends there
    return int(np.maximum(hi - np.maximum(lo - 1, reach), 0).sum())


def _clip_near(tri: np.ndarray) -> list[np.ndarray]:
    """The part of the triangle (3, 3) at z >= NEAR_M as triangles (none, one, or a quadrilateral's two)."""
    poly = []
    for a, b in zip(tri, np.roll(tri, -1, axis=0)):
        if a[2] >= NEAR_M:
            poly.append(a)
        if (a[2] >= NEAR_M) != (b[2] >= NEAR_M):
            poly.append(a + (NEAR_M - a[2]) / (b[2] - a[2]) * (b - a))
    return [np.array([poly[0], poly[k], poly[k + 1]]) for k in range(1, len(poly) - 1)]


def _row_runs(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per triangle uv (M, 3, 2), px, and canvas row y: the pixel centres ceil(x_left)..floor(x_right) it covers,
    clipped to the canvas (x in [-W, 2 W), y in [-H, 2 H)). (rows, left, right), int arrays of the rows met."""
    top = np.maximum(np.ceil(uv[:, :, 1].min(axis=1)), -height).astype(int)
    bottom = np.minimum(np.floor(uv[:, :, 1].max(axis=1)), 2 * height - 1).astype(int)
    count = np.maximum(bottom - top + 1, 0)
    which = np.repeat(np.arange(len(uv)), count)
    rows = top[which] + np.arange(len(which)) - np.repeat(np.cumsum(count) - count, count)
    a = uv[which]
    b = np.roll(a, -1, axis=1)
    y = rows[:, None].astype(float)
    spans = (np.minimum(a[..., 1], b[..., 1]) <= y) & (y <= np.maximum(a[..., 1], b[..., 1])) & (a[..., 1] != b[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x = a[..., 0] + (y - a[..., 1]) / (b[..., 1] - a[..., 1]) * (b[..., 0] - a[..., 0])
    left = np.maximum(np.ceil(np.where(spans, x, np.inf).min(axis=1, initial=np.inf)), -width)
    right = np.minimum(np.floor(np.where(spans, x, -np.inf).max(axis=1, initial=-np.inf)), 2 * width - 1)
    ok = left <= right
    return rows[ok], left[ok].astype(int), right[ok].astype(int)


def bop_model_info(vertices_mm: np.ndarray) -> dict:
    """models_info.json's entry: extent and diameter (the largest distance between two vertices), mm.
    vertices_mm: (V, 3). Memory linear in V (model_diameter_mm)."""
    lo, hi = vertices_mm.min(axis=0), vertices_mm.max(axis=0)
    return {"diameter": model_diameter_mm(vertices_mm), "min_x": float(lo[0]), "min_y": float(lo[1]),
            "min_z": float(lo[2]), "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]),
            "size_z": float(hi[2] - lo[2])}


def model_diameter_mm(vertices_mm: np.ndarray, chunk_pairs: int = DIAMETER_CHUNK_PAIRS) -> float:
    """The largest distance between two of the points (V, 3), exact: it joins two vertices of their convex
    hull, so only the hull's vertices (and the points Qhull found within roundoff of a facet) are compared,
    pairwise in blocks of at most `chunk_pairs` distances (memory linear in V whatever the hull's size). A flat or
    degenerate point set (no 3-D hull) compares every point the same way."""
    pts = np.asarray(vertices_mm, dtype=float)
    if len(pts) < 2:
        return 0.0
    pts = pts[_hull_candidates(pts)]
    pts = pts - 0.5 * (pts.min(axis=0) + pts.max(axis=0))  # centred: small norms, no cancellation below
    sq = np.einsum("ij,ij->i", pts, pts)
    minus_2t = -2.0 * pts.T  # (3, n)
    rows = max(1, chunk_pairs // len(pts))
    best = 0.0
    for i in range(0, len(pts), rows):
        d2 = pts[i:i + rows] @ minus_2t[:, i:]  # (rows, n - i): the pairs (r, j >= r), |p_r - p_j|^2 - |p_r|^2
        d2 += sq[None, i:]
        best = max(best, float((d2.max(axis=1) + sq[i:i + rows]).max()))
    return math.sqrt(max(best, 0.0))


def _hull_candidates(pts: np.ndarray) -> np.ndarray:
    """Indices of the points that can end a diameter: the convex hull's vertices and coplanar points; all the
    points when they span no 3-D hull."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):
        return np.arange(len(pts))
    return np.unique(np.concatenate([hull.vertices, hull.coplanar[:, 0]]).astype(int))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals, area-weighted: each vertex sums the cross products (twice the area times the unit
    normal) of the triangles (F, 3) that use it, counter-clockwise seen from outside. A vertex whose sum vanishes
    (no or only degenerate triangles) takes the direction from the points' centre, or +z at the centre."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=int).reshape(-1, 3)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for corner in range(3):
        np.add.at(acc, f[:, corner], cross)
    norm = np.linalg.norm(acc, axis=1)
    bad = ~(norm > 0)
    if bad.any():
        radial = v[bad] - v.mean(axis=0)
        r = np.linalg.norm(radial, axis=1)
        radial[~(r > 0)] = (0.0, 0.0, 1.0)
        acc[bad], norm[bad] = radial, np.linalg.norm(radial, axis=1)
    return acc / norm[:, None]


def ply_with_normals(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> bytes:
    """An ASCII PLY (x y z nx ny nz per vertex as float; triangles as vertex lists), as the BOP toolkit's
    inout.load_ply reads it. vertices (V, 3) in the file's unit, faces (F, 3), normals (V, 3) unit."""
    v, n, f = np.asarray(vertices, float), np.asarray(normals, float), np.asarray(faces, int).reshape(-1, 3)
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(v)}\n"
            + "".join(f"property float {c}\n" for c in ("x", "y", "z", "nx", "ny", "nz"))
            + f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = [f"{a:.6f} {b:.6f} {c:.6f} {d:.6f} {e:.6f} {g:.6f}" for (a, b, c), (d, e, g) in zip(v, n)]
    rows += [f"3 {a} {b} {c}" for a, b, c in f]
    return (head + "\n".join(rows) + "\n").encode("ascii")
