"""Cold start from images: a pose per frame from the named corners, the half-turn hypotheses, a short batch fit.

No prior and no truth: the tracker buffers the first lit frames with enough named corners and hands them here.

1. `pnp_state`: each frame's named corners (A-H, OpenCV px) give a pose by PnP (SQPnP, then Levenberg-Marquardt
   on the reprojection error): rho (target CoM relative to the chaser, in C, m) and the MRP p of T relative to C.
   The tracker takes it through robust_pnp.robust_pnp: kept bit for bit where every corner passes the fit's gate,
   else solved again by RANSAC over minimal sets, the frame's outlying corners dropped (NaN) from the window.
2. `align_namings`: a detector's naming may flip under the half-turn about the long axis (A<->C, B<->D, E<->G,
   F<->H) from one frame to the next. The poses of one physical hypothesis turn by a few degrees per frame; a
   flip turns them by 180 deg. Each frame takes the naming (the detector's or its half-turn) whose attitude is
   nearer the previous frame's, so the window holds one consistent sequence (hypothesis 0) and its half-turn
   (hypothesis 1). The detector's own half-turn probability of each frame is kept as the appearance cue.
3. `batch_fit`: Gauss-Newton with Levenberg-Marquardt damping on the state at the window's last frame: the
   filter's own dynamics (filtering.dynamics.propagate, RK4, torque-free plus the relative-orbit gravity) carry a
   candidate state back over the window (RK4 sub-steps of at most 1 s, shorter for a fast tumble), the pixel model (filtering.measurements)
   predicts every frame's corners, residuals are whitened by the detector's covariance (times the error model's
   inflation for frame-to-frame correlation), outliers are down-weighted (Huber) and gated. The fit's covariance
   is (J^T W J)^-1, scaled up by the reduced chi-square when the residuals are larger than the covariance says.
   The window is fitted under every naming (NAMINGS: the aligned one and its renaming by each of the box's three
   half-turns; a window whose first frame was named off by the y or z half-turn has its truth under that one);
   their chi-square differ through the dynamics (a half-turn flips the sign of two products of inertia, so only
   one of them is torque-free with the MJCF's inertia tensor).
4. `hypothesis_log_weights`: -chi^2 / 2 of each fit plus the appearance log-likelihoods.

The half-turns above are ENVISAT's box namings; another target's keypoints are renamed by its own symmetries
(pipelines/tracking/namings.py, the `namings` argument of the functions here) in the same steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import dcm_to_mrp, mrp_shadow, mrp_to_dcm
from envisat_pose.filtering.dynamics import propagate, rk4_step_s
from envisat_pose.filtering.measurements import measure
from envisat_pose.geometry import PinholeCamera
from envisat_pose.pipelines.tracking.namings import BOX_NAMES, Namings, box_namings, renamed_state
from envisat_pose.pipelines.tracking.robust_pnp import keypoint_pose, pose_state
from envisat_pose.state import MRP, N_STATE, POS, RATE, VEL


def box_symmetries() -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The box's half-turns about its x, y and z axes (namings.box_namings, from the MJCF's box): name -> (perm
    (8,), S (3, 3), d (3,) m in T) with corner perm[k] = S corner k + d. Each maps the box's corners onto
    themselves, so a naming may be off by any of them. Read-only arrays."""
    n = box_namings()
    return {name: (n.perms[i], n.S[i], n.d[i]) for i, name in enumerate(n.names) if i > 0}


