"""Our UKF as pure functions over a batch of runs: `predict(mean, cov, ...)`, `update(mean, cov, z, mask, ...)`.

Shapes: mean (..., n), cov (..., n, n), with any leading batch dims (runs). Sigma points are the scaled
symmetric set of van der Merwe (filterpy's MerweScaledSigmaPoints): chi_0 = x, chi_k = x + [L]_k,
chi_(n+k) = x - [L]_k, with L L^T = (n + lambda) P (the rows of filterpy's upper Cholesky factor).

Attitude (reference sheet, section 4): the MRP mean is kept on |p| <= 1. Sigma points are drawn around the mean
on its set; after propagation each sigma point's MRP is brought to the set of the central sigma point before
averaging (`state_mean`), the averaged mean is switched to its shadow if |p| > 1, and every residual brings the
sigma point's MRP to the set of the point it is compared with (`state_residual`). After an update that carries
|p| over 1 the mean switches and the covariance maps with S = d(shadow)/dp (`shadow_switch`).
The same hooks serve filterpy's reference filter (filtering/reference.py), so the two are equal step by step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from envisat_pose.attitude import (
    align_mrp,
    mrp_compose,
    mrp_kinematics_matrix,
    mrp_shadow,
    mrp_shadow_jacobian,
    mrp_to_dcm,
    skew,
)
from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2, load_inertia_T_kg_m2, propagate
from envisat_pose.filtering.screw_chart import screw_local, screw_retract, screw_transport
from envisat_pose.state import MRP, RATE  # the 12-state's layout has one home


@dataclass(frozen=True)
class SigmaWeights:
    """Scaled unscented weights: lam = alpha^2 (n + kappa) - n; Wm, Wc: (2n + 1,)."""

    n: int
    lam: float
    Wm: np.ndarray
    Wc: np.ndarray


def merwe_weights(n: int, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> SigmaWeights:
    """Weights of the scaled symmetric sigma-point set (van der Merwe 2004), as in filterpy."""
    lam = alpha**2 * (n + kappa) - n
    Wc = np.full(2 * n + 1, 0.5 / (n + lam))
    Wm = Wc.copy()
    Wc[0] = lam / (n + lam) + (1.0 - alpha**2 + beta)
    Wm[0] = lam / (n + lam)
    return SigmaWeights(n, lam, Wm, Wc)


# ---------------------------------------------------------------- attitude-aware hooks (shared with filterpy)

def state_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b for 12-states, with a's MRP first brought to the set of b's. (..., 12)."""
    d = a - b
    d[..., MRP] = align_mrp(a[..., MRP], b[..., MRP]) - b[..., MRP]
    return d


