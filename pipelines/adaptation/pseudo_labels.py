"""Pseudo-labels from a tracker's own output: a fixed-interval smoother over its tracked segments, and the corner
labels of a pose (`envisat adapt` teaches the detector a user's frames without labels).

Pure functions over numpy arrays; no I/O, no truth.

Segments. A segment is a maximal run of frames whose filter ran without a break: status tracking or coasting
(envisat_pose/status.py: both hold a running filter's estimate) and, where the per-frame number of open half-turn
hypotheses is given (det.npz `n_hypotheses`), one hypothesis left (the half-turn decided). Any acquiring or lost
frame, or a frame with its half-turn open, ends a segment. Only the segment's tracking frames are trusted as
labels (`trusted`); its coasting frames are smoothed through (they carry the filter's prediction) but labelled
nothing.

The smoother. The unscented Rauch-Tung-Striebel smoother (Saerkkae 2008) run backwards over each segment from the
filter's posteriors (x_k, P_k) alone: each step re-predicts frame k's posterior through the filter's own dynamics
(filtering/dynamics.py `propagate`, RK4, the reference sheet's equations) with the filter's process noise
Q = diag(q_sigma^2) dt, and

    G_k = C_k (P^-_(k+1))^-1,   x^s_k = x_k [+] G_k (x^s_(k+1) [-] x^-_(k+1)),
    P^s_k = P_k + G_k (P^s_(k+1) - P^-_(k+1)) G_k^T,

with C_k the cross-covariance of the sigma points before and after the step. The attitude is smoothed in an error
state: [+] and [-] act on a rotation vector dtheta in T (rad) with Gamma = exp(-[dtheta x]) Gamma_ref, the sign
of the MRP kinematics p' = B(p) w (so dp = B(p) dtheta to first order); position, velocity and rate add. The
filter's covariance, on additive MRP differences at its own shadow set, enters and leaves through B(p): P_theta =
M P_p M^T with M = B(p)^-1. So the smoother never averages or differences MRPs across the shadow set (a tumbling
target crosses |p| = 1 every turn), and the smoothed MRP is left on |p| <= 1 with its covariance on that set.
Frames of the error state at x^s_(k+1) and x^-_(k+1) differ by the small smoothing correction; the covariance is
not transported between them (second order).

Labels. `corner_labels` projects the box's corners A-H (models/envisat.xml, envisat_pose.geometry) at a pose
through the one PinholeCamera, with the exact face test of the box (geometry.visible_corners, from the camera's
centre) as visibility and the truth's in-frame rule (in front of the camera, inside [-0.5, W - 0.5) x
[-0.5, H - 0.5)): the fields perception/data.py's decode_label returns. The face test does not see the solar
array hide a corner (a shard's depth-tested label does).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from envisat_pose.attitude import dcm_to_mrp, mrp_kinematics_matrix, mrp_to_dcm
from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2, load_inertia_T_kg_m2, propagate
from envisat_pose.filtering.measurements import corners_C_m, project
from envisat_pose.filtering.ukf import merwe_weights
from envisat_pose.geometry import PinholeCamera, load_geometry, visible_corners
from envisat_pose.state import MRP, N_STATE
from envisat_pose.status import COASTING, TRACKING

# ---------------------------------------------------------------------------------------------------------
# Segments of a track


def segment_frames(status: np.ndarray, n_hypotheses: np.ndarray | None = None) -> np.ndarray:
    """Frames inside a segment: a running filter (tracking or coasting) with its half-turn decided (one
    hypothesis, where n_hypotheses (T,) is given). status (T,) codes -> (T,) bool."""
    status = np.asarray(status)
    inside = np.isin(status, (TRACKING, COASTING))
    if n_hypotheses is not None:
        inside &= np.asarray(n_hypotheses) == 1
    return inside


def tracked_segments(status: np.ndarray, n_hypotheses: np.ndarray | None = None) -> list[tuple[int, int]]:
    """The segments of a track as [start, stop) frame ranges, in order: maximal runs of segment_frames that hold
    at least one tracking frame (a run of coasting alone has nothing to label)."""
    status = np.asarray(status)
    inside = segment_frames(status, n_hypotheses)
    edges = np.diff(np.concatenate([[0], inside.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops) if np.any(status[a:b] == TRACKING)]


def trusted_frames(status: np.ndarray, n_hypotheses: np.ndarray | None = None) -> np.ndarray:
    """Frames whose smoothed pose may label the image: tracking, half-turn decided. (T,) bool."""
    return segment_frames(status, n_hypotheses) & (np.asarray(status) == TRACKING)


# ---------------------------------------------------------------------------------------------------------
# The error state: attitude as a rotation vector in T


def state_plus(x: np.ndarray, e: np.ndarray) -> np.ndarray:
    """x [+] e: the 12-state x (..., 12) moved by the error e (..., 12): position, velocity and rate added, the
    attitude turned by the rotation vector e[MRP] (rad, in T): Gamma = exp(-[e x]) Gamma(p). MRP on |p| <= 1."""
    x, e = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(e, dtype=float))
    out = x + e
    lead = x.shape[:-1]
    turn = Rotation.from_rotvec(-e[..., MRP].reshape(-1, 3)).as_matrix().reshape(lead + (3, 3))
    out[..., MRP] = dcm_to_mrp(turn @ mrp_to_dcm(x[..., MRP]))
    return out


def state_minus(x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """x [-] x_ref: the error e (..., 12) with x = x_ref [+] e (the rotation vector of Gamma(p) Gamma(p_ref)^T,
    rad in T, whichever shadow set either MRP is on)."""
    x, x_ref = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(x_ref, dtype=float))
    e = x - x_ref
    lead = x.shape[:-1]
    E = mrp_to_dcm(x[..., MRP]) @ np.swapaxes(mrp_to_dcm(x_ref[..., MRP]), -1, -2)
    e[..., MRP] = -Rotation.from_matrix(E.reshape(-1, 3, 3)).as_rotvec().reshape(lead + (3,))
    return e


def _attitude_map(p_mrp: np.ndarray, to_error: bool) -> np.ndarray:
    """(..., 12, 12): identity but the attitude block, M = B(p)^-1 (MRP difference -> rotation vector) when
    to_error, else B(p) (rotation vector -> MRP difference)."""
    p = np.asarray(p_mrp, dtype=float)
    B = mrp_kinematics_matrix(p)
    if to_error:
        pp = np.einsum("...i,...i->...", p, p)[..., None, None]
        B = 16.0 / (1.0 + pp) ** 2 * np.swapaxes(B, -1, -2)  # B B^T = ((1 + p.p) / 4)^2 I
    A = np.broadcast_to(np.eye(N_STATE), p.shape[:-1] + (N_STATE, N_STATE)).copy()
    A[..., MRP, MRP] = B
    return A


def to_error_cov(x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """A covariance on additive MRP differences at x's set (the filter's) -> on the error state at x.
    x (..., 12), P (..., 12, 12) -> (..., 12, 12)."""
    A = _attitude_map(np.asarray(x)[..., MRP], to_error=True)
    return A @ P @ np.swapaxes(A, -1, -2)


def from_error_cov(x: np.ndarray, P_e: np.ndarray) -> np.ndarray:
    """The inverse of to_error_cov: an error-state covariance at x -> additive MRP differences at x's set."""
    A = _attitude_map(np.asarray(x)[..., MRP], to_error=False)
    return A @ P_e @ np.swapaxes(A, -1, -2)


