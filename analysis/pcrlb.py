"""Posterior Cramér-Rao lower bound (Tichavský, Muravchik, Nehorai 1998), recursive, for additive Gaussian noise.

For x_{k+1} = f_k(x_k) + w_k, w_k ~ N(0, Q_k), z_k = h_k(x_k) + v_k, v_k ~ N(0, R_k), x_0 ~ N(x0, P0), the
information matrix J_k of x_k obeys

    J_0     = P0^-1 + I_0                                   (I_0 = 0 when the first step has no update)
    J_{k+1} = (Q_k + F_k J_k^-1 F_k^T)^-1 + I_{k+1},        I_k = H_k^T R_k^-1 H_k over the measured rows

with F_k, H_k the Jacobians along the TRUE trajectory (the usual evaluation for a known nominal trajectory).
Any unbiased estimator has E[(x_hat - x)(x_hat - x)^T] >= J_k^-1; this module returns the bound covariance
B_k = J_k^-1. It is the Kalman filter's covariance recursion with the Jacobians at the truth, so on a linear
model it equals the Kalman covariance.

Numerics: Q may be ~1e-14 or 0 (singular), the state mixes metres with radians per second, and the measured
rows change every step. The recursion therefore never inverts Q, P or J: it carries a square root S_k
(B_k = S_k S_k^T), predicts it with a QR of [F S, Q^1/2], and updates it with the Cholesky factor C of
I + S^T I_k S (eigenvalues >= 1, well conditioned): B = S (I + S^T I_k S)^-1 S^T = (S C^-T)(S C^-T)^T. A step
without a measurement (I_k = 0) leaves the prediction unchanged.

The dynamics and measurement models are callables (the app passes the filter's `propagate` and measurement
functions): this stage imports only the core.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from envisat_pose.attitude import align_mrp
from envisat_pose.state import ATTITUDE, MRP, block_sums

# Central-difference steps for the 12-state (m, m/s, MRP, rad/s): rounding error ~ eps |f| / h and truncation
# ~ h^2 |f'''| both stay near 1e-10 relative for the ENVISAT scenario (|rho| ~ 50 m, |w| ~ 0.05 rad/s, dt ~ 1 s).
STATE_FD_STEP = np.array([1e-4] * 3 + [1e-5] * 3 + [1e-6] * 3 + [1e-6] * 3)


def fd_jacobian(f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, step: np.ndarray | float) -> np.ndarray:
    """Central-difference Jacobian df/dx at x, all 2n perturbed points in one call of f.

    f maps (..., S, n) -> (..., S, *out) and broadcasts over the leading axes of x (S = 2n stencil points).
    x: (..., n); step: absolute steps, scalar or (n,). Returns (..., *out, n).
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    h = np.broadcast_to(np.asarray(step, dtype=float), (n,))
    D = np.diag(h)
    X = np.concatenate([x[..., None, :] + D, x[..., None, :] - D], axis=-2)  # (..., 2n, n)
    Y = np.asarray(f(X), dtype=float)  # (..., 2n, *out): axis `lead` holds the stencil
    lead = x.ndim - 1
    Yp, Ym = Y[(slice(None),) * lead + (slice(0, n),)], Y[(slice(None),) * lead + (slice(n, 2 * n),)]
    d = (Yp - Ym) / (2.0 * h.reshape((n,) + (1,) * (Y.ndim - lead - 1)))  # (..., n, *out)
    return np.moveaxis(d, lead, -1)


def align_state_mrp(y: np.ndarray, y_ref: np.ndarray) -> np.ndarray:
    """12-states y with their MRP brought to the set of y_ref (broadcast), so a finite-difference stencil
    never straddles the shadow switch. (..., 12) -> (..., 12)."""
    y = np.array(y, dtype=float, copy=True)
    y[..., MRP] = align_mrp(y[..., MRP], np.broadcast_to(y_ref[..., MRP], y[..., MRP].shape))
    return y


