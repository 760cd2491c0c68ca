"""The detector's error model for a filter: covariance scale, frame-to-frame correlation and
residual bias of the errors of correctly named corners, measured on held-out sequences. Plain numpy.

Shapes: T frames of one sequence, K keypoints (ENVISAT's 8 corners A-H, or another target's keypoints in its
weights' order). err_px (T, K, 2) = detected - label, px, NaN where the keypoint
was not found and named right; sigma_px (T, K, 2) the detector's predicted standard deviation per image axis
(sqrt of the covariance's diagonal), px.

Frame-to-frame correlation. The lag-k autocorrelation of a series x_t with gaps is estimated from the pairs
(t, t + k) both present: r_k = [sum x_t x_{t+k} / n_k] / [sum x_t^2 / n_0], x demeaned by the pooled mean of
its corner and axis over all sequences (that mean is the residual bias, reported on its own; a bias that
differs per sequence stays in the correlation, as it does for a filter). Pooled over corners, axes and
sequences by adding the sums, on errors normalized by the predicted sigma (z = e / sigma), so frames of
different error size weigh as the filter weighs them. AR(1): rho = r_1 (Yule-Walker), correlation time
-dt / ln(rho).

Variance inflation for a filter that treats the errors as white. For stationary errors of variance s^2 and
autocorrelation rho_k, the mean of n consecutive errors has variance
    (s^2 / n) [1 + 2 sum_{k=1}^{n-1} (1 - k/n) rho_k]  ->  (s^2 / n) tau,  tau = 1 + 2 sum_{k>=1} rho_k,
as n grows. A filter that takes the errors as white credits n frames with the information n / s^2 about what
they share (the slowly moving state); they carry n / (s^2 tau). Using R = tau s^2 makes the two agree. For
AR(1), rho_k = rho^k, so tau = 1 + 2 rho / (1 - rho) = (1 + rho) / (1 - rho). This is the long-memory limit:
for a filter whose memory is short against the correlation time it is conservative (memory_inflation
gives the factor for a filter of a given memory, the one the tracker uses).

The detector's errors are not AR(1) (measured on held-out sequences: r_1 ~ 0.5 but r_2 ~ r_1, then a slow
decay): they are a white part plus a slowly varying part. The model fitted is that sum, white noise of variance
share 1 - a plus an AR(1) of share a and coefficient phi: rho_k = a phi^k for k >= 1 (a = 1: pure AR(1)), fitted
by least squares on log r_k over the leading positive lags, weighted by their pair counts. Its tau is
1 + 2 a phi / (1 - phi), which is (1 + rho) / (1 - rho) when a = 1; the correlation time is -dt / ln(phi).
`acf_inflation` sums the measured r_k as a check.

Correlation in the view's rotation. The errors come from what the detector sees, and the view changes as the
target turns: measured on held-out sequences, the lag-k correlation falls about twice as fast at 5 deg/s as at
2.7 deg/s. With the labels' R_cam_from_target (T, 3, 3) per frame, the pairs (t, t + k) (k = 1..angle_max_lag)
are binned by the angle of the view's rotation between them, theta = angle(R_{t+k} R_t^T), and the same
pooled sums give r(theta) per bin; rho(theta) = a_theta exp(-theta / theta_c) is fitted to every bin (at its
pairs' mean angle) by least squares on r itself, weighted by the pair counts (fit_exponential_decay: on log r
the bins where r is near zero and noisy would pull the fit). A
filter that knows the target's rate |w| (rad/s) then takes phi = exp(-|w| dt / theta_c) per frame interval
(phi_at_rotation).

Bias. Per frame with at least 3 corners named right and no found usable corner named wrong, the apparent
scale: the least-squares s with (p - p_bar) ~ s (q - q_bar) over its right corners (p detected, q labels,
bars their centroids), s = sum (p - p_bar).(q - q_bar) / sum |q - q_bar|^2. The radial error of a right corner:
e . u, u the unit vector from the detected corners' centroid to the detected corner (positive outward).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields

import numpy as np

from envisat_pose.geometry import CORNER_NAMES


@dataclass(frozen=True)
class ErrorModel:
    """What a filter needs of the detector's pixel errors (shipped in the weights' metadata as `error_model`).

    cov_scale: the factor s on the network's covariance with mean e^T (s C)^-1 e = 2 on these data.
    rho_lag1: lag-1 autocorrelation of the normalized errors from frame to frame (pooled).
    ar1_share, ar1_phi: the fitted model rho_k = ar1_share * ar1_phi^k (k >= 1): white noise plus an AR(1) part
    of that variance share and coefficient (module doc).
    inflation: tau = 1 + 2 ar1_share ar1_phi / (1 - ar1_phi), the factor on R for a filter that treats the
    errors as white ((1 + rho) / (1 - rho) for a pure AR(1)).
    corr_time_s: -dt / ln(ar1_phi), s, of the AR(1) part (0 when there is none).
    angle_share, corr_angle_rad: the same model in the view's rotation, rho(theta) = angle_share
    exp(-theta / corr_angle_rad) for two frames whose view turned by theta rad (module doc); 0, 0 when it was not
    measured (sequences without their rotations).
    bias_scale: mean apparent scale of the detected corners about their centroid (1: none).
    bias_radial_px: mean signed radial error, px (positive outward).
    bias_scale_sd: how far a new sequence's mean apparent scale falls from bias_scale (each sequence has its own
    views, light and camera): the standard deviation of the sequences' means about theirs, times sqrt(1 + 1 / n) for the
    n sequences' mean itself (0: not measured, fewer than two sequences).
    n_frames: frames the model was measured on. source: what it was measured on (datasets, ROI mode).
    """

    cov_scale: float = 1.0
    rho_lag1: float = 0.0
    ar1_share: float = 0.0
    ar1_phi: float = 0.0
    inflation: float = 1.0
    corr_time_s: float = 0.0
    angle_share: float = 0.0
    corr_angle_rad: float = 0.0
    bias_scale: float = 1.0
    bias_radial_px: float = 0.0
    bias_scale_sd: float = 0.0
    n_frames: int = 0
    source: str = ""

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @staticmethod
    def from_json(text: str | None) -> "ErrorModel":
        """From the metadata's JSON (unknown keys ignored, missing ones at their defaults); the defaults for None."""
        if not text:
            return ErrorModel()
        raw = json.loads(text)
        names = {f.name: f.type for f in fields(ErrorModel)}
        kw = {k: v for k, v in raw.items() if k in names}
        for k in ("cov_scale", "rho_lag1", "ar1_share", "ar1_phi", "inflation", "corr_time_s", "angle_share",
                  "corr_angle_rad", "bias_scale", "bias_radial_px", "bias_scale_sd"):
            if k in kw:
                kw[k] = float(kw[k])
        if "n_frames" in kw:
            kw["n_frames"] = int(kw["n_frames"])
        if "source" in kw:
            kw["source"] = str(kw["source"])
        return ErrorModel(**kw)