def state_mean(sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
    """Weighted mean of sigma points (..., S, 12): MRPs on the central point's set, then |p| <= 1. (..., 12)."""
    s = np.array(sigmas, dtype=float, copy=True)
    s[..., MRP] = align_mrp(s[..., MRP], s[..., :1, MRP])
    m = Wm @ s
    m[..., MRP] = mrp_shadow(m[..., MRP])
    return m


def shadow_switch(mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Switch runs whose MRP has |p| > 1 to the shadow set; the MRP rows/columns of cov map with S. (..., 12)."""
    p = mean[..., MRP]
    switch = np.einsum("...i,...i->...", p, p) > 1.0
    if not np.any(switch):
        return mean, cov
    mean, cov = mean.copy(), cov.copy()
    S = mrp_shadow_jacobian(np.where(switch[..., None], p, 1.0))
    S = np.where(switch[..., None, None], S, np.eye(3))
    mean[..., MRP] = mrp_shadow(p)
    cov[..., MRP, :] = S @ cov[..., MRP, :]
    cov[..., :, MRP] = cov[..., :, MRP] @ np.swapaxes(S, -1, -2)
    return mean, cov


# ---------------------------------------------------------------- covariance health

def repair_cov(cov: np.ndarray, rel_floor: float = 1e-12, abs_floor: float = 1e-18) -> tuple[np.ndarray, np.ndarray]:
    """Symmetrize; where a covariance is not positive definite, take |eigenvalues|, at least a floor.

    Returns (cov, repaired (...,) bool). Never raises: NaN entries are left for the caller's finite check.
    """
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    try:
        np.linalg.cholesky(cov)
        return cov, np.zeros(cov.shape[:-2], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    finite = np.isfinite(cov).all(axis=(-1, -2))
    safe = np.where(finite[..., None, None], cov, np.eye(cov.shape[-1]))
    w, V = np.linalg.eigh(safe)
    floor = np.maximum(rel_floor * np.abs(w).max(axis=-1, keepdims=True), abs_floor)
    bad = (w.min(axis=-1) <= floor[..., 0]) & finite
    # a negative eigenvalue is round-off or a broken input: its magnitude is a better guess than ~0, which
    # would make the filter certain along that direction forever
    fixed = np.einsum("...ij,...j,...kj->...ik", V, np.maximum(np.abs(w), floor), V)
    return np.where(bad[..., None, None], fixed, cov), bad


def sigma_points(mean: np.ndarray, cov: np.ndarray, w: SigmaWeights) -> np.ndarray:
    """Scaled symmetric sigma points. mean (..., n), cov (..., n, n) -> (..., 2n + 1, n)."""
    A = (w.n + w.lam) * cov
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        L = np.linalg.cholesky(repair_cov(A)[0])
    D = np.swapaxes(L, -1, -2)  # row k = column k of L = row k of the upper factor U = L^T
    m = mean[..., None, :]
    return np.concatenate([m, m + D, m - D], axis=-2)


# ---------------------------------------------------------------- the rotation chart of the sigma points

def _mrp_B(p: np.ndarray) -> np.ndarray:
    """4 B(p) (attitude.mrp_kinematics_matrix): dp = _mrp_B(p) a for a small error MRP a. (..., 3, 3)."""
    return 4.0 * mrp_kinematics_matrix(p)


def chart_retract(mean: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The states at deviations D from mean in the rotation chart: (..., 12) mean, D (..., 12) or (..., S, 12).

    The additive chart puts a sigma point at mean + D. This one reads D's MRP part as the rotation it is to first
    order, the error MRP a = B(p)^T D_p / (1 + p.p)^2 (B = 4 x the kinematics matrix: D_p = B a), and turns the
    body by it: Gamma = Gamma(a) Gamma(p), composed, not added; the angular velocity turns with the body, w =
    Gamma(a) (w_mean + D_w - 4 w_mean x a) (its components in C are those of mean plus D_w's to first order).
    Rotating a body about an axis of symmetry, with its rate, is then a straight line in D at any angle (a rod's
    unmeasured rotation about its own axis: tests/filtering/test_sigma_chart.py). To first order in D it is the
    additive chart. Translation: mean + D."""
    mean = np.asarray(mean, dtype=float)
    D = np.asarray(D, dtype=float)
    m = mean[..., None, :] if D.ndim == mean.ndim + 1 else mean
    X = m + D
    p, w = np.broadcast_to(m[..., MRP], D[..., MRP].shape), np.broadcast_to(m[..., RATE], D[..., RATE].shape)
    pp = np.einsum("...i,...i->...", p, p)
    a = np.einsum("...ji,...j->...i", _mrp_B(p), D[..., MRP]) / np.square(1.0 + pp)[..., None]
    X[..., MRP] = mrp_compose(a, p)
    X[..., RATE] = np.einsum("...ij,...j->...i", mrp_to_dcm(a), w + D[..., RATE] - 4.0 * np.cross(w, a))
    return X


def chart_local(X: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """chart_retract's inverse: D with chart_retract(mean, D) = X (the smaller of the two error rotations).
    X (..., S, 12) or (..., 12), mean (..., 12)."""
    X = np.asarray(X, dtype=float)
    mean = np.asarray(mean, dtype=float)
    m = mean[..., None, :] if X.ndim == mean.ndim + 1 else mean
    D = X - m
    p, w = np.broadcast_to(m[..., MRP], X[..., MRP].shape), np.broadcast_to(m[..., RATE], X[..., RATE].shape)
    a = mrp_shadow(mrp_compose(X[..., MRP], -p))                  # Gamma(a) = Gamma(p_X) Gamma(p)^T
    D[..., MRP] = np.einsum("...ij,...j->...i", _mrp_B(p), a)
    D[..., RATE] = np.einsum("...ji,...j->...i", mrp_to_dcm(a), X[..., RATE]) - w + 4.0 * np.cross(w, a)
    return D


def chart_error(x_true: np.ndarray, x_hat: np.ndarray, chart: str = "additive") -> np.ndarray:
    """The estimate's error x_hat - x_true in the chart of its covariance (FilterConfig.sigma_chart), for NEES and
    Mahalanobis distances: "additive", the difference with the truth's MRP on the estimate's set (state_residual);
    "rotation" ("screw"), minus chart_local(x_true, x_hat) (screw_local). x_true broadcastable to x_hat (..., 12).
    Returns (..., 12)."""
    x_true = np.broadcast_to(x_true, np.shape(x_hat)).copy()
    local = CHART_MAPS[chart][1] if chart != "additive" else state_residual
    return -local(x_true, np.asarray(x_hat, dtype=float))


def _chart_M(mean: np.ndarray) -> np.ndarray:
    """The rotation chart's (D_p, D_w) at mean as a linear map of (a, b): the error MRP and the angular-velocity
    error in C, which do not depend on the mean: D_p = B(p) a, D_w = Gamma(p) b + 4 w x a. (..., 6, 6)."""
    p, w = mean[..., MRP], mean[..., RATE]
    M = np.zeros(mean.shape[:-1] + (6, 6))
    M[..., :3, :3] = _mrp_B(p)
    M[..., 3:, :3] = 4.0 * skew(w)
    M[..., 3:, 3:] = mrp_to_dcm(p)
    return M


def chart_transport(cov: np.ndarray, mean_from: np.ndarray, mean_to: np.ndarray) -> np.ndarray:
    """A covariance in the rotation chart at mean_from, carried to the chart at mean_to (an update moved the
    mean, or switched its MRP to the shadow set): T P T^T with T = M(to) G M(from)^-1 on the attitude and rate
    rows and columns (_chart_M), G the error MRP's reset to the new mean, d a' / d a = B(d)^T / (1 + d.d)^2 for
    the turn d from one mean to the other (exact at the new mean), the rate error in C unchanged. Without it the
    rate's covariance stays in the old attitude's axes, and a rate known well in magnitude and poorly in
    direction leaks information into the unmeasured rotation. (..., 12, 12)."""
    d = mrp_shadow(mrp_compose(mean_to[..., MRP], -mean_from[..., MRP]))
    G = np.broadcast_to(np.eye(6), mean_to.shape[:-1] + (6, 6)).copy()
    G[..., :3, :3] = np.swapaxes(_mrp_B(d), -1, -2) / np.square(1.0 + np.einsum("...i,...i->...", d, d))[..., None, None]
    T6 = _chart_M(mean_to) @ G @ np.linalg.inv(_chart_M(mean_from))
    T = np.broadcast_to(np.eye(cov.shape[-1]), cov.shape).copy()
    T[..., MRP.start:RATE.stop, MRP.start:RATE.stop] = T6
    out = T @ cov @ np.swapaxes(T, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


# FilterConfig.sigma_chart -> (retract, local, transport) of the charts other than the additive one
CHART_MAPS = {"rotation": (chart_retract, chart_local, chart_transport),
              "screw": (screw_retract, screw_local, screw_transport)}


def sigma_deviations(cov: np.ndarray, w: SigmaWeights) -> np.ndarray:
    """The scaled symmetric set's deviations from the mean: 0, +[L]_k, -[L]_k with L L^T = (n + lambda) P, as
    sigma_points draws them. cov (..., n, n) -> (..., 2n + 1, n)."""
    A = (w.n + w.lam) * cov
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        L = np.linalg.cholesky(repair_cov(A)[0])
    D = np.swapaxes(L, -1, -2)
    return np.concatenate([np.zeros_like(D[..., :1, :]), D, -D], axis=-2)


def chart_sigma_points(mean: np.ndarray, cov: np.ndarray, w: SigmaWeights, chart: str = "additive") -> np.ndarray:
    """The sigma points a filter of that chart (FilterConfig.sigma_chart) draws about mean: sigma_points (mean plus
    the columns), or for "rotation" ("screw") chart_retract (screw_retract) of sigma_deviations (those of
    ut_update and ut_predict_rotation). mean (..., n), cov (..., n, n) -> (..., 2n + 1, n)."""
    if chart != "additive":
        return CHART_MAPS[chart][0](mean, sigma_deviations(cov, w))
    return sigma_points(mean, cov, w)


def ut_predict_rotation(mean: np.ndarray, cov: np.ndarray, fx: Callable[[np.ndarray], np.ndarray], Q: np.ndarray,
                        w: SigmaWeights, chart: str = "rotation") -> tuple[np.ndarray, np.ndarray]:
    """The unscented time update in the rotation chart (chart_retract; chart "screw": screw_retract): sigma
    points along rotations, propagated by fx, their mean taken in the chart of the central propagated point,
    their residuals in the chart of that mean (on |p| <= 1). Returns (mean, cov)."""
    retract, local, _ = CHART_MAPS[chart]
    sig_f = fx(retract(mean, sigma_deviations(cov, w)))
    ref = sig_f[..., 0, :]
    m = retract(ref, np.einsum("s,...si->...i", w.Wm, local(sig_f, ref)))
    m[..., MRP] = mrp_shadow(m[..., MRP])
    res = local(sig_f, m)
    P = _wsum_outer(res, res, w.Wc) + Q
    return m, repair_cov(P)[0]


# ---------------------------------------------------------------- the two steps

def _wsum_outer(a: np.ndarray, b: np.ndarray, W: np.ndarray) -> np.ndarray:
    """sum_s W_s a_s b_s^T. a (..., S, i), b (..., S, j), W (S,) -> (..., i, j)."""
    return np.swapaxes(a * W[:, None], -1, -2) @ b


def _plain_mean(sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
    return Wm @ sigmas


def _plain_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a - b


def ut_predict(mean: np.ndarray, cov: np.ndarray, fx: Callable[[np.ndarray], np.ndarray], Q: np.ndarray,
               w: SigmaWeights, mean_fn=_plain_mean, residual_fn=_plain_residual) -> tuple[np.ndarray, np.ndarray]:
    """Generic unscented time update. fx maps sigma points (..., S, n) -> (..., S, n). Returns (mean, cov)."""
    sig_f = fx(sigma_points(mean, cov, w))
    m = mean_fn(sig_f, w.Wm)                                   # x = sum Wm chi
    res = residual_fn(sig_f, m[..., None, :])
    P = _wsum_outer(res, res, w.Wc) + Q                        # P = sum Wc (chi - x)(chi - x)^T + Q
    return m, repair_cov(P)[0]


def positive_definite(S: np.ndarray) -> np.ndarray:
    """(...,) bool: S (..., M, M) is finite, symmetric to rounding and positive definite (its smallest eigenvalue
    above rounding of its largest)."""
    finite = np.isfinite(S).all(axis=(-1, -2))
    S_ok = np.where(finite[..., None, None], 0.5 * (S + np.swapaxes(S, -1, -2)), np.eye(S.shape[-1]))
    w = np.linalg.eigvalsh(S_ok)
    return finite & (w[..., 0] > 1e-12 * np.maximum(np.abs(w[..., -1]), 1e-300))


def _safe_inv(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched inverse that never raises, and which runs it is valid for: an innovation covariance S that is not
    positive definite (non-finite, singular or indefinite) gives NaN for its run, so its update fails (rolled back
    and reported by the estimator) instead of producing a negative NIS. Returns (S^-1, pd (...,) bool)."""
    pd = positive_definite(S)
    S_ok = np.where(pd[..., None, None], S, np.eye(S.shape[-1]))
    SI = np.linalg.inv(S_ok)
    return np.where(pd[..., None, None], SI, np.nan), pd


def ut_update(mean: np.ndarray, cov: np.ndarray, z: np.ndarray, mask: np.ndarray, Rm: np.ndarray,
              hx: Callable[[np.ndarray], np.ndarray], w: SigmaWeights, residual_fn=_plain_residual,
              gate=None, chart: str = "additive"):
    """Generic unscented measurement update with a mask of used components.

    z (..., M), mask (..., M) bool, Rm (..., M, M) noise covariance; hx maps sigma points (..., S, n) ->
    (..., S, M). Unused components get zero innovation and unit variance, which is exactly the update on the
    used subset. gate: optional callable (y, S_full, mask) -> mask applied before the update.
    Returns (mean, cov, nis, mask, y, K, Pzz, pd) with Pzz the state part of the innovation covariance and pd
    (...,) bool: the innovation covariance was positive definite (elsewhere mean, cov and nis are NaN).
    """
    M = z.shape[-1]
    if chart != "additive":  # sigma points along the chart (CHART_MAPS); their deviations are the residuals
        dx = sigma_deviations(cov, w)
        sig = CHART_MAPS[chart][0](mean, dx)
    else:
        sig = sigma_points(mean, cov, w)
    zs = hx(sig)
    zp = w.Wm @ zs                                                 # predicted measurement
    dz = zs - zp[..., None, :]
    if chart == "additive":
        dx = residual_fn(sig, mean[..., None, :])
    Pzz = _wsum_outer(dz, dz, w.Wc)
    Pxz = _wsum_outer(dx, dz, w.Wc)                                # cross covariance
    y_all = z - zp                                                 # innovation
    if gate is not None:
        mask = gate(np.where(mask, y_all, 0.0), Pzz + Rm, mask)
    m2 = mask[..., :, None] & mask[..., None, :]
    S = np.where(m2, Pzz + Rm, np.eye(M))                          # innovation covariance
    SI, pd = _safe_inv(S)
    Pxz = Pxz * mask[..., None, :]
    y = np.where(mask, y_all, 0.0)
    K = Pxz @ SI                                                   # Kalman gain
    step = (K @ y[..., None])[..., 0]
    mean = CHART_MAPS[chart][0](mean, step) if chart != "additive" else mean + step
    cov = cov - K @ S @ np.swapaxes(K, -1, -2)
    nis = (y[..., None, :] @ SI @ y[..., :, None])[..., 0, 0]  # >= 0 where pd; NaN (a failed update) elsewhere
    return mean, cov, nis, mask, y, K, np.where(m2, Pzz, 0.0), pd


def predict(mean: np.ndarray, cov: np.ndarray, c0: np.ndarray, dt_s: float, Q: np.ndarray, w: SigmaWeights,
            J_T: np.ndarray | None = None, mu_m3_s2: float = MU_EARTH_M3_S2,
            max_step_s: float = 1.0, gravity_gradient: bool = False, chart: str = "additive"
            ) -> tuple[np.ndarray, np.ndarray]:
    """UKF time update of the 12-state over dt_s with the filter's RK4 model and the MRP hooks (chart
    "rotation" or "screw": ut_predict_rotation's sigma points along rotations).

    mean (..., 12), cov (..., 12, 12), c0 chaser state (r_m, rdot_m_s, theta_rad, thetadot_rad_s) at the start,
    (4,) or (..., 4); Q (12, 12) or (..., 12, 12) process noise of the step; mu_m3_s2 the Earth's gravitational
    parameter; gravity_gradient: the model applies the gravity-gradient torque. Returns the prior (mean, cov).
    """
    J_T = load_inertia_T_kg_m2() if J_T is None else J_T
    c = np.asarray(c0, dtype=float)
    c = c[..., None, :] if c.ndim > 1 else c
    fx = lambda sig: propagate(sig, c, dt_s, J_T, mu_m3_s2, max_step_s, gravity_gradient)  # noqa: E731
    if chart != "additive":
        return ut_predict_rotation(mean, cov, fx, Q, w, chart)
    return ut_predict(mean, cov, fx, Q, w, state_mean, state_residual)


@dataclass
class UpdateInfo:
    """What an update saw, per run: nis (...,), dof (...,) measured components used, accepted (..., K) corners,
    innovation y (..., M) and gain K (..., n, M) (zero where a component was not used), Pzz_state (..., M, M);
    indefinite (...,) bool: the innovation covariance was not positive definite (the update failed: NaN)."""

    nis: np.ndarray
    dof: np.ndarray
    accepted: np.ndarray
    y: np.ndarray
    K: np.ndarray
    Pzz_state: np.ndarray
    indefinite: np.ndarray


def block_diag_corners(cov_c: np.ndarray) -> np.ndarray:
    """Per-corner covariances (..., K, m, m) -> block-diagonal (..., K m, K m)."""
    nc, m = cov_c.shape[-3], cov_c.shape[-1]
    out = np.zeros(cov_c.shape[:-3] + (nc, m, nc, m))
    for c in range(nc):
        out[..., c, :, c, :] = cov_c[..., c, :, :]
    return out.reshape(cov_c.shape[:-3] + (nc * m, nc * m))


def gate_corners(y: np.ndarray, S: np.ndarray, mask: np.ndarray, m: int, threshold: float) -> np.ndarray:
    """Chi-square gate per corner: keep corner c if y_c^T S_cc^-1 y_c <= threshold (m dof).

    y (..., K m) innovation, S (..., K m, K m) innovation covariance, mask (..., K m) components (whole corners).
    threshold: a number or one per run (...,). Returns the mask (..., K m) without the rejected corners.
    """
    nc = y.shape[-1] // m
    mask_c = mask.reshape(mask.shape[:-1] + (nc, m))[..., 0]
    yc = y.reshape(y.shape[:-1] + (nc, m))
    Sb = S.reshape(S.shape[:-2] + (nc, m, nc, m))
    Scc = np.einsum("...cicj->...cij", Sb)
    Scc = np.where(mask_c[..., None, None], Scc, np.eye(m))
    d2 = (yc[..., None, :] @ np.linalg.solve(Scc, yc[..., :, None]))[..., 0, 0]
    thr = np.asarray(threshold, dtype=float)
    thr = thr[..., None] if thr.ndim else thr
    return np.repeat(mask_c & (d2 <= thr), m, axis=-1)  # NaN distances fail the test too


def update(mean: np.ndarray, cov: np.ndarray, z: np.ndarray, mask_c: np.ndarray, R_c: np.ndarray,
           hx: Callable[[np.ndarray], np.ndarray], w: SigmaWeights,
           gate_threshold: float | None = None, chart: str = "additive") -> tuple[np.ndarray, np.ndarray, UpdateInfo]:
    """UKF measurement update of the 12-state with a varying set of measured corners.

    mean (..., 12), cov (..., 12, 12); z (..., K, m) measurements; mask_c (..., K) bool measured corners;
    R_c (..., K, m, m) per-corner noise covariances; hx: (..., 12) -> (..., K, m) the measurement model of all
    corners. gate_threshold: chi-square bound per corner, a number or (...,) per run (None: no gating). After the update the MRP switches
    to its shadow where |p| > 1 (mean and covariance together). Returns (mean, cov, info).
    """
    nc, m = z.shape[-2], z.shape[-1]
    M = nc * m
    Rm = block_diag_corners(np.broadcast_to(R_c, z.shape + (m,)))
    hx_flat = lambda sig: hx(sig).reshape(sig.shape[:-1] + (M,))  # noqa: E731
    gate = None
    if gate_threshold is not None:
        gate = lambda y, S, mask: gate_corners(y, S, mask, m, gate_threshold)  # noqa: E731
    mask = np.repeat(np.asarray(mask_c, dtype=bool), m, axis=-1)
    prior_mean = np.asarray(mean, dtype=float)
    mean, cov, nis, mask, y, K, Pzz, pd = ut_update(mean, cov, z.reshape(z.shape[:-2] + (M,)), mask, Rm, hx_flat,
                                                   w, state_residual, gate, chart)
    if chart != "additive":  # the posterior's covariance in the chart of the posterior's mean, on |p| <= 1
        moved = mean.copy()
        moved[..., MRP] = mrp_shadow(moved[..., MRP])
        ok = np.isfinite(moved).all(-1)
        to = np.where(ok[..., None], moved, prior_mean)
        transported = CHART_MAPS[chart][2](np.where(ok[..., None, None], cov, np.eye(cov.shape[-1])), prior_mean, to)
        cov = np.where(ok[..., None, None], transported, cov)
        mean = moved
    mean, cov = shadow_switch(mean, cov)
    cov = repair_cov(cov)[0]
    accepted = mask.reshape(mask.shape[:-1] + (nc, m))[..., 0]
    return mean, cov, UpdateInfo(nis=nis, dof=mask.sum(axis=-1), accepted=accepted, y=y, K=K, Pzz_state=Pzz,
                                  indefinite=~pd)