# ---------------------------------------------------------------------------------------------------------
# The unscented RTS smoother, generic


def _add(x: np.ndarray, e: np.ndarray) -> np.ndarray:
    return x + e


def _sub(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return x - y


def _sym(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def unscented_rts(means: np.ndarray, covs: np.ndarray, step: Callable[[int, np.ndarray], np.ndarray],
                  Q: np.ndarray, plus: Callable = _add, minus: Callable = _sub, alpha: float = 1.0,
                  beta: float = 2.0, kappa: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fixed-interval unscented RTS smoother over one run of T filtered posteriors.

    means (T, n_x) the filter's posterior means; covs (T, n, n) their covariances in the error coordinates of
    plus/minus (plus(x (S, n_x), e (S, n)) -> (S, n_x), minus(x, x_ref) -> (S, n); additive by default);
    step(k, X (S, n_x)) -> (S, n_x) the dynamics from frame k to k + 1; Q (T - 1, n, n) the process noise of
    each step in error coordinates. Sigma points: van der Merwe's scaled set (filtering/ukf.py's weights).
    Returns (smoothed means (T, n_x), smoothed covariances (T, n, n) in error coordinates at the smoothed means,
    gains (T - 1, n, n)). For a linear step and additive coordinates it is the closed-form RTS smoother.
    """
    means, covs, Q = np.asarray(means, dtype=float), np.asarray(covs, dtype=float), np.asarray(Q, dtype=float)
    T, n = covs.shape[0], covs.shape[-1]
    w = merwe_weights(n, alpha, beta, kappa)
    xs, Ps = means.copy(), covs.copy()
    gains = np.zeros((max(T - 1, 0), n, n))
    for k in range(T - 2, -1, -1):
        # sigma points of frame k's posterior in its error coordinates
        L = np.linalg.cholesky((n + w.lam) * _sym(covs[k]))
        E = np.concatenate([np.zeros((1, n)), L.T, -L.T])                 # (2n + 1, n): chi_i = x_k [+] E_i
        Y = step(k, plus(np.broadcast_to(means[k], (2 * n + 1, means.shape[-1])), E))
        # predicted mean: the weighted mean of the propagated points about the central one, then re-centred
        D0 = minus(Y, np.broadcast_to(Y[0], Y.shape))
        x_pred = plus(Y[0][None], (w.Wm @ D0)[None])[0]
        D = minus(Y, np.broadcast_to(x_pred, Y.shape))                  # chi'_i [-] x^-_(k+1)
        d_mean = w.Wm @ D
        Dc = D - d_mean
        P_pred = _sym(np.einsum("s,si,sj->ij", w.Wc, Dc, Dc) + Q[k])     # P^- = sum Wc (chi' - x^-)(.)^T + Q
        C = np.einsum("s,si,sj->ij", w.Wc, E, Dc)                        # C = sum Wc (chi - x)(chi' - x^-)^T
        G = np.linalg.solve(P_pred, C.T).T                               # G = C (P^-)^-1 (P^- symmetric)
        r = minus(xs[k + 1][None], x_pred[None])[0] - d_mean             # x^s_(k+1) [-] x^-_(k+1)
        xs[k] = plus(means[k][None], (G @ r)[None])[0]
        Ps[k] = _sym(covs[k] + G @ (Ps[k + 1] - P_pred) @ G.T)
        gains[k] = G
    return xs, Ps, gains


# ---------------------------------------------------------------------------------------------------------
# The 12-state smoother over a tracker's output


@dataclass(frozen=True)
class SmoothedTrack:
    """A track smoothed segment by segment. x (T, 12) and P (T, 12, 12): smoothed state and covariance (P on
    additive MRP differences at x's set, as the filter's); outside every segment the filter's own (NaN where it
    had none). segment (T,) int: the frame's segment index, -1 outside. trusted (T,) bool: tracking, half-turn
    decided, inside a segment (what may label an image). segments: [(start, stop)] frame ranges."""

    x: np.ndarray
    P: np.ndarray
    segment: np.ndarray
    trusted: np.ndarray
    segments: list


def smooth_track(t_s: np.ndarray, x_hat: np.ndarray, P: np.ndarray, status: np.ndarray, chaser: np.ndarray,
                 q_sigma: tuple[float, float, float, float], n_hypotheses: np.ndarray | None = None,
                 J_T: np.ndarray | None = None, mu_m3_s2: float = MU_EARTH_M3_S2, gravity_gradient: bool = False,
                 max_step_s: float = 1.0) -> SmoothedTrack:
    """Smooth a tracker's output over its tracked segments (module docstring).

    t_s (T,) s; x_hat (T, 12) and P (T, 12, 12) the per-frame posterior (est.npz's x_hat[0], P[0]: NaN where no
    estimate); status (T,) codes (est.npz status[0]); chaser (T, 4) the chaser's orbit (r_m, rdot_m_s, theta_rad,
    thetadot_rad_s) at t_s, as the tracker's chaser_at gives it; q_sigma: the filter's process noise per sqrt(s)
    in the state's four groups (m, m/s, MRP, rad/s: the Tracker's fcfg.q_sigma, its filter's raised to the
    tracker's detector_q_sigma); n_hypotheses (T,) (det.npz's): open half-turn hypotheses per frame; J_T, mu_m3_s2,
    gravity_gradient, max_step_s: the filter's model (as the tracker's `dyn`).
    """
    t_s, x_hat, P = np.asarray(t_s, dtype=float), np.asarray(x_hat, dtype=float), np.asarray(P, dtype=float)
    chaser = np.asarray(chaser, dtype=float)
    J_T = load_inertia_T_kg_m2() if J_T is None else J_T
    q2 = np.repeat(np.square(np.asarray(q_sigma, dtype=float)), 3)
    segments = tracked_segments(status, n_hypotheses)
    x_out, P_out = x_hat.copy(), P.copy()
    seg = np.full(len(t_s), -1, dtype=np.int64)
    for i, (a, b) in enumerate(segments):
        seg[a:b] = i
        if not (np.isfinite(x_hat[a:b]).all() and np.isfinite(P[a:b]).all()):
            raise ValueError(f"frames {a}..{b - 1}: a tracked segment holds a non-finite estimate")
        if b - a < 2:
            continue
        x_seg = x_hat[a:b]
        dt = np.diff(t_s[a:b])

        def step(k: int, X: np.ndarray, a=a, dt=dt) -> np.ndarray:
            return propagate(X, chaser[a + k], float(dt[k]), J_T, mu_m3_s2, max_step_s, gravity_gradient)

        # the filter's Q (additive MRP) in error coordinates at the step's start
        Q = to_error_cov(x_seg[:-1], q2 * np.eye(N_STATE) * dt[:, None, None])
        xs, Ps_e, _ = unscented_rts(x_seg, to_error_cov(x_seg, P[a:b]), step, Q, state_plus, state_minus)
        x_out[a:b] = xs
        P_out[a:b] = from_error_cov(xs, Ps_e)
    return SmoothedTrack(x_out, P_out, seg, trusted_frames(status, n_hypotheses) & (seg >= 0), segments)


# ---------------------------------------------------------------------------------------------------------
# Corner labels of a pose


def corner_labels(x: np.ndarray, camera: PinholeCamera) -> dict:
    """The corner labels of the pose in x (..., 12) (position and attitude used) through `camera`.

    Returns corners_px (..., 8, 2) px (OpenCV convention: pixel centres at integer coordinates); visible
    (..., 8) bool, the box's exact face test from the camera's centre; in_frame (..., 8) bool, in front of the
    camera and inside [-0.5, W - 0.5) x [-0.5, H - 0.5); K (3, 3): decode_label's fields (perception/data.py).
    """
    x = np.asarray(x, dtype=float)
    uv, z_K = project(corners_C_m(x), camera)
    G = mrp_to_dcm(x[..., MRP])
    cam_T = np.einsum("...ij,...j->...i", G, camera.pos_C_m - x[..., :3])  # the camera's centre in T
    in_frame = (z_K > 0) & (uv[..., 0] >= -0.5) & (uv[..., 0] < camera.width_px - 0.5) \
        & (uv[..., 1] >= -0.5) & (uv[..., 1] < camera.height_px - 0.5)
    return {"corners_px": uv, "visible": visible_corners(cam_T, load_geometry()), "in_frame": in_frame,
            "K": camera.K}


def label_record(x: np.ndarray, camera: PinholeCamera) -> dict:
    """One frame's pseudo-label as plain JSON data, read back by perception/data.py's decode_label: corners_px,
    visible, in_frame, K, the pose (R_cam_from_target, t_cam_from_target_m in K) and the state x (12,); the image
    is the user's own, stored as it came (image_stored "corrupted": no corruption is applied on read)."""
    x = np.asarray(x, dtype=float)
    lab = corner_labels(x, camera)
    R_K_T = camera.R_K_from_C @ mrp_to_dcm(x[MRP]).T
    t_K = camera.R_K_from_C @ (x[:3] - camera.pos_C_m)
    return {"corners_px": lab["corners_px"].tolist(), "visible": lab["visible"].tolist(),
            "in_frame": lab["in_frame"].tolist(), "K": lab["K"].tolist(), "R_cam_from_target": R_K_T.tolist(),
            "t_cam_from_target_m": t_K.tolist(), "x": x.tolist(), "image_stored": "corrupted", "corruption": {},
            "source": "pseudo_label"}


