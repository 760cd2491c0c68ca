"""The filter's measurement noise from the detector: its calibrated covariance taken to the error model's scale and
inflated for the errors' frame-to-frame correlation at the filter's own memory (docs/design.md, "The tracker").

The detector's error model (perception/errormodel.py, fitted by `envisat calibrate` on held-out sequences and stored
in the weights' metadata) says how its normalized errors correlate from frame to frame: white noise plus an AR(1)
part of share a and coefficient phi (per frame interval, from the time fit, or per angle the view turned, from the
rotation fit). A filter that averages its frames with memory lambda misses the factor
tau(lambda) = 1 + 2 a phi lambda / (1 - phi lambda) (errormodel.memory_inflation), which R takes here. The filter's
memory is read from its own last update (`filter_memory`); the cold start's window of n frames uses the exponential
average of the same effective length (`window_memory`).
"""

from __future__ import annotations

import numpy as np

from envisat_pose.perception.errormodel import ErrorModel, memory_inflation, phi_at, phi_at_rotation
from envisat_pose.state import MRP, POS

CORRELATION_MODELS = ("filter_memory", "long_memory", "white")
CORRELATION_IN = ("slower", "rotation", "time")
POSE = np.r_[POS, MRP]  # the directions each frame measures: position and attitude


def detector_error_model(detector):
    """The detector's ErrorModel (`envisat calibrate`), or the white default when it has none."""

    em = getattr(detector, "error_model", None)
    return em if isinstance(em, ErrorModel) else ErrorModel()


def sequence_cov_factor(em, detector) -> float:
    """em.cov_scale / the detector's cov_scale: the factor that takes the detector's covariance (calibrated on
    random views) to the scale the error model measured on held-out sequences; 1 without a measured model."""
    det_scale = getattr(getattr(detector, "cfg", None), "cov_scale", None)
    if not em.n_frames or not det_scale or not em.cov_scale > 0:
        return 1.0
    return float(em.cov_scale / det_scale)


def ar1_at(em, kind: str, dt_s: float, rate_rad_s: float | None = None) -> tuple[float, float]:
    """(a, phi): the AR(1) share and per-frame coefficient of the error model em's correlated part between two
    frames dt_s apart. kind "time": the time fit (phi_at); "rotation": with the view turning at rate_rad_s and a
    rotation fit in em, that of the angle turned in dt_s (phi_at_rotation), else the time fit; "slower": of the
    two, the one whose correlation lasts longer (the larger long-memory inflation a phi / (1 - phi)): the errors
    persist while the view has not turned (a slow tumble) and while the frames are close in time (a fast one)."""

    by_time = (em.ar1_share, phi_at(em.ar1_phi, em.corr_time_s, dt_s))
    if kind == "time" or rate_rad_s is None or em.corr_angle_rad <= 0.0:
        return by_time
    by_angle = (em.angle_share, phi_at_rotation(em.corr_angle_rad, rate_rad_s, dt_s))
    if kind == "rotation":
        return by_angle
    lasting = lambda ap: ap[0] * ap[1] / max(1.0 - ap[1], 1e-12)  # noqa: E731
    return by_angle if lasting(by_angle) > lasting(by_time) else by_time


def correlation_inflation(em, model: str, lam: float, dt_s: float, rate_rad_s: float | None = None,
                          kind: str = "rotation") -> float:
    """The factor on the detector's covariance for the errors' frame-to-frame correlation (module doc): the error
    model em's white + AR(1) errors at frame interval dt_s (s) for a filter of memory lam in [0, 1], the AR(1)
    part's coefficient as ar1_at(em, kind, dt_s, rate_rad_s) gives it (rate_rad_s: the view's rotation rate)."""

    if model == "white":
        return 1.0
    a, phi = ar1_at(em, kind, dt_s, rate_rad_s)
    if a <= 0.0:
        return 1.0
    return max(memory_inflation(a, phi, 1.0 if model == "long_memory" else lam), 1.0)


def evidence_weight(em, model: str, lam: float, dt_s: float, rate_rad_s: float | None = None,
                    kind: str = "rotation") -> float:
    """The weight of one frame's cost in a log-likelihood summed over many frames: tau(lam) / tau(1). The cost's
    NIS reads the innovations against R x tau(lam) (correlation_inflation at the filter's memory lam), but a sum
    over all the frames holds the errors' whole correlation, tau(1) (the long-memory inflation), so a frame counts
    for tau(lam) / tau(1) of an independent one. 1 for white errors or where tau(1) is not finite."""
    if model == "white":
        return 1.0
    long = correlation_inflation(em, "long_memory", 1.0, dt_s, rate_rad_s, kind)
    if not np.isfinite(long) or long <= 0.0:
        return 1.0
    return float(min(1.0, correlation_inflation(em, model, lam, dt_s, rate_rad_s, kind) / long))


