"""The pixel covariance of another target's keypoint detector (the filter's R), fitted on held-out frames: plain
numpy. The job that runs the detector over labelled frames and writes the fit into the weights is
pipelines/detector/calibrate_target.py (`envisat calibrate --target`).

The model: per keypoint k an isotropic covariance sigma_k^2 I (px^2), the same for every frame. The keypoint
network has no covariance head (ENVISAT's corner network predicts a 2x2 per corner, scaled on held-out data);
the simplest honest model for it is one sigma per keypoint, fitted robustly from the errors e = detected - label
of its correct detections (usable, called visible, within the match radius of their label under the frame's
best twin naming): sigma_k = median(|e_x|, |e_y|) / Phi^-1(0.75), both axes pooled about zero (not about their
median: a bias is part of the error the filter sees), Phi^-1(0.75) = 0.6745 the median of |x| for x ~ N(0, 1).
The median keeps the rare far outlier inside the match radius from inflating sigma for every frame; whether the
errors are Gaussian enough for a filter shows in the check: e^T C^-1 e = |e|^2 / sigma_k^2 over the same
detections, whose mean is 2 (chi-square, 2 dof) and whose share within the chi-square's 95 % gate is 0.95 when
the model holds (heavier tails: a mean above 2; the truncation at the match radius pulls it the other way).

The median's price is its spread: over m Gaussian components the estimate's standard error is
sigma sqrt(MAD_VARIANCE / m), MAD_VARIANCE = 1 / (4 f(q)^2 q^2) = 1.3605 (q = 0.6745 the median of |x|, f its
half-normal density 2 phi(q)), so 18 % of sigma from the 2 x 20 components of 20 detections, 5 % from 300. A
sigma too small by d inflates its keypoint's e^T C^-1 e by 1 / (1 - d)^2, so a check on few detections per
keypoint reads above 2 even for Gaussian errors (about 2 (1 + 3 MAD_VARIANCE / m)). A keypoint with fewer than
MIN_CORRECT correct detections is not calibrated (NaN).
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtri  # the normal's quantile without scipy.stats (0.7 s at a verb's start)

from envisat_pose.gates import chi2_gate

GAUSS_ABS_MEDIAN = float(ndtri(0.75))  # median |x| of x ~ N(0, 1): 0.6745
# m x the variance of robust_sigma / sigma over m Gaussian components (module doc): 1.3605
_PDF_AT_MEDIAN = float(np.exp(-GAUSS_ABS_MEDIAN ** 2 / 2.0) / np.sqrt(2.0 * np.pi))  # N(0, 1)'s density there
MAD_VARIANCE = float(1.0 / (4.0 * (2.0 * _PDF_AT_MEDIAN) ** 2 * GAUSS_ABS_MEDIAN ** 2))
MIN_CORRECT = 20  # correct detections a keypoint needs to be calibrated (sigma's standard error 18 %)
CHECK_PROB = 0.95  # the gate whose share the check reports


def robust_sigma(err_px: np.ndarray) -> float:
    """The per-axis Gaussian sigma, px, of errors err_px (M, 2) about zero: median(|components|) / 0.6745 (NaN
    without errors)."""
    e = np.abs(np.asarray(err_px, float).reshape(-1))
    e = e[np.isfinite(e)]
    return float(np.median(e) / GAUSS_ABS_MEDIAN) if len(e) else float("nan")


def fit_keypoint_sigma(err_px: np.ndarray, min_count: int = MIN_CORRECT) -> tuple[np.ndarray, np.ndarray]:
    """(sigma (K,) px, count (K,)) from err_px (N, K, 2), NaN where the detection is not a correct one: each
    keypoint's robust_sigma over its correct detections, NaN where it has fewer than min_count."""
    err = np.asarray(err_px, float)
    ok = np.all(np.isfinite(err), axis=-1)
    count = ok.sum(axis=0)
    sigma = np.array([robust_sigma(err[ok[:, k], k]) if count[k] >= min_count else np.nan
                      for k in range(err.shape[1])])
    return sigma, count.astype(np.int64)