def label_sigma_px(x: np.ndarray, P: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """How uncertain each corner label is: the largest 1-sigma (px) of each corner's projection under the
    state's covariance, by the unscented transform. x (N, 12), P (N, 12, 12) (additive MRP, the filter's) ->
    (N, 8) px. A pipeline may refuse labels above a few tenths of a pixel."""
    x, P = np.atleast_2d(np.asarray(x, dtype=float)), np.asarray(P, dtype=float).reshape(-1, N_STATE, N_STATE)
    n = N_STATE
    w = merwe_weights(n)
    L = np.linalg.cholesky((n + w.lam) * _sym(to_error_cov(x, P)))            # (N, 12, 12)
    E = np.concatenate([np.zeros((len(x), 1, n)), np.swapaxes(L, -1, -2), -np.swapaxes(L, -1, -2)], axis=1)
    pts = state_plus(np.broadcast_to(x[:, None], E.shape), E)                   # (N, 25, 12)
    uv, _ = project(corners_C_m(pts), camera)                                     # (N, 25, 8, 2)
    d = uv - np.einsum("s,nsci->nci", w.Wm, uv)[:, None]
    cov = np.einsum("s,nsci,nscj->ncij", w.Wc, d, d)
    return np.sqrt(np.linalg.eigvalsh(cov)[..., -1])
