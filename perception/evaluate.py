"""Scoring named corners against labels: pure functions over plain arrays.

Shapes: N frames, 8 corners A-H. pred_px (N, 8, 2) px, NaN where a corner was not found; true_px (N, 8, 2) px;
usable (N, 8) bool, the labelled corners a detector should find (visible and in frame). A corner counts as a hit
at radius r px when it was found, named as the label names it, and lies within r of it: a missed or wrongly
named corner is a miss. A frame declared ambiguous under the half-turn about the long axis (A<->C, B<->D,
E<->G, F<->H) is scored with the better of its two namings (`better_naming`: the labels choose between the two
the detector offers; the tracker chooses by the dynamics); pck_*_strict and the strict swaps score the first naming
of every frame.

Also here: the classical peers (Harris and Shi-Tomasi with sub-pixel refinement and oracle association), the
pose from named corners by solvePnP, and the corruption grouping of labels (`corruption_levels`).
"""

from __future__ import annotations

import cv2
import numpy as np

from envisat_pose.contracts import SEVERITIES
from envisat_pose.geometry import CORNER_NAMES, load_geometry
from envisat_pose.perception.box_symmetry import symmetry_permutations
from envisat_pose.perception.calibrate import nees_px
from envisat_pose.perception.errormodel import apparent_scale, mean_se, radial_errors

# the half-turn about the long axis x: corner k shows where corner HALF_TURN_PERM[k] was, derived from the target's
# geometry (A<->C, B<->D, E<->G, F<->H for the box of models/envisat.xml)
HALF_TURN_PERM = symmetry_permutations(load_geometry())["x"][0]
MATCH_PX = 5.0  # radius within which a named corner is 'correctly named' (swaps, calibration, the better naming)


def corner_errors(pred_px: np.ndarray, true_px: np.ndarray) -> np.ndarray:
    """Pixel distance of each named corner from the labelled corner of the same name: (N, 8), NaN where missing."""
    return np.linalg.norm(np.asarray(pred_px, float) - np.asarray(true_px, float), axis=-1)


def hits(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, radius_px: float) -> np.ndarray:
    """(N, 8) bool: usable corners found and named right within radius_px."""
    err = corner_errors(pred_px, true_px)
    return np.asarray(usable, bool) & np.nan_to_num(err <= radius_px, nan=False)


def better_naming(pred_px: np.ndarray, alt_px: np.ndarray, ambiguous: np.ndarray, true_px: np.ndarray,
                  usable: np.ndarray, radius_px: float = MATCH_PX) -> tuple[np.ndarray, np.ndarray]:
    """The naming each frame is scored with: the alternative where the frame is ambiguous and the alternative has
    more hits within radius_px (ties: the smaller summed error of usable found corners). Returns (chosen (N, 8, 2),
    used_alt (N,) bool)."""
    pred, alt = np.asarray(pred_px, float), np.asarray(alt_px, float)
    h0 = hits(pred, true_px, usable, radius_px).sum(axis=1)
    h1 = hits(alt, true_px, usable, radius_px).sum(axis=1)
    e0 = np.where(usable, np.nan_to_num(corner_errors(pred, true_px), nan=0.0), 0.0).sum(axis=1)
    e1 = np.where(usable, np.nan_to_num(corner_errors(alt, true_px), nan=0.0), 0.0).sum(axis=1)
    use = np.asarray(ambiguous, bool) & ((h1 > h0) | ((h1 == h0) & (e1 < e0)))
    return np.where(use[:, None, None], alt, pred), use


def pck(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, radius_px: float) -> float:
    """Share of usable corners that are hits at radius_px (NaN when there are none)."""
    n = int(np.sum(usable))
    return float(hits(pred_px, true_px, usable, radius_px).sum() / n) if n else float("nan")


def error_stats(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray) -> dict[str, dict]:
    """Median and 95th percentile of the error, px, of usable corners that were found (named as found: a wrong
    name shows as a large error), per corner name and over all ('all'); with their count."""
    err = corner_errors(pred_px, true_px)
    sel = np.asarray(usable, bool) & np.isfinite(err)

    def stats(e: np.ndarray) -> dict:
        if len(e) == 0:
            return {"median_px": float("nan"), "p95_px": float("nan"), "count": 0}
        return {"median_px": float(np.median(e)), "p95_px": float(np.percentile(e, 95)), "count": int(len(e))}

    out = {"all": stats(err[sel])}
    for k, name in enumerate(CORNER_NAMES):
        out[name] = stats(err[:, k][sel[:, k]])
    return out