def sigma_standard_error(sigma_px: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The standard error of fit_keypoint_sigma's sigma (K,) from count (K,) detections (2 components each):
    sigma sqrt(MAD_VARIANCE / (2 count)) (NaN where sigma is)."""
    return np.asarray(sigma_px, float) * np.sqrt(MAD_VARIANCE / (2.0 * np.maximum(np.asarray(count, float), 1.0)))


def isotropic_cov(sigma_px: np.ndarray, frames: int) -> np.ndarray:
    """(frames, K, 2, 2) px^2: sigma_k^2 I for every frame (NaN where sigma_k is NaN)."""
    s2 = np.asarray(sigma_px, float) ** 2
    cov = s2[:, None, None] * np.eye(2)[None]
    return np.broadcast_to(cov, (int(frames),) + cov.shape).copy()


def isotropic_nees(err_px: np.ndarray, sigma_px: np.ndarray) -> np.ndarray:
    """e^T C^-1 e = |e|^2 / sigma_k^2 per detection: err_px (N, K, 2), sigma_px (K,) -> (N, K), NaN where either
    is NaN."""
    e = np.asarray(err_px, float)
    return np.sum(e * e, axis=-1) / np.asarray(sigma_px, float)[None] ** 2


def nees_check(err_px: np.ndarray, sigma_px: np.ndarray, names, prob: float = CHECK_PROB) -> dict:
    """The check of a fit on detections err_px (N, K, 2) (NaN: not a correct one): over every detection with a
    finite error and sigma ('all') and per keypoint name, the mean of e^T C^-1 e (2 when honest), the share within
    the chi-square gate of probability prob at 2 dof (prob when honest) and the count."""
    v = isotropic_nees(err_px, sigma_px)
    gate = chi2_gate(prob, 2)

    def stats(x: np.ndarray) -> dict:
        x = x[np.isfinite(x)]
        if len(x) == 0:
            return {"mean_nees": float("nan"), "within_gate": float("nan"), "count": 0}
        return {"mean_nees": float(np.mean(x)), "within_gate": float(np.mean(x <= gate)), "count": int(len(x))}

    return {"gate_prob": prob, "all": stats(v.ravel()),
            "per_keypoint": {str(n): stats(v[:, k]) for k, n in enumerate(names)}}


REJECT_GRID = np.arange(0.0, 30.01, 0.5)  # whitened radii |e| / sigma_k at which reject_curve tabulates its share


def reject_curve(err_px: np.ndarray, given: np.ndarray, usable: np.ndarray, sigma_px: np.ndarray) -> dict:
    """What a correct track's gate can reject: over the detections the tracker is given (given (N, K) bool: called
    visible, with a position and a calibrated sigma), the share whose whitened error |e| / sigma_k exceeds r, at
    each r of REJECT_GRID. err_px (N, K, 2): detected - label under the frame's best twin naming, correct or not;
    a detection of a keypoint that is not usable (hidden or out of frame) counts as beyond every radius. A
    tracker gating a corner at a chi-square bound g against sigma_k^2 x s (s >= 1: its inflation and scale; the
    prior's spread only widens it) rejects at most the share at r = sqrt(g s) of a correct track's corners.
    Returns {"r_sigma": grid, "share": shares, "given": count}; shares are NaN without detections."""
    e = np.asarray(err_px, float)
    sigma = np.asarray(sigma_px, float)[None]
    g = np.asarray(given, bool) & np.isfinite(sigma) & np.isfinite(e).all(-1)
    w = np.linalg.norm(e, axis=-1) / sigma
    w = np.where(np.asarray(usable, bool), w, np.inf)[g]
    share = np.array([float(np.mean(w > r)) if len(w) else float("nan") for r in REJECT_GRID])
    return {"r_sigma": [float(r) for r in REJECT_GRID], "share": [float(s) for s in share], "given": int(len(w))}


def reject_share(curve: dict, gate: float, scale: float = 1.0) -> float:
    """The share of a correct track's corners a chi-square gate `gate` per corner rejects at most, the detector's
    covariance taken at `scale` (reject_curve's dict; linear between its radii, its last share beyond them)."""
    r = np.sqrt(float(gate) * max(float(scale), 0.0))
    return float(np.interp(r, curve["r_sigma"], curve["share"]))