def transition_jacobians(fx: Callable[[np.ndarray], np.ndarray], x_true: np.ndarray,
                         step: np.ndarray | float = STATE_FD_STEP,
                         align: Callable | None = align_state_mrp) -> np.ndarray:
    """F_k = d f_k / dx at x_true[k], k = 0 .. T-2, in one batched call.

    fx: (T-1, S, n) -> (T-1, S, n), row k propagates states at t_k to t_{k+1} (the app binds the chaser state
    at t_k and dt_k, e.g. `lambda X: propagate(X, chaser[:-1, None], dt_s, J_T, mu)`). x_true: (T, n).
    align(y, y_ref): puts the propagated stencil on the set of x_true[k+1] (default: the MRP shadow set), so
    F maps to the coordinates the truth uses at k+1. Returns (T-1, n, n).
    """
    ref = x_true[1:, None, :]
    g = (lambda X: align(fx(X), ref)) if align is not None else fx
    return fd_jacobian(g, x_true[:-1], step)


def measurement_jacobians(hx: Callable[[np.ndarray], np.ndarray], x_true: np.ndarray,
                          step: np.ndarray | float = STATE_FD_STEP) -> np.ndarray:
    """H_k for every corner: hx maps (T, S, n) -> (T, S, c, m) (all c corners, noise-free, e.g. the filter's
    `measure(X, kind, camera)`); x_true (T, n). Returns (T, c, m, n)."""
    return fd_jacobian(hx, x_true, step)


def measurement_information(H: np.ndarray, measured: np.ndarray, R_corner: np.ndarray) -> np.ndarray:
    """I = sum over measured corners of H_i^T R_i^-1 H_i.

    H: (..., c, m, n); measured: (..., c) bool (the truth's visible set, in frame, not dropped), or float: each
    corner's probability of being measured (its expected information, for random failures); R_corner: per
    corner noise covariance, broadcastable to (..., c, m, m). Returns (..., n, n), symmetric PSD.
    """
    R_corner = np.broadcast_to(R_corner, H.shape[:-1] + (H.shape[-2],))
    W = np.linalg.solve(R_corner, H)  # R^-1 H, (..., c, m, n)
    I = np.einsum("...cmi,...cmj->...cij", H, W) * np.asarray(measured, dtype=float)[..., None, None]
    I = I.sum(-3)
    return 0.5 * (I + np.swapaxes(I, -1, -2))


def psd_sqrt(Q: np.ndarray) -> np.ndarray:
    """A square root L of a symmetric PSD matrix, Q = L L^T (eigenvalues clipped at 0). (..., n, n)."""
    lam, V = np.linalg.eigh(0.5 * (Q + np.swapaxes(Q, -1, -2)))
    return V * np.sqrt(np.maximum(lam, 0.0))[..., None, :]


def _update_sqrt(S: np.ndarray, info: np.ndarray) -> np.ndarray:
    """Square root of ((S S^T)^-1 + info)^-1 = S (I + S^T info S)^-1 S^T, as S C^-T with C C^T = I + S^T info S."""
    n = S.shape[-1]
    M = np.eye(n) + np.swapaxes(S, -1, -2) @ info @ S
    C = np.linalg.cholesky(0.5 * (M + np.swapaxes(M, -1, -2)))
    return np.swapaxes(np.linalg.solve(C, np.swapaxes(S, -1, -2)), -1, -2)


def _predict_sqrt(S: np.ndarray, F: np.ndarray, Q_sqrt: np.ndarray) -> np.ndarray:
    """Square root of F S S^T F^T + Q: the triangular factor of QR([F S, Q^1/2]^T)."""
    FS = F @ S
    Qs = np.broadcast_to(Q_sqrt, FS.shape)
    A = np.concatenate([np.swapaxes(FS, -1, -2), np.swapaxes(Qs, -1, -2)], axis=-2)  # (..., 2n, n)
    return np.swapaxes(np.linalg.qr(A, mode="r"), -1, -2)


