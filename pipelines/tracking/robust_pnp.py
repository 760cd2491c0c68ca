"""The cold start's per-frame PnP, robust to a few gross outliers among the named keypoints.

`keypoint_pose`: SQPnP, then Levenberg-Marquardt on the reprojection error (OpenCV), of the keypoints given; the
cold start's PnP (acquisition.pnp_state) since its beginning.

`robust_pnp`: one keypoint named on the wrong feature (a glint, a twin's name) pulls the all-keypoint pose by
degrees and every keypoint's residual with it, and the window's batch fit took both: with 10 % of the keypoints
gross outliers (a stand-in detector, seeds 0-4 of the upper stage, the 3U cubesat, a two-fold box and a
quarter-turn prism, 150 s) 6 of 20 runs first tracked at 64-137 s and 2 prism runs never; with this step all 20
at 24-42 s, none claimed wrong either way.

1. The pose of all named keypoints is kept, bit for bit, when it is self-consistent: every keypoint's squared
   reprojection residual whitened by its covariance (d^2 = r^T cov^-1 r, 2 dof) under the gate (the batch fit's,
   gates.chi2_gate(GATE_PROB, 2) = 23.03: a keypoint of the right pose passes it with probability 0.99999, so a
   clean frame of 12 keypoints falls back about once in 8000). A clean frame's pose and keypoints are the
   cold start's before; so are a frame's whose named keypoints a detector already chose by RANSAC.
2. Otherwise hypothesise and verify over minimal sets of 4 keypoints: every 4-subset of the measured ones
   (exhaustive, deterministic: 495 for 12 keypoints; beyond MAX_SUBSETS a sample drawn from a fixed seed), each
   set's AP3P pose scored by MSAC (the sum over the measured keypoints of min(d^2, gate)); the inliers (d^2 < gate)
   of the best few (LOCAL_REFITS distinct sets) refitted by SQPnP until the set stops changing; the refit that
   passes the most keypoints (then the lowest MSAC cost) gives the set, whose pose is SQPnP + LM.
3. The refit replaces the all-keypoint pose only when it passes more keypoints than that pose does and at least
   min_keypoints; a refit of 4 keypoints (a box's 5 seen with one outlier) only when no other minimal set's pose
   passes 4 keypoints of another set (4 keypoints check their pose by 2 residual components: one consistent set
   is evidence, two are a guess). Its outliers are returned, so the tracker drops them from the frame (NaN) and
   the window's batch fit never sees them. A frame of 4 keypoints (no spare to tell an outlier by), or none of
   whose refits passes these, keeps its all-keypoint pose and all its keypoints, as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from math import comb

import numpy as np

from envisat_pose.attitude import dcm_to_mrp
from envisat_pose.geometry import PinholeCamera
from envisat_pose.state import MRP, N_STATE, POS

MINIMAL = 4  # keypoints of a minimal set (SQPnP's unique pose of general points)
MAX_SUBSETS = 500  # the most minimal sets tried; every 4-subset of up to 12 keypoints (495)
LOCAL_REFITS = 5  # the distinct consistent sets of the best minimal sets refitted (_best_refit)
SUBSET_SEED = 0  # the fixed seed of the sample beyond MAX_SUBSETS: the same frame gives the same pose


@dataclass(frozen=True)
class RobustPose:
    """A frame's pose: x (12,) the state (rho_C_m, 0, p_mrp, 0); inliers (K,) bool the measured keypoints the pose
    was fitted to (all measured ones when the all-keypoint pose was kept); ransac: whether it was not kept."""

    x: np.ndarray
    inliers: np.ndarray
    ransac: bool


def keypoint_pose(obj_T_m: np.ndarray, img_px: np.ndarray, K: np.ndarray, minimal: bool = False,
                  refine: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """(R_K_from_T (3, 3), t_K_m (3,)) of keypoints obj_T_m (n, 3) seen at img_px (n, 2) (OpenCV px) by SQPnP,
    then (refine) Levenberg-Marquardt on the reprojection error; minimal: a set of exactly 4 by AP3P (3 keypoints'
    poses, the fourth choosing among them; a few times faster than SQPnP). None when PnP fails or puts the target
    behind the camera."""
    import cv2

    obj = np.ascontiguousarray(obj_T_m, dtype=np.float64)
    img = np.ascontiguousarray(img_px, dtype=np.float64)
    try:
        good, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_AP3P if minimal else cv2.SOLVEPNP_SQPNP)
        if not good:
            return None
        if refine:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    except cv2.error:
        return None
    t_K = tvec.reshape(3)
    if not (np.isfinite(t_K).all() and t_K[2] > 0):
        return None
    return cv2.Rodrigues(rvec)[0], t_K


def pose_state(R_K_from_T: np.ndarray, t_K_m: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """The 12-state (rho_C_m, 0, p_mrp, 0) of a camera pose: rho the target's origin in C, p the MRP of T from C."""
    x = np.zeros(N_STATE)
    x[POS] = camera.R_K_from_C.T @ t_K_m + camera.pos_C_m  # rho = R_C_from_K t_K + camera position in C
    x[MRP] = dcm_to_mrp(R_K_from_T.T @ camera.R_K_from_C)  # Gamma = T_from_C = (R_K_from_T)^T R_K_from_C
    return x


