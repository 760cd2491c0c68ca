"""Scoring another target's named keypoints against the labels: pure functions over plain arrays (plus OpenCV's
PnP). The job that runs the keypoint detector over a dataset is pipelines/detector/evaluate_target.py.

Shapes: N frames, K keypoints (the Target's order). pred_px (N, K, 2) px, the detector's position of each channel
(always given: its heatmap's peak); true_px (N, K, 2) px, the labels'; usable (N, K) bool, the labelled keypoints a
detector should find (visible: unoccluded by the Target's exact ray casts, and in the frame); called (N, K) bool,
the keypoints the detector calls visible (visible_prob at its threshold).

- Localization: the distance of each usable keypoint's position from its label, whatever the detector calls its
  visibility (that is scored apart): PCK at r px is the share of usable keypoints within r (r inclusive), median
  and p95 over the usable keypoints.
- Visibility: precision (called visible and usable over called visible) and recall (over usable).
- Named wrongly: a keypoint called visible whose position lies within MATCH_PX of the label of ANOTHER usable
  keypoint and not within MATCH_PX of its own (the wrong channel fired: a twin, a neighbour); its rate is per
  keypoint called visible.
- Twins: where the Target has rotations its materials keep (keypoint_loss.relabelings: the identity first), no
  image tells the twin namings apart; `best_relabeling` picks per frame the permutation with the most keypoints
  within MATCH_PX of their labels (ties: the smaller summed distance), and the scores are given under it too.
- Pose: cv2.solvePnPRansac (EPnP, reprojection threshold PNP_REPROJ_PX) on the keypoints called visible against
  the Target's keypoints_T_m and the label's K, refined on its inliers (SOLVEPNP_ITERATIVE); scored as the angle of
  R R_true^T (deg) and |t - t_true| in % of the range |t_true|. "Solved" is any pose PnP returns (an untrained
  network's too, thousands of times the range off); "found" is a plausible one (pose_found: at least 6 RANSAC inliers, their
  reprojection RMS within 5 px, the range within a factor 2 of the label's), the errors' medians and p95 are over
  those; "correct" is a found one within POSE_OK_DEG and POSE_OK_PCT of the label's. Each share is over all frames.
"""

from __future__ import annotations

import cv2
import numpy as np

from envisat_pose.perception.evaluate import MATCH_PX, visibility_precision_recall

PCK_RADII_PX = (2.0, 5.0)
PNP_REPROJ_PX = MATCH_PX  # RANSAC's inlier threshold: a keypoint farther off is as good as named wrongly
PNP_MIN_POINTS = 4
POSE_OK_DEG, POSE_OK_PCT = 5.0, 5.0  # a correct pose: within 5 deg and 5 % of the range (2.5 m at 50 m)
# a pose found (pose_found): a consensus beyond EPnP RANSAC's 5-point sample, fitting its inliers as RANSAC
# accepted them, at a range a factor 2 of the label's at most (a barely trained network's PnP puts the target
# up to 1e7 times its range off: those are no poses, and their errors are kept out of the medians)
FOUND_MIN_INLIERS, FOUND_RMS_PX, FOUND_RANGE_FACTOR = 6, PNP_REPROJ_PX, 2.0
FOUND_RULE = {"min_inliers": FOUND_MIN_INLIERS, "max_rms_px": FOUND_RMS_PX, "range_factor": FOUND_RANGE_FACTOR}


def keypoint_distances(pred_px: np.ndarray, true_px: np.ndarray) -> np.ndarray:
    """(N, K) px: the distance of each channel's position from the label of the same name."""
    return np.linalg.norm(np.asarray(pred_px, float) - np.asarray(true_px, float), axis=-1)


def best_relabeling(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, perms: np.ndarray,
                    radius_px: float = MATCH_PX) -> np.ndarray:
    """(N,) int: per frame the row of perms (P, K) under which pred_px[:, perm] (channel perm[k] taken as keypoint
    k) has the most usable keypoints within radius_px of their labels; ties go to the smaller summed distance of
    the usable keypoints, then to the earlier row (the identity first)."""
    pred, usable = np.asarray(pred_px, float), np.asarray(usable, bool)
    perms = np.asarray(perms, np.int64).reshape(-1, pred.shape[1])
    d = np.stack([keypoint_distances(pred[:, p], true_px) for p in perms], axis=1)  # (N, P, K)
    hits = np.sum(usable[:, None] & (d <= radius_px), axis=2)
    total = np.sum(np.where(usable[:, None], d, 0.0), axis=2)
    best = hits.max(axis=1, keepdims=True)
    total = np.where(hits == best, total, np.inf)
    return np.argmin(total, axis=1)