def lag_sums(x: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """Sums of x_t x_{t+k} over the pairs both present and the pair counts, k = 0..max_lag, along axis 0 of x
    (T, ...) (NaN: absent), summed over the other axes: (max_lag + 1,), (max_lag + 1,)."""
    x = np.asarray(x, dtype=np.float64)
    num, cnt = np.zeros(max_lag + 1), np.zeros(max_lag + 1)
    for k in range(min(max_lag, len(x) - 1) + 1):
        a, b = x[:len(x) - k], x[k:]
        ok = np.isfinite(a) & np.isfinite(b)
        num[k] = float(np.sum(np.where(ok, a * b, 0.0)))
        cnt[k] = float(ok.sum())
    return num, cnt


def autocorrelation(num: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """r_k = (num_k / cnt_k) / (num_0 / cnt_0) from lag_sums (NaN where a lag has no pair)."""
    num, cnt = np.asarray(num, float), np.asarray(cnt, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = np.where(cnt > 0, num / np.maximum(cnt, 1), np.nan)
        return cov / cov[0]


def ar1_inflation(rho: float) -> float:
    """(1 + rho) / (1 - rho): the variance inflation of AR(1) errors treated as white (module doc)."""
    return float((1.0 + rho) / (1.0 - rho))


def acf_inflation(r: np.ndarray) -> float:
    """1 + 2 sum_{k>=1} r_k over the leading lags while r_k > 0 (the measured autocorrelation's tau)."""
    total = 1.0
    for v in np.asarray(r, float)[1:]:
        if not np.isfinite(v) or v <= 0:
            break
        total += 2.0 * v
    return float(total)


def fit_log_linear(x: np.ndarray, r: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """(a, b) of r = a exp(b x) by least squares on log r weighted by w: x, r (> 0), w (n,), n >= 2."""
    x, r, w = (np.asarray(v, float) for v in (x, r, w))
    A = np.stack([np.ones(len(x)), x], axis=1) * np.sqrt(w)[:, None]
    coef = np.linalg.lstsq(A, np.log(r) * np.sqrt(w), rcond=None)[0]
    return float(np.exp(coef[0])), float(coef[1])


def fit_white_plus_ar1(r: np.ndarray, pairs: np.ndarray) -> tuple[float, float]:
    """(a, phi) of rho_k = a phi^k (k >= 1) fitted to the measured r_k (max_lag + 1,) by least squares on
    log r_k over the leading lags while r_k > 0, weighted by the pair counts (max_lag + 1,). One positive lag:
    a pure AR(1), (1, r_1); none: (0, 0). phi is kept in [0, 1) and a in [0, 1]."""
    r, w = np.asarray(r, float), np.asarray(pairs, float)
    n_pos = 0
    for j in range(1, len(r)):
        if not np.isfinite(r[j]) or r[j] <= 0:
            break
        n_pos += 1
    if n_pos == 0:
        return 0.0, 0.0
    if n_pos == 1:
        return 1.0, float(min(r[1], 1.0 - 1e-9))
    lags = np.arange(len(r), dtype=float)
    a, b = fit_log_linear(lags[1:n_pos + 1], r[1:n_pos + 1], w[1:n_pos + 1])
    return float(min(a, 1.0)), min(float(np.exp(b)), 1.0 - 1e-9)


def fit_exponential_decay(x: np.ndarray, r: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """(a, c) of r = a exp(-x / c), a >= 0, by weighted least squares on r over the points with w > 0 and r finite:
    for each c of a log grid (ratio 1.002 from x's smallest positive spacing / 4 to 100 x its largest value) a is
    the closed form sum w r f / sum w f^2, f = exp(-x / c); the c of least residual wins. (0, 0) with fewer than 2
    points or no positive a."""
    x, r, w = (np.asarray(v, float) for v in (x, r, w))
    ok = (w > 0) & np.isfinite(r) & np.isfinite(x)
    x, r, w = x[ok], r[ok], w[ok]
    if len(x) < 2 or not np.any(x > 0):
        return 0.0, 0.0
    lo, hi = np.min(np.diff(np.unique(np.r_[0.0, x]))) / 4.0, 100.0 * np.max(x)
    c = np.exp(np.arange(np.log(lo), np.log(hi), np.log(1.002)))  # (G,)
    f = np.exp(-x[None] / c[:, None])  # (G, n)
    a = np.maximum((f * (w * r)).sum(1) / (f * f * w).sum(1), 0.0)
    cost = ((a[:, None] * f - r) ** 2 * w).sum(1)
    j = int(np.argmin(cost))
    return (float(a[j]), float(c[j])) if a[j] > 0 else (0.0, 0.0)


def rotation_angles(R: np.ndarray, k: int) -> np.ndarray:
    """The angle (rad) the view turned between frames t and t + k: of R_{t+k} R_t^T, for R (T, 3, 3)
    R_cam_from_target; (T - k,)."""
    R = np.asarray(R, float)
    M = np.einsum("tij,tkj->tik", R[k:], R[:len(R) - k])
    return np.arccos(np.clip((np.trace(M, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))


def angle_sums(x: np.ndarray, R: np.ndarray, max_lag: int, bin_rad: float, max_rad: float):
    """Sums of x_t x_{t+k} and pair counts by the view's rotation between the two frames, for lags 1..max_lag:
    x (T, ...) (NaN: absent), R (T, 3, 3) R_cam_from_target; bins [j bin_rad, (j + 1) bin_rad) below max_rad.
    Returns (num (B,), cnt (B,), angle (B,)): angle the sum of the pairs' angles (rad, each counted as often as
    cnt counts it; angle / cnt is a bin's mean angle); the lag-0 sums are lag_sums'."""
    x = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
    n_bins = int(np.ceil(max_rad / bin_rad))
    num, cnt, ang = np.zeros(n_bins), np.zeros(n_bins), np.zeros(n_bins)
    for k in range(1, min(max_lag, len(x) - 1) + 1):
        theta = rotation_angles(R, k)
        b = np.floor(theta / bin_rad).astype(int)
        a, c = x[:len(x) - k], x[k:]
        ok = np.isfinite(a) & np.isfinite(c)
        keep = b < n_bins
        n_ok = ok.sum(axis=1).astype(float)
        np.add.at(num, b[keep], np.sum(np.where(ok, a * c, 0.0), axis=1)[keep])
        np.add.at(cnt, b[keep], n_ok[keep])
        np.add.at(ang, b[keep], (theta * n_ok)[keep])
    return num, cnt, ang


def model_inflation(a: float, phi: float) -> float:
    """tau = 1 + 2 a phi / (1 - phi) of rho_k = a phi^k (module doc)."""
    return float(1.0 + 2.0 * a * phi / (1.0 - phi))


def memory_inflation(a: float, phi: float, lam: float) -> float:
    """tau(lambda) = 1 + 2 a phi lambda / (1 - phi lambda): the inflation of R for a filter with memory lambda.

    A filter whose estimate is (near enough) an exponentially weighted average of its frames, weight
    K lambda^j on the frame j steps back (lambda = 1 - K), holds the variance
    K^2 s^2 sum_{i,j} lambda^(i+j) rho_|i-j| = s^2 K / (2 - K) [1 + 2 sum_{k>=1} rho_k lambda^k] of errors with
    autocorrelation rho_k; the bracket is the factor a white-noise filter misses. For rho_k = a phi^k it sums to
    1 + 2 a phi lambda / (1 - phi lambda): 1 for lambda = 0 (a filter that keeps nothing of the past), the
    long-memory tau (model_inflation) as lambda -> 1. a, phi per frame interval; lambda in [0, 1]."""
    x = float(phi) * float(np.clip(lam, 0.0, 1.0))
    return float(1.0 + 2.0 * a * x / (1.0 - x)) if x < 1.0 else float("inf")


def phi_at(phi: float, corr_time_s: float, dt_s: float) -> float:
    """The AR(1) coefficient at another frame interval dt_s: exp(-dt / corr_time) (0 without a correlation time;
    phi itself when dt is not positive)."""
    if corr_time_s <= 0.0:
        return 0.0
    if not dt_s > 0.0:
        return float(phi)
    return float(np.exp(-dt_s / corr_time_s))


def phi_at_rotation(corr_angle_rad: float, rate_rad_s: float, dt_s: float) -> float:
    """The correlation of the errors of two frames dt_s apart while the view turns at rate_rad_s (rad/s), per
    unit share: exp(-|rate| dt / corr_angle) (0 without a correlation angle)."""
    if corr_angle_rad <= 0.0:
        return 0.0
    return float(np.exp(-abs(rate_rad_s) * max(dt_s, 0.0) / corr_angle_rad))


def correlation_time(rho: float, dt_s: float) -> float:
    """-dt / ln(rho) for 0 < rho < 1, s; 0 otherwise."""
    return float(-dt_s / np.log(rho)) if 0.0 < rho < 1.0 else 0.0


def apparent_scale(pred_px: np.ndarray, true_px: np.ndarray, right: np.ndarray, wrong: np.ndarray) -> np.ndarray:
    """Per frame the least-squares scale of the right corners about their centroid against the labels (module
    doc): pred_px, true_px (N, K, 2); right (N, K) bool corners named right; wrong (N, K) bool found usable
    corners named wrong. (N,), NaN for frames with fewer than 3 right corners or any wrong one."""
    p, q = np.asarray(pred_px, float), np.asarray(true_px, float)
    right = np.asarray(right, bool)
    n = right.sum(axis=1)
    w = right[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        pc = np.sum(np.where(w, p, 0.0), axis=1) / n[:, None]
        qc = np.sum(np.where(w, q, 0.0), axis=1) / n[:, None]
        dp, dq = p - pc[:, None], q - qc[:, None]
        s = np.sum(np.where(right, np.sum(dp * dq, -1), 0.0), 1) / np.sum(np.where(right, np.sum(dq * dq, -1), 0.0), 1)
    ok = (n >= 3) & ~np.asarray(wrong, bool).any(axis=1)
    return np.where(ok, s, np.nan)


def radial_errors(pred_px: np.ndarray, true_px: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Signed radial error (N, K) px of the right corners about the centroid of the frame's right detected
    corners, positive outward; NaN elsewhere and in frames with fewer than 2 right corners."""
    p, q = np.asarray(pred_px, float), np.asarray(true_px, float)
    right = np.asarray(right, bool)
    n = right.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        pc = np.sum(np.where(right[..., None], p, 0.0), axis=1) / n[:, None]
        d = p - pc[:, None]
        u = d / np.linalg.norm(d, axis=-1, keepdims=True)
        r = np.sum((p - q) * u, axis=-1)
    return np.where(right & (n >= 2)[:, None], r, np.nan)


def mean_se(x: np.ndarray) -> tuple[float, float, int]:
    """(mean, standard error of the mean, count) of the finite values (NaN, NaN, 0 when none)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan"), 0
    se = float(np.std(x, ddof=1) / np.sqrt(len(x))) if len(x) > 1 else float("nan")
    return float(np.mean(x)), se, int(len(x))


SCALE_MIN_FRAMES = 10  # a sequence's mean apparent scale counts in the spread between sequences from these frames


def scale_spread(scales: list[np.ndarray], min_frames: int = SCALE_MIN_FRAMES) -> tuple[float, list[float]]:
    """ErrorModel.bias_scale_sd from each sequence's per-frame apparent scales (NaN: none that frame), and the
    sequences' means (those with at least min_frames frames). (0, means) with fewer than two such sequences."""
    means = [float(np.mean(x[np.isfinite(x)])) for x in map(np.asarray, scales) if np.isfinite(x).sum() >= min_frames]
    if len(means) < 2:
        return 0.0, means
    return float(np.std(means, ddof=1) * np.sqrt(1.0 + 1.0 / len(means))), means


ANGLE_BIN_RAD = np.radians(4.0)  # the view-rotation bins of the correlation in angle
ANGLE_MAX_RAD = np.radians(90.0)
ANGLE_MAX_LAG = 40  # frames: under half a spin period of the fastest named tumble (72 s at 1 Hz)


def measure_error_model(sequences: list[dict], cov_scale: float, max_lag: int = 20, source: str = "",
                        names: tuple[str, ...] = CORNER_NAMES) -> tuple[ErrorModel, dict]:
    """The error model of held-out sequences. Each sequence: err_px (T, K, 2) (NaN where not named right),
    sigma_px (T, K, 2) the detector's predicted per-axis sigma at cov_scale 1, scale (T,) apparent scale per
    frame, radial_px (T, K), dt_s the frame interval, and optionally R_cam_from_target (T, 3, 3) (the labels'
    view: when every sequence has it, the correlation in the view's rotation is fitted too). cov_scale: the
    fitted scale (the NEES mean 2 on the same corners). names: the K keypoints' names (ENVISAT's corners A-H by
    default; another target's keypoints in the weights' order). Returns the ErrorModel and a record of every
    number (plain JSON data)."""
    if any(s["err_px"].shape[1:] != (len(names), 2) for s in sequences):
        raise ValueError(f"err_px of {len(names)} keypoints {names} expected, got shapes "
                         f"{sorted({s['err_px'].shape[1:] for s in sequences})}")
    e_all = np.concatenate([s["err_px"] for s in sequences])
    ok = np.isfinite(e_all)
    bias_px = np.where(ok, e_all, 0.0).sum(axis=0) / np.maximum(ok.sum(axis=0), 1)  # (K, 2), 0 where none
    by_angle = all("R_cam_from_target" in s for s in sequences)
    n_bins = int(np.ceil(ANGLE_MAX_RAD / ANGLE_BIN_RAD))
    pooled_z, pooled_px, per, pooled_angle, view_rate_deg_s = _pooled_sums(sequences, bias_px, cov_scale, max_lag,
                                                                           by_angle, n_bins, names)
    r_z = autocorrelation(*pooled_z)
    r_px = autocorrelation(*pooled_px)
    rho = float(r_z[1]) if len(r_z) > 1 and np.isfinite(r_z[1]) else 0.0
    a, phi = fit_white_plus_ar1(r_z, pooled_z[1])
    a_th, th_c, r_th, theta_mean = 0.0, 0.0, np.full(n_bins, np.nan), np.full(n_bins, np.nan)
    if by_angle:
        a_th, th_c, r_th, theta_mean = _angle_fit(pooled_angle, pooled_z)
    dts = {float(s["dt_s"]) for s in sequences}
    dt = dts.pop() if len(dts) == 1 else float("nan")
    scale_m, scale_se, scale_n, rho_scale = _scale_stats(sequences)
    scale_sd, scale_means = scale_spread([s["scale"] for s in sequences])
    rad_m, rad_se, rad_n = mean_se(np.concatenate([s["radial_px"].ravel() for s in sequences]))
    n_frames = int(sum(len(s["err_px"]) for s in sequences))
    model = ErrorModel(cov_scale=float(cov_scale), rho_lag1=rho, ar1_share=a, ar1_phi=phi,
                       inflation=model_inflation(a, phi), corr_time_s=correlation_time(phi, dt),
                       angle_share=a_th, corr_angle_rad=th_c, bias_scale=scale_m if scale_n else 1.0,
                       bias_radial_px=rad_m if rad_n else 0.0, bias_scale_sd=scale_sd, n_frames=n_frames, source=source)
    clean = lambda a: [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]  # noqa: E731
    record = {
        "error_model": json.loads(model.to_json()),
        "dt_s": dt, "max_lag": max_lag,
        "autocorr_normalized": clean(r_z), "autocorr_px": clean(r_px),
        "pairs_by_lag": clean(pooled_z[1]),
        "pure_ar1": {"rho": rho, "inflation": ar1_inflation(rho), "lag2_predicted": rho ** 2,
                     "lag2_measured": clean(r_z[2:3])[0] if len(r_z) > 2 else None},
        "fitted_autocorr": [1.0] + [a * phi ** k for k in range(1, max_lag + 1)],
        "acf_inflation": acf_inflation(r_z),
        "autocorr_by_angle": None if not by_angle else {
            "bin_deg": float(np.degrees(ANGLE_BIN_RAD)), "max_lag": ANGLE_MAX_LAG, "r": clean(r_th),
            "pairs": clean(pooled_angle[1]), "mean_deg": clean(np.degrees(theta_mean)),
            "fitted": clean(a_th * np.exp(-theta_mean / th_c) if th_c > 0 else np.zeros(n_bins)),
            "corr_angle_deg": float(np.degrees(th_c)), "view_rate_deg_s": view_rate_deg_s},
        "autocorr_lag1_by_corner": {c: {a: clean(autocorrelation(*per[c][a])[1:2])[0] for a in "xy"} for c in per},
        "bias_px_by_corner": {c: clean(bias_px[k]) for k, c in enumerate(names)},
        "scale": {"mean": scale_m, "se": scale_se, "frames": scale_n, "rho_lag1": rho_scale,
                  "by_sequence": scale_means, "between_sd": scale_sd,
                  "se_ar1": scale_se * np.sqrt(max(ar1_inflation(rho_scale), 0.0)) if abs(rho_scale) < 1 else None},
        "radial_px": {"mean": rad_m, "se": rad_se, "corners": rad_n},
        "corners": int(np.isfinite(e_all[..., 0]).sum()),
    }
    return model, record


def _pooled_sums(sequences: list[dict], bias_px: np.ndarray, cov_scale: float, max_lag: int, by_angle: bool,
                 n_bins: int, names: tuple[str, ...]) -> tuple:
    """The lag sums (lag_sums: counts, products) of the sequences' errors less the bias, pooled over them:
    normalized by the predicted sigma at cov_scale (pooled_z) and in px (pooled_px), per corner and axis in px
    (per), and, by_angle, by the view's rotation angle (angle_sums: n_bins bins) with each sequence's median
    view rate, deg/s. Returns (pooled_z, pooled_px, per, pooled_angle, view_rate_deg_s)."""
    pooled_z = [np.zeros(max_lag + 1), np.zeros(max_lag + 1)]
    pooled_px = [np.zeros(max_lag + 1), np.zeros(max_lag + 1)]
    per = {c: {a: [np.zeros(max_lag + 1), np.zeros(max_lag + 1)] for a in "xy"} for c in names}
    pooled_angle = [np.zeros(n_bins), np.zeros(n_bins), np.zeros(n_bins)]
    view_rate_deg_s = []
    for s in sequences:
        x = s["err_px"] - bias_px[None]
        z = x / (s["sigma_px"] * np.sqrt(cov_scale))
        if by_angle:
            for acc, v in zip(pooled_angle, angle_sums(z, s["R_cam_from_target"], ANGLE_MAX_LAG, ANGLE_BIN_RAD,
                                                       ANGLE_MAX_RAD)):
                acc += v
            view_rate_deg_s.append(float(np.degrees(np.median(rotation_angles(s["R_cam_from_target"], 1)))
                                         / float(s["dt_s"])))
        for acc, arr in ((pooled_z, z), (pooled_px, x)):
            n, c = lag_sums(arr, max_lag)
            acc[0] += n
            acc[1] += c
        for k, name in enumerate(names):
            for a, axis in enumerate("xy"):
                n, c = lag_sums(x[:, k, a], max_lag)
                per[name][axis][0] += n
                per[name][axis][1] += c
    return pooled_z, pooled_px, per, pooled_angle, view_rate_deg_s


def _angle_fit(pooled_angle: list[np.ndarray], pooled_z: list[np.ndarray]) -> tuple:
    """The correlation by the view's rotation angle, r(theta), and its exponential fit (share at most 1).
    Returns (share, correlation angle rad, r per bin, mean angle per bin rad)."""
    # the lag-0 variance is the time series' own (pooled_z): r(theta) on the same footing as r_k
    with np.errstate(invalid="ignore", divide="ignore"):
        r_th = np.where(pooled_angle[1] > 0, pooled_angle[0] / np.maximum(pooled_angle[1], 1), np.nan) / (
            pooled_z[0][0] / pooled_z[1][0])
        theta_mean = pooled_angle[2] / pooled_angle[1]
    a_th, th_c = fit_exponential_decay(theta_mean, r_th, pooled_angle[1])
    return min(a_th, 1.0), th_c, r_th, theta_mean


def _scale_stats(sequences: list[dict]) -> tuple[float, float, int, float]:
    """The apparent scale over every frame: (mean, standard error, frames, lag-1 autocorrelation along the
    sequences: the per-frame scale is itself correlated, so its AR(1) standard error is wider)."""
    scale_m, scale_se, scale_n = mean_se(np.concatenate([s["scale"] for s in sequences]))
    sc = [np.zeros(2), np.zeros(2)]
    for s in sequences:
        n, c = lag_sums(s["scale"] - scale_m, 1)
        sc[0] += n
        sc[1] += c
    rho_scale = float(autocorrelation(*sc)[1]) if sc[1][1] > 0 else 0.0
    return scale_m, scale_se, scale_n, rho_scale
