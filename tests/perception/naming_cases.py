"""Ground-truth naming cases: the box's corners of random poses through the project camera (no network)."""

import numpy as np

from envisat_pose.geometry import load_camera, load_geometry, visible_corners
from envisat_pose.perception.heatmaps import CORNER_END, CORNER_JTYPE


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def make_case(rng: np.random.Generator, noise_px: float = 1.0, n_spurious: int = 2, type_acc: float = 0.85,
              side_acc: float = 0.5):
    """A view of the box: candidates (shuffled visible corners + noise + spurious), their types' probabilities
    (M, 4): the end right with probability type_acc (5 % flipped), the side with side_acc (0.5: the image cannot
    tell +z from -z), and the truth (R, t, corners_px (8, 2), visible (8,))."""
    cam = load_camera()
    g = load_geometry()
    K = cam.K
    while True:
        R = random_rotation(rng)
        rng_m = rng.uniform(20.0, 80.0)
        off = rng.uniform(-0.5, 0.5, size=2) * 0.5 * cam.width_px / cam.f_px * rng_m
        t = np.array([off[0], off[1], rng_m])
        Xc = g.corners_T_m @ R.T + t
        px = (Xc[:, :2] / Xc[:, 2:]) * cam.f_px + [cam.cu_px, cam.cv_px]
        vis = visible_corners(-R.T @ t, g) & np.all((px > 0) & (px < cam.width_px - 1), axis=1)
        if vis.sum() >= 4:
            break
    idx = np.flatnonzero(vis)
    pts = px[idx] + rng.normal(scale=noise_px, size=(len(idx), 2))
    types = CORNER_END[idx]
    sides = CORNER_JTYPE[idx] % 2
    # spurious junctions somewhere around the target
    centre = px[vis].mean(axis=0)
    span = np.ptp(px[vis], axis=0).max() + 20
    spur = centre + rng.uniform(-span, span, size=(n_spurious, 2))
    pts = np.concatenate([pts, spur])
    truth_id = np.concatenate([idx, -np.ones(n_spurious, int)])
    p1 = np.where(np.concatenate([types, rng.integers(0, 2, n_spurious)]) == 1, type_acc, 1 - type_acc)
    flip = rng.random(len(p1)) < 0.05
    p1 = np.where(flip, 1 - p1, p1)
    p1[len(idx):] = 0.5
    s1 = np.where(np.concatenate([sides, np.zeros(n_spurious, int)]) == 1, side_acc, 1 - side_acc)
    s1[len(idx):] = 0.5
    type_prob = np.stack([(1 - p1) * (1 - s1), (1 - p1) * s1, p1 * (1 - s1), p1 * s1], -1)
    order = rng.permutation(len(pts))
    return {"points_px": pts[order], "truth_id": truth_id[order], "type_prob": type_prob[order],
            "K": K, "R": R, "t": t, "corners_px": px, "visible": vis, "image_size": (cam.width_px, cam.height_px)}


def outcome(case: dict, naming, tol_px: float = 6.0, found_only: bool = False) -> str:
    """'right' (true names), 'ambiguous' (the half-turn alternative is right and flagged), or 'wrong'.
    found_only: the corners whose candidate was dropped must be predicted visible, not matched."""
    if naming is None:
        return "wrong"
    vis = case["visible"]
    found = np.zeros(8, bool)
    found[case["truth_id"][case["truth_id"] >= 0]] = True
    check = vis & found if found_only else vis

    def fits(n) -> bool:
        return bool(np.all(np.linalg.norm(n.corners_px[check] - case["corners_px"][check], axis=1) < tol_px)
                    and np.array_equal(n.visible, vis))

    if fits(naming):
        return "right"
    if naming.ambiguous and naming.alternative is not None and fits(naming.alternative):
        return "ambiguous"
    return "wrong"