def window_memory(frames: int) -> float:
    """(n - 1) / (n + 1): the memory of the exponential average as long (in effective frames) as an equal-weight
    window of n frames, the cold start's before the filter's first update."""
    return (frames - 1.0) / (frames + 1.0)


def filter_memory(P_prior: np.ndarray, P_post: np.ndarray) -> float | None:
    """lambda = (det P_post / det P_prior)^(1/6) over position and attitude: the share of its past a filter keeps
    after an update (1 - K in one dimension); None where either is not positive definite."""
    try:
        la = np.linalg.cholesky(P_prior[np.ix_(POSE, POSE)])
        lb = np.linalg.cholesky(P_post[np.ix_(POSE, POSE)])
    except np.linalg.LinAlgError:
        return None
    log_ratio = 2.0 * (np.sum(np.log(np.diag(lb))) - np.sum(np.log(np.diag(la))))  # log det P_post / det P_prior
    return float(np.clip(np.exp(log_ratio / len(POSE)), 0.0, 1.0)) if np.isfinite(log_ratio) else None


def detection_measurement(fd, inflation: float, scale: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The filter's view of one FrameDetection: named corners (8, 2) (NaN where not found), their covariance
    (8, 2, 2) x inflation, and the probability of the half-turn naming. The detector's measured apparent scale
    (its corners sit scale x farther from their centroid than the labels) is undone about the centroid."""
    z = np.asarray(fd.corners_px, dtype=float)
    cov = np.asarray(fd.cov_px, dtype=float)
    ok = np.asarray(fd.visible, bool) & np.isfinite(z).all(-1) & np.isfinite(cov).all((-1, -2))
    z = np.where(ok[:, None], z, np.nan)
    if ok.sum() >= 2 and scale != 1.0:
        c = z[ok].mean(axis=0)
        z = np.where(ok[:, None], c + (z - c) / scale, np.nan)
    cov = np.where(ok[:, None, None], 0.5 * (cov + np.swapaxes(cov, -1, -2)) * inflation, np.nan)
    return z, cov, float(np.clip(np.nan_to_num(fd.alt_probability), 0.0, 1.0))


def nis_sum_dispersion(em, dt_s: float, frames: int, rate_rad_s: float | None = None,
                       kind: str = "rotation") -> float:
    """kappa >= 1: the factor by which the variance of a sum of `frames` frames' NIS exceeds the chi-square's,
    because the detector's errors correlate from frame to frame (the error model em: white + AR(1) of share a and
    coefficient phi, ar1_at(em, kind, dt_s, rate_rad_s)). For Gaussian errors the squares of two with
    correlation rho correlate by rho^2, so kappa = 1 + 2 sum_k (1 - k/n) (a phi^k)^2; the windowed sum is then
    taken as kappa x chi2(dof / kappa) (the same mean, kappa times the variance)."""
    a, phi = ar1_at(em, kind, dt_s, rate_rad_s)
    if a <= 0.0 or frames < 2:
        return 1.0
    k = np.arange(1, frames)
    return float(1.0 + 2.0 * np.sum((1.0 - k / frames) * (a * phi ** k) ** 2))


def scale_sigma(em, corrected: bool) -> float:
    """The relative range error a filter cannot average away: a corner pattern s times too large puts the target
    at range / s on every frame. The error model (held-out sequences) measured the detector's mean apparent scale
    bias_scale and how far one sequence's scale falls from it (bias_scale_sd: each sequence has its own views,
    light and camera). With the mean undone (`corrected`) what is left is a new run's own scale, bias_scale_sd;
    without it the mean's offset |s - 1| is added in quadrature. A model without a measured spread (older weights:
    bias_scale_sd 0) takes |s - 1| for it. 0 without a measured model."""
    if not em.n_frames:
        return 0.0
    offset, sd = abs(float(em.bias_scale) - 1.0), float(em.bias_scale_sd)
    if corrected:
        return sd if sd > 0.0 else offset
    return float(np.hypot(offset, sd))


def range_consider(mean: np.ndarray, cov: np.ndarray, sigma_rel: float) -> np.ndarray:
    """cov (..., 12, 12) plus the range error of an apparent-scale error of sigma_rel: (sigma_rel x range)^2 along
    the line of sight (a rank-one addition u u^T to the position block, u the unit line of sight of mean's
    position; unchanged where sigma_rel is 0). A scale error s common to every frame moves the estimated position
    by -(s - 1) x range along the line of sight whatever the filter averages, so its variance adds to the
    filter's (a consider parameter: reported, never fed back into the gain, where it would make the filter follow
    each frame's range instead of averaging them)."""
    if sigma_rel <= 0.0:
        return cov
    pos = mean[..., POS]
    r = np.linalg.norm(pos, axis=-1, keepdims=True)
    u = pos / np.maximum(r, 1e-9)
    add = (sigma_rel * r[..., 0]) ** 2
    out = np.array(cov, dtype=float)
    out[..., POS, POS] += add[..., None, None] * u[..., :, None] * u[..., None, :]
    return out