def half_turn() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The half-turn about the long axis (box_symmetries()["x"]): A<->C, B<->D, E<->G, F<->H with the box centred
    on the CoM; the one symmetry the appearance and the inertia tell apart only slowly."""
    return box_symmetries()["x"]


@dataclass(frozen=True)
class FramePose:
    """One buffered frame of the acquisition window.

    t_s: time, s; chaser (4,): the chaser's polar orbit at t_s; z_px (8, 2) the named corners (NaN where not
    found), cov_px (8, 2, 2) their covariance, px^2 (already inflated for correlation); p_alt: the detector's
    probability that the half-turn naming is the right one; x_pnp (12,): the PnP pose (rho, p; velocity and
    rate zero), or None when PnP failed."""

    t_s: float
    chaser: np.ndarray
    z_px: np.ndarray
    cov_px: np.ndarray
    p_alt: float
    x_pnp: np.ndarray | None


def pnp_state(z_px: np.ndarray, corners_T_m: np.ndarray, camera: PinholeCamera, min_corners: int = 4
              ) -> np.ndarray | None:
    """The pose of the named corners z_px (8, 2) (NaN where missing) as a 12-state (rho_C_m, 0, p_mrp, 0), or None
    with fewer than min_corners corners or when PnP fails. corners_T_m (8, 3): A-H in T."""
    ok = np.isfinite(z_px).all(-1)
    if ok.sum() < max(min_corners, 4):
        return None
    pose = keypoint_pose(corners_T_m[ok], z_px[ok], camera.K)
    return None if pose is None else pose_state(*pose, camera)


def half_turn_state(x: np.ndarray) -> np.ndarray:
    """The same physical pose described by the half-turn naming (half_turn: S, d): T' has Gamma' = S Gamma, its
    origin moved by d (rho' = rho + Gamma^T d, zero for a box centred on the CoM) and w' = S w. (..., 12)."""
    return symmetric_state(x, half_turn())


def symmetric_state(x: np.ndarray, symmetry: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """The same physical pose described by the naming a box symmetry (perm, S, d) gives (half_turn_state for any
    of box_symmetries; namings.renamed_state). (..., 12)."""
    return renamed_state(x, symmetry[1], symmetry[2])


def half_turn_naming(z_px: np.ndarray, cov_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The half-turn renaming of corners (8, 2) and covariances (8, 2, 2): corner i takes corner perm[i]."""
    return box_namings().renamed(z_px, cov_px, 1)


NAMINGS = BOX_NAMES  # ENVISAT's corner network's namings (namings.box_namings), by index


def renamed_window(frames: list[FramePose], naming: int, namings: Namings | None = None) -> list[FramePose]:
    """The window's frames under naming (an index of namings, None: ENVISAT's box_namings): keypoints,
    covariances and PnP poses renamed, the half-turn probability taken as namings.aligned_p_alt says (the
    long-axis half-turn's 1 - p for ENVISAT's: only the renaming by the half-turn it speaks of turns it)."""
    nm = namings or box_namings()
    if naming == 0:
        return list(frames)
    perm = nm.perms[naming]
    p_alt = (lambda p: 1.0 - p) if nm.half_turn_prob and naming == 1 else (lambda p: p)
    return [FramePose(f.t_s, f.chaser, f.z_px[perm], f.cov_px[perm], p_alt(f.p_alt),
                      None if f.x_pnp is None else nm.state(f.x_pnp, naming)) for f in frames]


def naming_state(x: np.ndarray, naming: int, namings: Namings | None = None) -> np.ndarray:
    """The state x described in naming (an index of namings, None: ENVISAT's box_namings)."""
    return (namings or box_namings()).state(x, naming)


def attitude_distance_rad(p_a: np.ndarray, p_b: np.ndarray) -> float:
    """Rotation angle between two MRP attitudes, rad."""
    G = mrp_to_dcm(np.asarray(p_a)) @ mrp_to_dcm(np.asarray(p_b)).T
    return float(np.arccos(np.clip((np.trace(G) - 1.0) / 2.0, -1.0, 1.0)))


def align_namings(frames: list[FramePose], namings: Namings | None = None) -> tuple[list[FramePose], np.ndarray]:
    """One consistent naming through the window (module docstring, 2). Each frame takes the relabeling (the
    detector's naming, or its renaming by one of the target's symmetries, Namings.relabel_*: namings, None:
    ENVISAT's box_namings) whose
    attitude is nearest the previous frame's: the detector's names may be off by any of the symmetries, and a
    physical tumble turns the body by a few degrees between frames, never by a symmetry's angle. Returns the frames
    renamed (their x_pnp follows; p_alt as namings.aligned_p_alt: for ENVISAT's, 1 - p under the long-axis
    half-turn and 0.5 under the others, which its half-turn probability says nothing about) and renamed (N,)
    bool. The first frame keeps the detector's naming."""
    nm = namings or box_namings()
    out, renamed, ref = [], [], None
    for fr in frames:
        best = None
        if ref is not None and fr.x_pnp is not None:
            dist = [attitude_distance_rad(nm.relabeled_state(fr.x_pnp, r)[MRP], ref) for r in range(nm.relabel_count)]
            r = int(np.argmin(dist[1:])) + 1 if nm.relabel_count > 1 else 0
            if r and dist[r] < dist[0]:
                best = r
        if best is not None:
            perm = nm.relabel_perms[best]
            fr = FramePose(fr.t_s, fr.chaser, fr.z_px[perm], fr.cov_px[perm],
                           nm.aligned_p_alt(fr.p_alt, int(nm.relabel_class[best])), nm.relabeled_state(fr.x_pnp, best))
        if fr.x_pnp is not None:
            ref = fr.x_pnp[MRP]
        out.append(fr)
        renamed.append(best is not None)
    return out, np.array(renamed)


def initial_guess(frames: list[FramePose]) -> np.ndarray:
    """A first state at the last frame from the PnP poses, robust to a few mis-named frames: the relative rate
    (rad/s, T) the median of the consecutive pairs' rotation rates; the attitude that of the last frame whose step
    from its predecessor agrees with that rate (an isolated wrong pose is never the anchor), carried to the last
    frame at the rate; the position (m, C) and velocity (m/s) a straight-line fit of the positions through their
    median residual's inliers."""
    from scipy.spatial.transform import Rotation

    have = [f for f in frames if f.x_pnp is not None]
    t = np.array([f.t_s for f in have])
    pos = np.array([f.x_pnp[POS] for f in have])
    x = have[-1].x_pnp.copy()
    if len(have) < 2 or not np.ptp(t) > 0:
        return x
    # Gamma' = -[w_r x] Gamma (v_T = Gamma v_C): Gamma_k Gamma_(k-1)^T ~ exp(-[w_r x] dt) for each pair
    rates = np.array([-Rotation.from_matrix(mrp_to_dcm(b.x_pnp[MRP]) @ mrp_to_dcm(a.x_pnp[MRP]).T).as_rotvec()
                      / (b.t_s - a.t_s) for a, b in zip(have[:-1], have[1:])])
    w = np.median(rates, axis=0)
    agree = np.linalg.norm(rates - w, axis=1) <= 3.0 * np.median(np.linalg.norm(rates - w, axis=1)) + 1e-9
    anchor = len(have) - 1
    while anchor > 0 and not agree[anchor - 1]:
        anchor -= 1
    G = Rotation.from_rotvec(-w * (t[-1] - t[anchor])).as_matrix() @ mrp_to_dcm(have[anchor].x_pnp[MRP])
    x[MRP] = dcm_to_mrp(G)
    x[RATE] = w
    fit = np.polyfit(t - t[-1], pos, 1)
    resid = np.linalg.norm(pos - (np.outer(t - t[-1], fit[0]) + fit[1]), axis=1)
    inl = resid <= 3.0 * np.median(resid) + 1e-9
    if inl.sum() >= 2 and np.ptp(t[inl]) > 0:
        fit = np.polyfit(t[inl] - t[-1], pos[inl], 1)
    x[VEL], x[POS] = fit[0], fit[1]
    return x


def _propagate_back(x_end: np.ndarray, t_end: float, times: np.ndarray, chaser_at, dyn: dict) -> np.ndarray:
    """States at `times` (N,) (sorted, <= t_end) from x_end (B, 12) at t_end, through the filter's dynamics in
    RK4 sub-steps of at most max_step_s, shorter for a fast tumble (dynamics.rk4_step_s). Returns (B, N, 12)."""

    B = x_end.shape[0]
    out = np.empty((B, len(times), N_STATE))
    x, t = x_end.copy(), float(t_end)
    step_s = rk4_step_s(dyn["max_step_s"], float(np.max(np.linalg.norm(x_end[:, RATE], axis=1), initial=0.0)))
    for i in range(len(times) - 1, -1, -1):
        target = float(times[i])
        while t - target > 1e-9:
            h = max(target - t, -step_s)
            x = propagate(x, chaser_at(t), h, dyn["J_T"], dyn["mu_m3_s2"], step_s, dyn["gravity_gradient"])
            x[:, MRP] = mrp_shadow(x[:, MRP])
            t += h
        out[:, i] = x
    return out


@dataclass(frozen=True)
class BatchFit:
    """A batch fit of one hypothesis: x (12,) at t_s, P (12, 12), chi2 (whitened residuals' sum of squares of the
    kept corners), dof (residual components kept minus 12), used (N, K) bool the keypoints kept, rejected: the
    measured corners the fit's gate dropped."""

    t_s: float
    x: np.ndarray
    P: np.ndarray
    chi2: float
    dof: int
    used: np.ndarray
    rejected: int = 0

    @property
    def valid(self) -> bool:
        """A fit a filter can start from: more residuals kept than states, a finite positive-definite P."""
        if self.dof <= 0 or not (np.isfinite(self.x).all() and np.isfinite(self.P).all()):
            return False
        return bool(np.linalg.eigvalsh(self.P).min() > 0.0)


def batch_fit(frames: list[FramePose], x_guess: np.ndarray, chaser_at, camera: PinholeCamera, dyn: dict,
              iterations: int = 15, huber: float = 3.0, gate: float | None = None,
              keypoints_T_m: np.ndarray | None = None) -> BatchFit:
    """Gauss-Newton / Levenberg-Marquardt fit of the state at the last frame (module docstring, 3): batch_fits of
    one window."""
    return batch_fits([frames], np.asarray(x_guess, float)[None], chaser_at, camera, dyn, iterations, huber, gate,
                      keypoints_T_m)[0]


def batch_fits(windows: list[list[FramePose]], x_guess: np.ndarray, chaser_at, camera: PinholeCamera, dyn: dict,
               iterations: int = 15, huber: float = 3.0, gate: float | None = None,
               keypoints_T_m: np.ndarray | None = None) -> list[BatchFit]:
    """Gauss-Newton / Levenberg-Marquardt fits of the state at the last frame (module docstring, 3) of H windows
    of the same frame times (one window under each naming), from x_guess (H, 12): each fit as it would be alone,
    the windows' candidate states carried back through the dynamics together (one propagation per step for all of
    them: a cold start costs about what one fit did).

    chaser_at(t_s) -> (4,) the chaser's polar orbit; dyn: J_T, mu_m3_s2, gravity_gradient, max_step_s; huber:
    the whitened residual norm per keypoint beyond which a keypoint is down-weighted; gate: chi-square bound per
    keypoint beyond which it is dropped after the first iterations (None: gates.chi2_gate(GATE_PROB, 2));
    keypoints_T_m: (K, 3) the target's keypoints (None: ENVISAT's corners A-H)."""
    from envisat_pose.gates import GATE_PROB, chi2_gate

    gate = chi2_gate(GATE_PROB, 2) if gate is None else float(gate)
    H = len(windows)
    times = np.array([f.t_s for f in windows[0]])
    t_end = float(times[-1])
    z = np.stack([np.stack([f.z_px for f in w]) for w in windows])  # (H, N, K, 2)
    meas = np.isfinite(z).all(-1)
    cov = np.stack([np.stack([f.cov_px for f in w]) for w in windows])
    L_inv = np.linalg.inv(np.linalg.cholesky(np.where(meas[..., None, None], cov, np.eye(2))))  # (H, N, K, 2, 2)
    steps = np.array([1e-3] * 3 + [1e-4] * 3 + [1e-5] * 3 + [1e-6] * 3)
    probe = np.concatenate([np.zeros((1, N_STATE)), np.diag(steps)])  # the state, then one step per component

    def whitened(X: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """(h, B, 12) states at t_end of the windows idx (h,) -> whitened residuals (h, B, N, K, 2) (0 where not
        measured)."""
        h, B = X.shape[:2]
        uv = measure(_propagate_back(X.reshape(h * B, N_STATE), t_end, times, chaser_at, dyn), "pixels", camera,
                     keypoints_T_m)
        uv = uv.reshape((h, B) + uv.shape[1:])
        r = np.where(meas[idx][:, None, ..., None], z[idx][:, None] - uv, 0.0)
        return np.einsum("hnkij,hbnkj->hbnki", L_inv[idx], r)

    x = np.array(x_guess, dtype=float).reshape(H, N_STATE)
    keep = meas.copy()
    lam = np.full(H, 1e-3)
    active = np.ones(H, bool)
    for it in range(iterations):
        idx = np.flatnonzero(active)
        if not idx.size:
            break
        W = whitened(x[idx][:, None] + probe[None], idx)
        r0 = W[:, 0]
        J = (W[:, 1:] - r0[:, None]) / steps[None, :, None, None, None]  # (h, 12, N, K, 2)
        norm = np.linalg.norm(r0, axis=-1)
        if it >= 3:
            keep[idx] = meas[idx] & (norm ** 2 < gate)
        w = np.where(keep[idx], np.minimum(1.0, huber / np.maximum(norm, 1e-12)), 0.0)  # IRLS Huber weights
        Jm = np.swapaxes((J * np.sqrt(w)[:, None, ..., None]).reshape(len(idx), N_STATE, -1), 1, 2)
        rm = (r0 * np.sqrt(w)[..., None]).reshape(len(idx), -1)
        Hm = np.einsum("hmi,hmj->hij", Jm, Jm)
        g = np.einsum("hmi,hm->hi", Jm, rm)
        cost0 = np.einsum("hm,hm->h", rm, rm)
        D = np.zeros_like(Hm)
        D[:, np.arange(N_STATE), np.arange(N_STATE)] = np.diagonal(Hm, axis1=1, axis2=2) + 1e-12
        x_new, cost1 = x[idx].copy(), np.full(len(idx), np.inf)
        pending = np.ones(len(idx), bool)
        while pending.any():  # Levenberg-Marquardt: raise each window's damping until its step lowers its cost
            p = np.flatnonzero(pending)
            dx = np.linalg.solve(Hm[p] + lam[idx[p]][:, None, None] * D[p], -g[p][..., None])[..., 0]
            xp = x[idx[p]] + dx
            xp[:, MRP] = mrp_shadow(xp[:, MRP])
            rp = whitened(xp[:, None], idx[p])[:, 0]
            x_new[p], cost1[p] = xp, np.sum(w[p][..., None] * rp ** 2, axis=(1, 2, 3))
            done = (cost1[p] <= cost0[p]) | (lam[idx[p]] > 1e8)
            lam[idx[p[~done]]] *= 10.0
            pending[p[done]] = False
        better = cost1 <= cost0
        x[idx[better]] = x_new[better]
        lam[idx[better]] = np.maximum(lam[idx[better]] / 10.0, 1e-9)
        if it >= 4:
            active[idx[np.abs(cost0 - cost1) < 1e-6 * np.maximum(cost0, 1.0)]] = False
    W = whitened(x[:, None] + probe[None], np.arange(H))
    return [fit_statistics(t_end, x[h], W[h], steps, meas[h], gate) for h in range(H)]


def fit_statistics(t_s: float, x: np.ndarray, W: np.ndarray, steps: np.ndarray, meas: np.ndarray, gate: float
                   ) -> BatchFit:
    """The BatchFit of a converged state x (12,) at t_s: W (13, N, K, 2) the whitened residuals of x and of x
    moved by each of steps (12,), meas (N, K) the keypoints measured. Keypoints beyond the gate are not kept; P is
    (J^T J)^-1 of the kept ones, scaled up by the reduced chi-square when it exceeds 1."""
    r0 = W[0]
    norm2 = np.sum(r0 ** 2, axis=-1)
    keep = meas & (norm2 < gate)
    J = ((W[1:] - r0[None]) / steps[:, None, None, None])[:, keep].reshape(N_STATE, -1).T
    chi2 = float(norm2[keep].sum())
    dof = int(2 * keep.sum() - N_STATE)
    P = np.linalg.pinv(J.T @ J)
    if dof > 0:
        P = P * max(1.0, chi2 / dof)  # residuals larger than their covariance: the fit is less certain than H says
    return BatchFit(t_s, x, 0.5 * (P + P.T), chi2, dof, keep, int(meas.sum() - keep.sum()))


def appearance_log_likelihood(frames: list[FramePose], clip: float, namings: Namings | None = None) -> np.ndarray:
    """(N,) log-likelihoods of the aligned window under each naming of namings (None: ENVISAT's box_namings;
    Namings.log_likelihood summed over the frames: one frame never decides alone)."""
    nm = namings or box_namings()
    return np.array([sum(nm.log_likelihood(f.p_alt, h, clip) for f in frames) for h in range(nm.count)])
