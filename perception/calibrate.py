"""Calibration of the per-corner pixel covariance on held-out data (the filter uses it as R).

Plain numpy. For correctly named visible corners with errors e (N, 2) px and predicted covariances C (N, 2, 2)
px^2, e^T C^-1 e follows a chi-square with 2 degrees of freedom when C is honest: its mean is 2 (the issue's
band: [1.6, 2.6]). One scalar s fitted on held-out data, C -> s C, brings the mean to 2; it ships with the weights.

Here: the fits alone (arrays in, numbers out). The job that runs the detector over held-out frames, matches its
corners to the labels and writes the fits into the weights is the pipeline pipelines/detector/calibrate.py
(`envisat calibrate`).
"""

from __future__ import annotations

import numpy as np


def nees_px(err_px: np.ndarray, cov_px: np.ndarray) -> np.ndarray:
    """e^T C^-1 e per corner: err (N, 2) px, cov (N, 2, 2) px^2 -> (N,)."""
    err = np.asarray(err_px, dtype=np.float64)
    return np.einsum("ni,ni->n", err, np.linalg.solve(np.asarray(cov_px, dtype=np.float64), err[..., None])[..., 0])


def fit_cov_scale(err_px: np.ndarray, cov_px: np.ndarray) -> float:
    """The scalar s with mean(e^T (s C)^-1 e) = 2 (the chi-square-2 mean)."""
    v = nees_px(err_px, cov_px)
    if len(v) == 0:
        raise ValueError("no corners to calibrate on")
    return float(np.mean(v) / 2.0)


def fit_floor(err_px: np.ndarray, cov_px: np.ndarray) -> float:
    """The variance f >= 0, px^2, with mean(e^T (C + f I)^-1 e) = 2: a floor added to both axes of covariances
    that leave out an error of their own (the sub-pixel refinement's line fits see the noise, not the model's
    misfit); 0 when the covariances already cover the errors. Bisection: the mean falls as f grows."""
    err, cov = np.asarray(err_px, float), np.asarray(cov_px, float)
    if len(err) == 0:
        raise ValueError("no corners to calibrate on")
    mean = lambda f: float(np.mean(nees_px(err, cov + f * np.eye(2))))  # noqa: E731
    if mean(0.0) <= 2.0:
        return 0.0
    lo, hi = 0.0, 1.0
    while mean(hi) > 2.0:
        lo, hi = hi, hi * 4.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mean(mid) > 2.0 else (lo, mid)
    return 0.5 * (lo + hi)


def calibration_by_group(err_px: np.ndarray, cov_px: np.ndarray, group: np.ndarray) -> dict[str, dict]:
    """Mean e^T C^-1 e and count per group label (e.g. corruption level); 'all' over everything."""
    v = nees_px(err_px, cov_px)
    group = np.asarray(group).astype(str)
    out = {"all": {"mean_nees": float(np.mean(v)) if len(v) else float("nan"), "count": int(len(v))}}
    for g in sorted(set(group.tolist())):
        sel = group == g
        out[g] = {"mean_nees": float(np.mean(v[sel])), "count": int(sel.sum())}
    return out