def visibility_precision_recall(pred_visible: np.ndarray, usable: np.ndarray) -> tuple[float, float]:
    """Precision (share of corners declared visible that are labelled usable) and recall (share of usable
    corners declared visible); NaN where the denominator is 0."""
    p, u = np.asarray(pred_visible, bool), np.asarray(usable, bool)
    tp = int(np.sum(p & u))
    return (tp / p.sum() if p.sum() else float("nan")), (tp / u.sum() if u.sum() else float("nan"))


def swaps(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, radius_px: float = MATCH_PX) -> np.ndarray:
    """(N, 8) bool: identity swaps, a found corner named i lying within radius_px of another usable labelled
    corner j != i and not within radius_px of its own."""
    pred, true = np.asarray(pred_px, float), np.asarray(true_px, float)
    d = np.linalg.norm(pred[:, :, None, :] - true[:, None, :, :], axis=-1)  # (N, i named, j labelled)
    near_other = np.nan_to_num(d <= radius_px, nan=False) & np.asarray(usable, bool)[:, None, :]
    near_other &= ~np.eye(8, dtype=bool)[None]
    own = np.nan_to_num(np.diagonal(d, axis1=1, axis2=2) <= radius_px, nan=False)
    return near_other.any(axis=2) & ~own


def swap_rate(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, radius_px: float = MATCH_PX) -> float:
    """Identity swaps per found corner (NaN when nothing was found)."""
    found = int(np.all(np.isfinite(pred_px), axis=-1).sum())
    return float(swaps(pred_px, true_px, usable, radius_px).sum() / found) if found else float("nan")


def mean_nees(pred_px: np.ndarray, cov_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray,
              radius_px: float = MATCH_PX) -> tuple[float, int]:
    """Covariance calibration: mean e^T C^-1 e (2 when honest) over usable corners named right within radius_px
    with a finite covariance (N, 8, 2, 2) px^2; and their count."""
    cov = np.asarray(cov_px, float)
    sel = hits(pred_px, true_px, usable, radius_px) & np.all(np.isfinite(cov), axis=(-2, -1))
    if not sel.any():
        return float("nan"), 0
    e = (np.asarray(pred_px, float) - np.asarray(true_px, float))[sel]
    return float(np.mean(nees_px(e, cov[sel]))), int(sel.sum())


def label_roi(corners_px: np.ndarray, image_hw: tuple[int, int], margin: float = 1.4, min_side_px: int = 64
              ) -> np.ndarray:
    """The region of interest (x0, y0, side) px a perfect prior gives, as the closed loop makes it from the
    predicted corners (app/run.predicted_roi with no prior uncertainty; its defaults roi_margin 1.4 and
    roi_min_side_px 64): the square around the extent of the finite labelled corners (8, 2) x margin."""
    pts = np.asarray(corners_px, float)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    h, w = image_hw
    if len(pts) == 0:
        return np.array([0, 0, max(h, w)], dtype=np.int64)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    side = max(float(np.max(hi - lo)) * margin, float(min_side_px))
    side = int(np.ceil(min(side, 2.0 * max(w, h))))
    x0, y0 = np.round((lo + hi) / 2 - side / 2).astype(int)
    return np.array([x0, y0, side], dtype=np.int64)


# --- the classical peers ------------------------------------------------------------------------------------


def classical_corners(image_u8: np.ndarray, harris: bool, max_corners: int = 500, quality: float = 0.001,
                      min_distance_px: float = 5.0, block_size: int = 5) -> np.ndarray:
    """Harris (harris=True) or Shi-Tomasi corners of an 8-bit frame, refined by cornerSubPix: (M, 2) px. Generous
    settings (many corners, a low quality floor): the oracle association then finds more of the box corners."""
    pts = cv2.goodFeaturesToTrack(image_u8, maxCorners=max_corners, qualityLevel=quality,
                                  minDistance=min_distance_px, blockSize=block_size,
                                  useHarrisDetector=harris, k=0.04)
    if pts is None:
        return np.zeros((0, 2))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    pts = cv2.cornerSubPix(image_u8, pts.astype(np.float32), (5, 5), (-1, -1), crit)
    return pts.reshape(-1, 2).astype(np.float64)