def whitened_d2(R_K_from_T: np.ndarray, t_K_m: np.ndarray, obj_T_m: np.ndarray, img_px: np.ndarray,
                cov_inv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Squared whitened reprojection residuals (H, n) of poses R (H, 3, 3), t (H, 3) at keypoints obj_T_m (n, 3)
    seen at img_px (n, 2) with inverse covariances cov_inv (n, 2, 2) px^-2; inf behind the camera."""
    p = np.einsum("hij,nj->hni", R_K_from_T, obj_T_m) + t_K_m[:, None]
    uvw = p @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        r = img_px - uvw[..., :2] / uvw[..., 2:]
    d2 = np.einsum("hni,nij,hnj->hn", r, cov_inv, r)
    return np.where((p[..., 2] > 0) & np.isfinite(d2), d2, np.inf)


def minimal_sets(n: int) -> np.ndarray:
    """(M, 4) index sets of n keypoints: every 4-subset, in order, up to MAX_SUBSETS; else MAX_SUBSETS drawn from
    SUBSET_SEED (each a sorted draw without replacement)."""
    if comb(n, MINIMAL) <= MAX_SUBSETS:
        return np.array(list(combinations(range(n), MINIMAL)), dtype=int).reshape(-1, MINIMAL)
    rng = np.random.default_rng(SUBSET_SEED)
    return np.sort(np.stack([rng.choice(n, MINIMAL, replace=False) for _ in range(MAX_SUBSETS)]), axis=1)


def _refit(obj, img, cov_inv, K, inl: np.ndarray, gate: float, rounds: int = 3):
    """SQPnP (without LM, which costs 5 times more: the chosen set's pose is refined once, robust_pnp) on the
    inliers inl (n,) bool, their set re-gated after each fit, until it stops changing (at most rounds fits).
    Returns (pose, inliers it was fitted to, its MSAC cost) or None."""
    pose, d2 = None, None
    for _ in range(rounds):
        if inl.sum() < MINIMAL:
            return None
        pose = keypoint_pose(obj[inl], img[inl], K, refine=False)
        if pose is None:
            return None
        d2 = whitened_d2(pose[0][None], pose[1][None], obj, img, cov_inv, K)[0]
        new = d2 < gate
        if (new == inl).all():
            break
        if new.sum() < MINIMAL:
            break  # the fit's set stays the one it was fitted to
        inl = new
    return pose, inl, float(np.minimum(d2, gate).sum())


def _best_refit(obj, img, cov_inv, K, d2: np.ndarray, gate: float):
    """The refit (_refit) of the consistent sets (d2 < gate, 4 keypoints or more) of the minimal sets' poses
    (d2 (H, n)) of the LOCAL_REFITS lowest MSAC costs, distinct sets only: the one that passes the most keypoints,
    then the lowest cost. A minimal set's pose is noisy: the set of the lowest cost may miss a keypoint the refit
    of a larger set keeps (a box's corner at d^2 24.5 after a refit on 5 corners, 2.4 on the 6 consistent ones).
    None where no set refits."""
    inl = d2 < gate
    seen, fits = set(), []
    for h in np.argsort(np.minimum(d2, gate).sum(axis=1), kind="stable"):  # MSAC; ties: the first set
        if inl[h].sum() < MINIMAL or inl[h].tobytes() in seen:
            continue
        seen.add(inl[h].tobytes())
        fit = _refit(obj, img, cov_inv, K, inl[h], gate)
        if fit is not None:
            fits.append(fit)
        if len(seen) == LOCAL_REFITS:
            break
    return min(fits, key=lambda f: (-int(f[1].sum()), f[2])) if fits else None


def robust_pnp(z_px: np.ndarray, cov_px: np.ndarray, keypoints_T_m: np.ndarray, camera: PinholeCamera,
               gate: float, min_keypoints: int = 4) -> RobustPose | None:
    """The pose of the named keypoints z_px (K, 2) (NaN where missing) with covariance cov_px (K, 2, 2) px^2 and
    the keypoints it keeps (module docstring): the all-keypoint pose where it passes the gate (chi-square per
    keypoint, 2 dof) at every keypoint, else the refit of the best minimal set's inliers. None with fewer than
    min_keypoints (at least 4) measured keypoints or when PnP fails. keypoints_T_m (K, 3) in T."""
    ok = np.isfinite(z_px).all(-1)
    if ok.sum() < max(min_keypoints, MINIMAL):
        return None
    obj, img, K = keypoints_T_m[ok].astype(float), z_px[ok].astype(float), camera.K
    pose = keypoint_pose(obj, img, K)
    x_all = None if pose is None else RobustPose(pose_state(*pose, camera), ok.copy(), False)
    cov_inv = np.linalg.inv(np.asarray(cov_px, float)[ok])  # a keypoint without a covariance passes no gate
    n_all = 0 if pose is None else int((whitened_d2(pose[0][None], pose[1][None], obj, img, cov_inv, K) < gate).sum())
    if n_all == len(obj) or len(obj) <= MINIMAL:
        return x_all
    hyp = [keypoint_pose(obj[s], img[s], K, minimal=True, refine=False) for s in minimal_sets(len(obj))]
    hyp = [h for h in hyp if h is not None]
    if not hyp:
        return x_all
    d2 = whitened_d2(np.stack([h[0] for h in hyp]), np.stack([h[1] for h in hyp]), obj, img, cov_inv, K)
    fit = _best_refit(obj, img, cov_inv, K, d2, gate)
    m = 0 if fit is None else int(fit[1].sum())
    sets = {row.tobytes() for row in d2 < gate if row.sum() >= MINIMAL}  # the minimal sets' consistent sets
    if m <= max(n_all, min_keypoints - 1) or (m == MINIMAL and len(sets) > 1):
        return x_all
    pose = keypoint_pose(obj[fit[1]], img[fit[1]], K)
    if pose is None:
        return x_all
    inliers = np.zeros(len(z_px), bool)
    inliers[np.flatnonzero(ok)[fit[1]]] = True
    return RobustPose(pose_state(*pose, camera), inliers, True)