def relabeled(a: np.ndarray, perms: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """a (N, K, ...) with each frame's keypoints taken in the order perms[chosen[n]]: out[n, k] = a[n, perm[k]]."""
    a = np.asarray(a)
    idx = np.asarray(perms, np.int64)[np.asarray(chosen, np.int64)]  # (N, K)
    return np.take_along_axis(a, idx.reshape(idx.shape + (1,) * (a.ndim - 2)), axis=1)


def wrongly_named(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, called: np.ndarray,
                  radius_px: float = MATCH_PX) -> np.ndarray:
    """(N, K) bool: keypoint i called visible, within radius_px of the label of a usable keypoint j != i and not
    within radius_px of its own label."""
    pred, true = np.asarray(pred_px, float), np.asarray(true_px, float)
    k = pred.shape[1]
    d = np.linalg.norm(pred[:, :, None, :] - true[:, None, :, :], axis=-1)  # (N, i channel, j label)
    near_other = (d <= radius_px) & np.asarray(usable, bool)[:, None, :] & ~np.eye(k, dtype=bool)[None]
    own = np.diagonal(d, axis1=1, axis2=2) <= radius_px
    return np.asarray(called, bool) & near_other.any(axis=2) & ~own


def correct_errors(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, called: np.ndarray,
                   radius_px: float = MATCH_PX) -> np.ndarray:
    """(N, K, 2) px: detected - label of the correct detections (usable, called visible and within radius_px of
    their own label), NaN elsewhere."""
    e = np.asarray(pred_px, float) - np.asarray(true_px, float)
    ok = np.asarray(usable, bool) & np.asarray(called, bool) & (np.linalg.norm(e, axis=-1) <= radius_px)
    return np.where(ok[..., None], e, np.nan)


def distance_stats(d: np.ndarray) -> dict:
    """Median and 95th percentile (numpy's linear interpolation) of distances d (M,) px, and their count."""
    d = np.asarray(d, float).ravel()
    if len(d) == 0:
        return {"median_px": float("nan"), "p95_px": float("nan"), "count": 0}
    return {"median_px": float(np.median(d)), "p95_px": float(np.percentile(d, 95)), "count": int(len(d))}


def _share(num: int, den: int) -> float:
    return float(num / den) if den else float("nan")


def keypoint_scores(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, called: np.ndarray,
                    radii_px=PCK_RADII_PX) -> dict:
    """The scores of one set of keypoints (any shape (..., 2) / (...)): usable count, pck_<r>px for each radius,
    median_px, p95_px, visibility precision and recall, called (count called visible), named_wrongly (count) and
    named_wrongly_rate (per keypoint called visible). Plain JSON data (NaN where undefined)."""
    usable, called = np.asarray(usable, bool), np.asarray(called, bool)
    d = keypoint_distances(pred_px, true_px)
    n = int(usable.sum())
    out = {"usable": n}
    for r in radii_px:
        out[f"pck_{r:g}px"] = _share(int(np.sum(usable & (d <= r))), n)
    out.update({k: v for k, v in distance_stats(d[usable]).items() if k != "count"})
    precision, recall = visibility_precision_recall(called, usable)
    out.update({"vis_precision": float(precision), "vis_recall": float(recall), "called": int(called.sum())})
    return out


def score_keypoints(pred_px: np.ndarray, true_px: np.ndarray, usable: np.ndarray, called: np.ndarray,
                    names, radius_px: float = MATCH_PX) -> dict:
    """keypoint_scores over every keypoint ('all') and per keypoint name ('per_keypoint'), with the keypoints
    named wrongly (wrongly_named at radius_px) counted in each."""
    pred, true = np.asarray(pred_px, float), np.asarray(true_px, float)
    usable, called = np.asarray(usable, bool), np.asarray(called, bool)
    wrong = wrongly_named(pred, true, usable, called, radius_px)

    def with_wrong(scores: dict, w: np.ndarray) -> dict:
        return {**scores, "named_wrongly": int(w.sum()), "named_wrongly_rate": _share(int(w.sum()),
                                                                                      scores["called"])}

    out = {"all": with_wrong(keypoint_scores(pred, true, usable, called), wrong), "per_keypoint": {}}
    for k, name in enumerate(names):
        out["per_keypoint"][str(name)] = with_wrong(
            keypoint_scores(pred[:, k], true[:, k], usable[:, k], called[:, k]), wrong[:, k])
    return out


# --- pose after PnP -----------------------------------------------------------------------------------------


def pnp_solve(points_px: np.ndarray, use: np.ndarray, K: np.ndarray, keypoints_T_m: np.ndarray,
              reproj_px: float = PNP_REPROJ_PX) -> dict | None:
    """PnP from the keypoints points_px (K, 2) where use (K,) of the Target's keypoints_T_m (K, 3):
    solvePnPRansac (EPnP), refined on its inliers by SOLVEPNP_ITERATIVE. {'R': R_cam_from_target (3, 3), 't':
    t_cam_from_target_m (3,), 'inliers': RANSAC's inlier count, 'rms_px': the refined pose's reprojection RMS over
    those inliers}; None with fewer than PNP_MIN_POINTS used or inliers, when the solver fails, or for a pose that
    puts an inlier behind the camera. Whether the pose is plausible is pose_found's question."""
    use = np.asarray(use, bool) & np.all(np.isfinite(points_px), axis=-1)
    if use.sum() < PNP_MIN_POINTS:
        return None
    obj = np.ascontiguousarray(np.asarray(keypoints_T_m, float)[use].reshape(-1, 1, 3))
    img = np.ascontiguousarray(np.asarray(points_px, float)[use].reshape(-1, 1, 2))
    K = np.asarray(K, float)
    try:
        good, rvec, tvec, inliers = cv2.solvePnPRansac(obj, img, K, None, reprojectionError=reproj_px,
                                                       iterationsCount=200, flags=cv2.SOLVEPNP_EPNP)
    except cv2.error:
        return None
    if not good or inliers is None or len(inliers) < PNP_MIN_POINTS:
        return None
    i = inliers.ravel()
    good, rvec, tvec = cv2.solvePnP(obj[i], img[i], K, None, rvec, tvec, useExtrinsicGuess=True,
                                    flags=cv2.SOLVEPNP_ITERATIVE)
    if not good or not np.all(np.isfinite(tvec)) or not np.all(np.isfinite(rvec)):
        return None
    R, t = cv2.Rodrigues(rvec)[0], tvec.reshape(3)
    cam = obj[i].reshape(-1, 3) @ R.T + t
    if np.any(cam[:, 2] <= 0):  # a pose with its keypoints behind the camera
        return None
    px = cam @ K.T
    rms = float(np.sqrt(np.mean(np.sum((px[:, :2] / px[:, 2:] - img[i].reshape(-1, 2)) ** 2, axis=1))))
    return {"R": R, "t": t, "inliers": int(len(i)), "rms_px": rms}


def pnp_pose(points_px: np.ndarray, use: np.ndarray, K: np.ndarray, keypoints_T_m: np.ndarray,
             reproj_px: float = PNP_REPROJ_PX) -> tuple[np.ndarray, np.ndarray] | None:
    """(R_cam_from_target (3, 3), t_cam_from_target_m (3,)) of pnp_solve, None where it gives none."""
    got = pnp_solve(points_px, use, K, keypoints_T_m, reproj_px)
    return None if got is None else (got["R"], got["t"])


def pose_found(solution: dict | None, t_true_m: np.ndarray) -> bool:
    """Whether pnp_solve's solution is a pose found, i.e. a plausible one (FOUND_RULE): at least
    FOUND_MIN_INLIERS RANSAC inliers (EPnP's RANSAC fits its 5-point sample exactly, so 5 "inliers" of any 5
    points is no consensus), its inliers' reprojection RMS at most FOUND_RMS_PX, and its range within a factor
    FOUND_RANGE_FACTOR of the label's |t_true_m| (the inliers in front of the camera: pnp_solve's own guard).
    False without a solution or a finite labelled range."""
    range_true_m = float(np.linalg.norm(np.asarray(t_true_m, float)))
    if solution is None or not np.isfinite(range_true_m) or range_true_m <= 0:
        return False
    ratio = float(np.linalg.norm(solution["t"])) / range_true_m
    return bool(solution["inliers"] >= FOUND_MIN_INLIERS and solution["rms_px"] <= FOUND_RMS_PX
                and 1.0 / FOUND_RANGE_FACTOR <= ratio <= FOUND_RANGE_FACTOR)


def pose_error(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray) -> tuple[float, float]:
    """(rotation error deg: the angle of R R_true^T; translation error in % of the range: 100 |t - t_true| /
    |t_true|)."""
    turn = cv2.Rodrigues(np.asarray(R, float) @ np.asarray(R_true, float).T)[0]  # accurate near 0, unlike acos
    t, t_true = np.asarray(t, float), np.asarray(t_true, float)
    return float(np.degrees(np.linalg.norm(turn))), float(100.0 * np.linalg.norm(t - t_true) / np.linalg.norm(t_true))


def pose_summary(err: np.ndarray, found: np.ndarray | None = None) -> dict:
    """err (N, 2) rotation deg and translation % of range per frame, NaN where PnP gave no pose; found (N,) bool
    the frames whose pose is a pose found (pose_found; None: every pose PnP gave). The share of frames PnP gave a
    pose ('solved_share', however far off), of frames with a pose found ('found_share'), with a correct one (found
    and within POSE_OK_DEG and POSE_OK_PCT, 'correct_share'), each over all frames; the median and p95 of each
    error over the frames with a pose found; the rule of each ('found_rule', 'correct_within')."""
    e = np.asarray(err, float).reshape(-1, 2)
    solved = np.all(np.isfinite(e), axis=1)
    ok = solved if found is None else solved & np.asarray(found, bool).reshape(-1)
    correct = ok & (np.where(ok, e[:, 0], np.inf) <= POSE_OK_DEG) & (np.where(ok, e[:, 1], np.inf) <= POSE_OK_PCT)
    out = {"frames": int(len(e)), "solved_share": _share(int(solved.sum()), len(e)),
           "found_share": _share(int(ok.sum()), len(e)), "found_rule": dict(FOUND_RULE),
           "correct_share": _share(int(correct.sum()), len(e)), "correct_within": [POSE_OK_DEG, POSE_OK_PCT]}
    for j, name in enumerate(("rotation_deg", "translation_pct")):
        v = e[ok, j]
        out[f"{name}_median"] = float(np.median(v)) if len(v) else float("nan")
        out[f"{name}_p95"] = float(np.percentile(v, 95)) if len(v) else float("nan")
    return out