def associate_nearest(points_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Oracle naming of unnamed points (M, 2): each usable labelled corner (8, 2) takes the nearest point not yet
    taken, closest pairs first. (8, 2) px, NaN where no point was left or the corner is not usable."""
    out = np.full((8, 2), np.nan)
    pts = np.asarray(points_px, float).reshape(-1, 2)
    if len(pts) == 0:
        return out
    d = np.linalg.norm(np.asarray(true_px, float)[:, None] - pts[None], axis=-1)
    d[~np.asarray(usable, bool)] = np.inf
    taken = np.zeros(len(pts), bool)
    for flat in np.argsort(d, axis=None):
        k, m = np.unravel_index(flat, d.shape)
        if not np.isfinite(d[k, m]):
            break
        if np.isnan(out[k, 0]) and not taken[m]:
            out[k] = pts[m]
            taken[m] = True
    return out


# --- pose ---------------------------------------------------------------------------------------------------


def pose_from_corners(corners_px: np.ndarray, K: np.ndarray, corners_T_m: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """(R_cam_from_target (3, 3), t_cam_from_target_m (3,)) by solvePnP from the found named corners (8, 2)
    (NaN: not found) of the box corners_T_m (8, 3) m: EPnP, then refined with SOLVEPNP_ITERATIVE. None with fewer
    than 4 corners or when the solver fails."""
    ok = np.all(np.isfinite(corners_px), axis=1)
    if ok.sum() < 4:
        return None
    obj = np.asarray(corners_T_m, float)[ok].reshape(-1, 1, 3)
    img = np.asarray(corners_px, float)[ok].reshape(-1, 1, 2)
    K = np.asarray(K, float)
    good, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_EPNP)
    if not good:
        return None
    good, rvec, tvec = cv2.solvePnP(obj, img, K, None, rvec, tvec, useExtrinsicGuess=True,
                                    flags=cv2.SOLVEPNP_ITERATIVE)
    if not good or not np.all(np.isfinite(tvec)):
        return None
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3)


def pose_errors(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg: the angle of R R_true^T)."""
    c = (np.trace(np.asarray(R) @ np.asarray(R_true).T) - 1.0) / 2.0
    return float(np.linalg.norm(np.asarray(t) - np.asarray(t_true))), float(np.degrees(np.arccos(np.clip(c, -1, 1))))


# --- corruption groups --------------------------------------------------------------------------------------


def _level(value: float, steps: tuple[float, float, float]) -> int:
    """0..3: how many of the ascending thresholds `steps` value reaches."""
    return int(sum(value >= s for s in steps))


def corruption_levels(corruption: dict, resolution_px: int) -> tuple[int, int]:
    """(noise level, blur level), each 0 'none' .. 3 'high', of a label's `corruption` entry.

    'paper' model: noise = the higher of the gaussian_noise and shot_noise levels, blur = the higher of the
    gaussian_blur and motion_blur levels (exposure is photometric and not counted). 'sensor' model (the space
    camera has no named levels): noise = its noise sigma at mid-grey in grey levels (shot and read noise), binned
    at the paper's Gaussian sigmas 2, 5, 10; blur = its equivalent Gaussian sigma at 1024 px (PSF sigma, an Airy
    PSF's first zero x 0.344, a streak of length L as L / sqrt(12), in quadrature) binned at the paper's blur
    sigmas 1, 2, 4. No entry: (0, 0).
    """
    c = corruption or {}
    if "levels" in c:
        lv = {k: SEVERITIES.index(v) if v in SEVERITIES else 0 for k, v in c["levels"].items()}
        return (max(lv.get("gaussian_noise", 0), lv.get("shot_noise", 0)),
                max(lv.get("gaussian_blur", 0), lv.get("motion_blur", 0)))
    if c.get("model") == "sensor":
        white = float(c.get("white_e", 0.0)) or 1.0
        sigma_e = np.sqrt(white / 2.0 + float(c.get("read_noise_e", 0.0)) ** 2)
        noise_grey = 255.0 * sigma_e / white
        psf = c.get("psf", {}) or {}
        psf_sigma = float(psf.get("sigma_px", 0.0)) if psf.get("kind") == "gaussian" else \
            0.344 * float(psf.get("first_zero_px", 0.0))
        streak = float(c.get("motion_blur_length_px", 0.0)) / np.sqrt(12.0)
        blur_1024 = np.hypot(psf_sigma, streak) * 1024.0 / resolution_px
        return _level(noise_grey, (2.0, 5.0, 10.0)), _level(blur_1024, (1.0, 2.0, 4.0))
    return 0, 0


def corruption_groups(noise_level: int, blur_level: int) -> list[str]:
    """The groups one frame is scored in: 'all'; exactly one of 'clean' (no noise, no blur), 'noise_only',
    'blur_only', 'combined' (both); and, marginally (overlapping), 'noise=<level>' and 'blur=<level>'."""
    kind = {(False, False): "clean", (True, False): "noise_only", (False, True): "blur_only",
            (True, True): "combined"}[(noise_level > 0, blur_level > 0)]
    return ["all", kind, f"noise={SEVERITIES[noise_level]}", f"blur={SEVERITIES[blur_level]}"]


GROUP_ORDER = (["all", "clean", "noise_only", "blur_only", "combined"] + [f"noise={s}" for s in SEVERITIES]
               + [f"blur={s}" for s in SEVERITIES])
# range bins (m) of the frames' target range |t_cam_from_target|: the random sets span 20-80 m
RANGE_EDGES_M = (35.0, 50.0, 65.0)
RANGE_GROUPS = ("range<35m", "range=35-50m", "range=50-65m", "range>=65m")


def range_group(range_m: float) -> str | None:
    """The range bin of a frame (RANGE_GROUPS), None when the range is unknown."""
    if not np.isfinite(range_m):
        return None
    return RANGE_GROUPS[int(np.searchsorted(RANGE_EDGES_M, range_m, side="right"))]


def bias_stats(chosen_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, radius_px: float = MATCH_PX) -> dict:
    """The residual bias of named corners (perception/errormodel.py): the per-frame apparent scale about the
    centroid (frames with at least 3 corners named right within radius_px and none named wrong) and the signed
    radial error px (positive outward) of the corners named right, each as mean, standard error and count."""
    right = hits(chosen_px, true_px, usable, radius_px)
    wrong = np.asarray(usable, bool) & np.all(np.isfinite(chosen_px), axis=-1) & ~right
    sm, sse, sn = mean_se(apparent_scale(chosen_px, true_px, right, wrong))
    rm, rse, rn = mean_se(radial_errors(chosen_px, true_px, right))
    return {"scale_mean": sm, "scale_se": sse, "scale_frames": sn, "radial_px_mean": rm, "radial_px_se": rse,
            "radial_corners": rn}


# --- one method over a set of frames ------------------------------------------------------------------------


def score_method(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, *, alt_px: np.ndarray | None = None,
                 ambiguous: np.ndarray | None = None, pred_visible: np.ndarray | None = None,
                 cov_px: np.ndarray | None = None, pose_err: np.ndarray | None = None) -> dict:
    """Every metric of one method over N frames. pred_px, alt_px (N, 8, 2); ambiguous (N,); pred_visible
    (N, 8) (None: no visibility claim, as for the classical peers); cov_px (N, 8, 2, 2) (None: no covariance);
    pose_err (N, 2) translation m and rotation deg, NaN where no pose. Plain JSON data (NaN where undefined)."""
    pred = np.asarray(pred_px, float)
    n = len(pred)
    alt = pred if alt_px is None else np.asarray(alt_px, float)
    amb = np.zeros(n, bool) if ambiguous is None else np.asarray(ambiguous, bool)
    chosen, used_alt = better_naming(pred, alt, amb, true_px, usable)
    turned, _ = better_naming(pred, pred[:, HALF_TURN_PERM], np.ones(n, bool), true_px, usable)
    out = {"frames": int(n), "usable_corners": int(np.sum(usable)),
           "errors": error_stats(chosen, true_px, usable),
           "pck_2px": pck(chosen, true_px, usable, 2.0), "pck_5px": pck(chosen, true_px, usable, 5.0),
           "pck_2px_strict": pck(pred, true_px, usable, 2.0), "pck_5px_strict": pck(pred, true_px, usable, 5.0),
           "swap_rate_strict": swap_rate(pred, true_px, usable),
           "swap_rate": swap_rate(chosen, true_px, usable),
           "ambiguous_share": float(amb.mean()) if n else float("nan"),
           "alt_naming_used_share": float(used_alt.mean()) if n else float("nan"),
           "bias": bias_stats(chosen, true_px, usable),
           "half_turn_free": {"errors": error_stats(turned, true_px, usable)["all"],
                              "pck_2px": pck(turned, true_px, usable, 2.0),
                              "pck_5px": pck(turned, true_px, usable, 5.0)}}
    if pred_visible is not None:
        p, r = visibility_precision_recall(pred_visible, usable)
        out["visibility"] = {"precision": p, "recall": r}
    if cov_px is not None:
        m, c = mean_nees(pred, cov_px, true_px, usable)
        out["calibration"] = {"mean_nees": m, "count": c}
    if pose_err is not None:
        pe = np.asarray(pose_err, float).reshape(-1, 2)
        ok = np.all(np.isfinite(pe), axis=1)
        out["pose"] = {"solved_share": float(ok.mean()) if n else float("nan"),
                       "translation_m_median": float(np.median(pe[ok, 0])) if ok.any() else float("nan"),
                       "rotation_deg_median": float(np.median(pe[ok, 1])) if ok.any() else float("nan"),
                       "translation_m_p95": float(np.percentile(pe[ok, 0], 95)) if ok.any() else float("nan"),
                       "rotation_deg_p95": float(np.percentile(pe[ok, 1], 95)) if ok.any() else float("nan")}
    return out