def pcrlb_recursion(P0: np.ndarray, F: np.ndarray, Q: np.ndarray, info: np.ndarray,
                    info_at_first: bool = True) -> np.ndarray:
    """The bound covariances B_k = J_k^-1, k = 0 .. T-1 (module docstring), in square-root form.

    P0: (..., n, n) prior covariance at t_0. F: (..., T-1, n, n) transition Jacobians. Q: process noise of each
    step, (n, n) or (..., T-1, n, n) (may be singular or 0). info: (..., T, n, n) measurement information
    (`measurement_information`; zeros at steps without measurement). info_at_first: the first step carries a
    measurement update (the filter's `filter_step` updates at t_0). Returns (..., T, n, n).
    """
    T = info.shape[-3]
    Q = np.asarray(Q, dtype=float)
    Q_sqrt = psd_sqrt(Q)
    per_step_Q = Q.ndim >= 3 and Q.shape[-3] == T - 1
    S = np.linalg.cholesky(0.5 * (P0 + np.swapaxes(P0, -1, -2)))
    if info_at_first:
        S = _update_sqrt(S, info[..., 0, :, :])
    out = np.empty(np.broadcast_shapes(S.shape[:-2], info.shape[:-3]) + (T,) + S.shape[-2:])
    out[..., 0, :, :] = S @ np.swapaxes(S, -1, -2)
    for k in range(1, T):
        Qs = Q_sqrt[..., k - 1, :, :] if per_step_Q else Q_sqrt
        S = _predict_sqrt(S, F[..., k - 1, :, :], Qs)
        S = _update_sqrt(S, info[..., k, :, :])
        out[..., k, :, :] = S @ np.swapaxes(S, -1, -2)
    return out


def pcrlb_along_truth(fx: Callable, hx: Callable, x_true: np.ndarray, measured: np.ndarray, R_corner: np.ndarray,
                      P0: np.ndarray, Q: np.ndarray, step: np.ndarray | float = STATE_FD_STEP,
                      info_at_first: bool = True, align: Callable | None = align_state_mrp) -> np.ndarray:
    """The bound for one truth trajectory: Jacobians by central differences, then `pcrlb_recursion`.

    fx, hx: as in `transition_jacobians` / `measurement_jacobians`; x_true (T, n); measured (T, c) bool, the
    corners measured at each step (or float: each one's probability of being measured); R_corner broadcastable
    to (T, c, m, m); P0 (n, n); Q (n, n) or (T-1, n, n).
    Returns (T, n, n).
    """
    F = transition_jacobians(fx, x_true, step, align)
    info = measurement_information(measurement_jacobians(hx, x_true, step), measured, R_corner)
    return pcrlb_recursion(P0, F, Q, info, info_at_first)


def block_bounds(B: np.ndarray, x_true: np.ndarray) -> np.ndarray:
    """RMSE lower bounds per state block from a bound covariance: sqrt of the block's trace for position (m),
    velocity (m/s) and angular velocity (rad/s); for attitude the error-angle bound
    4 / (1 + p.p) sqrt(trace B_pp) (rad; MRP difference -> rotation vector, B B^T = ((1 + p.p) / 4)^2 I).

    B: (..., 12, 12); x_true: (..., 12) (its MRP sets the attitude scale). Returns (..., 4), comparable with
    `stats.CampaignStats.rmse_block`.
    """
    tr = np.maximum(block_sums(np.diagonal(B, axis1=-2, axis2=-1)), 0.0)
    p = x_true[..., MRP]
    scale = np.ones(tr.shape)
    scale[..., ATTITUDE] = 4.0 / (1.0 + np.einsum("...i,...i->...", p, p))
    return scale * np.sqrt(tr)


def efficiency(rmse_block: np.ndarray, bound_block: np.ndarray, t_s: np.ndarray, settle_s: float = 0.0) -> np.ndarray:
    """RMSE / PCRLB per block over the steps at or after t_s[0] + settle_s: the ratio of the RMS over time of
    each. (T, 4), (T, 4), (T,) -> (4,); 1 is the best any unbiased estimator can do."""
    k = t_s >= t_s[0] + settle_s
    return np.sqrt(np.mean(rmse_block[k] ** 2, axis=0) / np.mean(bound_block[k] ** 2, axis=0))
