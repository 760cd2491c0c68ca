"""Running the batched UKF over a measurement history for R runs at once, with the robustness a mission needs.

The filter is steppable: `init_state` makes a FilterState (everything R runs carry between steps), and the pure
`filter_step(state, measurement, setup)` predicts from the state's time to the measurement's (no prediction when
they are equal, as for the first frame at the initial estimate's time), then updates with its corners, and
returns a new state; `run_filter` is the loop of filter_step over a measurement history. FilterSetup holds the
model: measurement kind, camera, inertia, mu and the gravity-gradient switch (take the truth's). Around the pure
steps of filtering/ukf.py a step adds, per run:
- chi-square gating of each corner (rejects a mis-associated corner);
- the measurement in partial updates where the prior is far wider than it (a campaign's or a warm start's first
  step: filtering/step_update.py);
- adaptive measurement noise: the detector's per-corner covariance comes in with the data, and an
  innovation-based scale r_scale (covariance matching: E[y y^T] = H P H^T + R) multiplies it;
- adaptive process noise, residual-based: Q_k = a Q_(k-1) + (1 - a) K y y^T K^T on top of the base Q;
- covariance inflation across outages: Q is multiplied by outage_q_scale while a run gets no measurement;
- never NaN: covariances are repaired (symmetrize, eigenvalue floor); a run whose step still gives a
  non-finite result keeps its previous estimate and is flagged;
- a divergence monitor: the NIS summed over a sliding window against its chi-square bound.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2, load_inertia_T_kg_m2, sigma_step_s
from envisat_pose.filtering.filter_config import FilterConfig, check_kernel
from envisat_pose.filtering.measurements import KINDS, POSE_CORNERS, dim_per_corner, measure, predicted_visible
from envisat_pose.filtering.step_update import measurement_update, uses_fused_kernel
from envisat_pose.filtering.ukf import (
    SigmaWeights,
    chart_error,
    chart_sigma_points,
    merwe_weights,
    predict,
    shadow_switch,
)
from envisat_pose.gates import chi2_bound, chi2_gate
from envisat_pose.geometry import PinholeCamera, load_camera, load_geometry
from envisat_pose.state import nees_window_diverged, nees_window_judged
from envisat_pose.target import Target, VisibilityTable


@dataclass
class FilterResult:
    """Output of `run_filter` for R runs over T steps.

    x_hat (R, T, 12), P (R, T, 12, 12) posteriors; n_meas (R, T) corners used; nis (R, T) (0 without
    measurement); dof (R, T) measured components used; rejected (R, T) corners rejected by the gate;
    diverged (R,) bool; repaired (R,) number of non-finite steps that were rolled back; r_scale (R,) the final
    adaptive measurement-noise scale (1 without adaptive_r); dropped (R, T) measured corners dropped by the
    visibility check (not gate rejections).
    """

    x_hat: np.ndarray
    P: np.ndarray
    n_meas: np.ndarray
    nis: np.ndarray
    dof: np.ndarray
    rejected: np.ndarray
    diverged: np.ndarray
    repaired: np.ndarray
    r_scale: np.ndarray
    dropped: np.ndarray


@dataclass(frozen=True)
class FilterSetup:
    """What stays fixed over a filter run: the settings and the filter's model.

    cfg: the UKF settings. kind: measurement kind (filtering.measurements.KINDS). camera: the chaser camera
    (pixel kinds). J_T: (3, 3) target inertia in T, kg m^2. mu_m3_s2: the Earth's gravitational parameter, m^3/s^2
    (take the truth's). gravity_gradient: the model applies the gravity-gradient torque (as the truth may).
    weights: the sigma-point weights of cfg. gate_threshold: chi-square bound per corner (None: no gate).
    keypoints_T_m: (K, 3) the target's keypoints in T, m, the measured "corners" (ENVISAT's A-H: K = 8).
    visibility: the rule of the visibility check: None, the exact face test of ENVISAT's box
    (geometry.visible_corners, in the fused kernel), or a target's fast table (target.VisibilityTable).
    """

    cfg: FilterConfig
    kind: str
    camera: PinholeCamera
    J_T: np.ndarray
    mu_m3_s2: float
    gravity_gradient: bool
    weights: SigmaWeights
    gate_threshold: float | None
    keypoints_T_m: np.ndarray
    visibility: VisibilityTable | None = None

    @property
    def num_keypoints(self) -> int:
        """K, the number of keypoints the filter measures."""
        return int(self.keypoints_T_m.shape[0])

    def hx(self, x: np.ndarray) -> np.ndarray:
        """The measurement model of all K keypoints, (..., 12) -> (..., K, m)."""
        return measure(x, self.kind, self.camera, self.keypoints_T_m)

    def predicted_visible(self, x: np.ndarray) -> np.ndarray:
        """Which keypoints states x (..., 12) show the chaser: (..., K) bool (filtering.measurements)."""
        return predicted_visible(x, self.visibility)

    def visible_by_prior(self, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
        """The visibility check's answer from a prior (mean (..., 12), cov (..., 12, 12)): (..., K) bool, the
        keypoints shown at its mean, or with cfg.visibility_from "spread" at its mean or any of its sigma points
        (the config's chart's, those the update draws)."""
        if self.cfg.visibility_from == "mean":
            return self.predicted_visible(mean)
        return self.predicted_visible(chart_sigma_points(mean, cov, self.weights, self.cfg.sigma_chart)).any(axis=-2)


def filter_inertia_T_kg_m2(target: Target) -> np.ndarray:
    """The inertia the filter takes of a target, (3, 3) kg m^2 in T: the `fullinertia` its file states, as written
    (as the filter has always read ENVISAT's: load_inertia_T_kg_m2), where it states one that MuJoCo's compiled
    inertia agrees with; MuJoCo's compiled inertia (Target.inertia_T_kg_m2) otherwise."""
    compiled = np.asarray(target.inertia_T_kg_m2, dtype=float)
    try:
        stated = load_inertia_T_kg_m2(target.path)
    except (ValueError, OSError):
        return compiled
    return stated if np.allclose(stated, compiled, rtol=1e-9, atol=0.0) else compiled


def make_setup(cfg: FilterConfig, kind: str, camera: PinholeCamera | None = None, J_T: np.ndarray | None = None,
               mu_m3_s2: float = MU_EARTH_M3_S2, gravity_gradient: bool = False,
               target: Target | None = None) -> FilterSetup:
    """A FilterSetup with the project's defaults: the MJCF's camera, and the target's keypoints and inertia.

    target: the target the filter measures (envisat_pose.target.Target); None: ENVISAT's corners A-H, its inertia
    and the box face test, exactly the filter's numbers before targets existed. J_T, when given, overrides the
    target's inertia."""
    if kind not in KINDS:
        raise ValueError(f"unknown measurement kind {kind!r}; expected one of {KINDS}")
    check_kernel(cfg.kernel)
    gate = chi2_gate(cfg.gate_prob, dim_per_corner(kind)) if cfg.gate_prob > 0 else None
    if target is None:
        keypoints, visibility = load_geometry().corners_T_m, None
        J = load_inertia_T_kg_m2() if J_T is None else J_T
    else:
        keypoints = np.ascontiguousarray(target.keypoints_T_m, dtype=float)
        visibility = target.filter_visibility
        J = filter_inertia_T_kg_m2(target) if J_T is None else J_T
    return FilterSetup(cfg, kind, camera or load_camera(), J, float(mu_m3_s2), bool(gravity_gradient),
                       merwe_weights(12, cfg.alpha, cfg.beta, cfg.kappa), gate, keypoints, visibility)


@dataclass(frozen=True)
class Measurement:
    """The keypoints measured at one time for R runs (K: the setup's keypoints).

    t_s: time, s. chaser: (4,) the chaser's polar orbit at t_s (r_m, rdot_m_s, theta_rad, thetadot_rad_s).
    z: (R, K, m) measurements; mask: (R, K) bool measured keypoints (a non-finite z counts as not measured);
    R_c: per-keypoint noise covariance, broadcastable to (R, K, m, m).
    """

    t_s: float
    chaser: np.ndarray
    z: np.ndarray
    mask: np.ndarray
    R_c: np.ndarray


@dataclass(frozen=True)
class FilterState:
    """Everything R runs carry from one filter step to the next (never mutated: filter_step returns a new one).

    t_s: time of the estimate, s; chaser: (4,) the chaser's orbit at t_s; k: steps taken so far.
    mean (R, 12), cov (R, 12, 12): the posterior at t_s. r_scale (R,): adaptive measurement-noise scale.
    Q_adapt (R, 12, 12): adaptive process noise per second. starved (R,) bool: no measurement used at the last
    step. locked (R,) int: consecutive lockout steps: the gate rejected every corner it was given, or, in a run not
    yet confirmed, more corners than it accepted and enough for a pose of their own (POSE_CORNERS; corners
    dropped by the visibility check never reach the gate: they neither count as rejections nor lock it).
    confirmed (R,) bool: the gate has accepted more corners than it rejected, and a pose's worth, at some step
    after the first (the run agreed with its measurements once: later rejections of most corners are taken for
    faulty corners; the first step's gate spans the initial covariance).
    win_nis, win_dof (W, R): the NIS divergence window (ring buffer, slot k % W). diverged (R,) bool;
    repaired (R,) int: non-finite steps rolled back. The last step's outputs: n_meas (R,) corners used,
    nis (R,) (never negative: an update whose innovation covariance is not positive definite fails instead),
    dof (R,) measured components used, rejected (R,) corners rejected by the gate, dropped (R,) measured corners
    dropped by the visibility check, indefinite (R,) bool: the innovation covariance was not positive definite
    (the update was refused and rolled back to the prediction, and the run flagged diverged).
    """

    t_s: float
    chaser: np.ndarray
    k: int
    mean: np.ndarray
    cov: np.ndarray
    r_scale: np.ndarray
    Q_adapt: np.ndarray
    starved: np.ndarray
    locked: np.ndarray
    confirmed: np.ndarray
    win_nis: np.ndarray
    win_dof: np.ndarray
    diverged: np.ndarray
    repaired: np.ndarray
    n_meas: np.ndarray
    nis: np.ndarray
    dof: np.ndarray
    rejected: np.ndarray
    dropped: np.ndarray
    indefinite: np.ndarray


def chaser_states(r_m, rdot_m_s, theta_rad, thetadot_rad_s) -> np.ndarray:
    """Stack the chaser's polar orbit into (T, 4) = (r_m, rdot_m_s, theta_rad, thetadot_rad_s)."""
    return np.stack([r_m, rdot_m_s, theta_rad, thetadot_rad_s], axis=-1).astype(float)


def init_state(x0_hat: np.ndarray, P0: np.ndarray, t_s: float, chaser: np.ndarray, cfg: FilterConfig) -> FilterState:
    """The state of R runs before their first measurement: x0_hat (R, 12) and P0 (12, 12) or (R, 12, 12) at t_s,
    the chaser's orbit chaser (4,) at t_s. The MRP starts on |p| <= 1."""
    mean = np.array(x0_hat, dtype=float)
    R = mean.shape[0]
    cov = np.broadcast_to(P0, (R, 12, 12)).copy()
    mean, cov = shadow_switch(mean, cov)
    W = cfg.divergence_window
    zeros_i = np.zeros(R, dtype=np.int64)
    return FilterState(t_s=float(t_s), chaser=np.array(chaser, dtype=float), k=0, mean=mean, cov=cov,
                       r_scale=np.ones(R), Q_adapt=np.zeros((R, 12, 12)), starved=np.zeros(R, dtype=bool),
                       locked=zeros_i, confirmed=np.zeros(R, dtype=bool), win_nis=np.zeros((W, R)),
                       win_dof=np.zeros((W, R)),
                       diverged=np.zeros(R, dtype=bool), repaired=zeros_i, n_meas=zeros_i, nis=np.zeros(R),
                       dof=zeros_i, rejected=zeros_i, dropped=zeros_i, indefinite=np.zeros(R, dtype=bool))


def _predict_step(state: FilterState, t_s: float, setup: FilterSetup) -> tuple[np.ndarray, np.ndarray]:
    """The prior at t_s: propagate from state.t_s (none if t_s == state.t_s). Returns (mean, cov)."""
    cfg = setup.cfg
    dt = float(t_s - state.t_s)
    if dt < 0:
        raise ValueError(f"a measurement at t = {t_s} s is older than the filter state (t = {state.t_s} s)")
    if dt == 0:
        return state.mean, state.cov
    Q = cfg.Q(dt)[None] * np.where(state.starved, cfg.outage_q_scale, 1.0)[:, None, None]
    if cfg.adaptive_q:
        Q = Q + state.Q_adapt * dt
    step_s = sigma_step_s(cfg.max_rk4_step_s, state.mean, state.cov, setup.weights.n + setup.weights.lam, dt)
    if uses_fused_kernel(cfg):
        from envisat_pose.filtering import fast  # numba compiles (or loads its cache) on first use

        return fast.predict_fused(state.mean, state.cov, state.chaser, dt, Q, setup, step_s)
    check_kernel(cfg.kernel)
    return predict(state.mean, state.cov, state.chaser, dt, Q, setup.weights, setup.J_T, setup.mu_m3_s2,
                   step_s, setup.gravity_gradient, cfg.sigma_chart)



def predict_to(state: FilterState, t_s: float, setup: FilterSetup) -> tuple[np.ndarray, np.ndarray]:
    """The prior of R runs at t_s (s, not before state.t_s): (mean (R, 12), cov (R, 12, 12)), as the next
    filter_step to t_s computes it. A closed loop uses it before the measurement exists (the predicted corners
    give the detector its region of interest) and hands it back to filter_step as `prior`."""
    return _predict_step(state, t_s, setup)


def filter_step(state: FilterState, meas: Measurement, setup: FilterSetup,
                prior: tuple[np.ndarray, np.ndarray] | None = None) -> FilterState:
    """One filter step of R runs: predict to meas.t_s, then update with its corners. Pure: returns a new state.

    Around the UKF update: visibility check, chi-square gate with the lockout rule, rollback of non-finite
    results, adaptive R and Q, and the windowed NIS divergence monitor (module docstring).
    prior: (mean, cov) from predict_to(state, meas.t_s, setup), when the caller made it already (the step is
    then the same, without predicting twice; several measurement hypotheses can share one prediction).
    """
    cfg = setup.cfg
    mean, cov = prior if prior is not None else _predict_step(state, meas.t_s, setup)
    mean_pred, cov_pred = mean, cov
    z = np.asarray(meas.z, dtype=float)
    m = z.shape[-1]
    R_c = np.broadcast_to(meas.R_c, z.shape + (m,))
    measured = np.asarray(meas.mask, dtype=bool) & np.isfinite(z).all(-1)  # a non-finite detection is a missing one
    gate = setup.gate_threshold
    release = state.locked >= cfg.gate_lockout_steps
    thr = None if gate is None else np.where(release, np.inf, gate)
    restart = release & ~state.confirmed  # released, never confirmed: wrong from its start, P0 on its covariance
    if gate is not None and restart.any():
        cov = np.where(restart[:, None, None], cov + cfg.P0, cov)
    check_kernel(cfg.kernel)
    up = measurement_update(mean, cov, z, measured, R_c, state.r_scale, thr, setup)
    mean, cov, mask_k = up["mean"], up["cov"], up["mask_k"]
    nis, dof, accepted = up["nis"], up["dof"], up["accepted"]
    # never NaN: roll a run back to its prediction (or its previous posterior) and flag it (the fast kernel
    # returns finite results for the runs it finished and says which runs the numpy filter redid: only those
    # can be non-finite)
    suspect = up.get("suspect")
    if suspect is None:
        bad = ~(np.isfinite(mean).all(-1) & np.isfinite(cov).all((-1, -2)))
    else:
        bad = np.zeros(mean.shape[0], dtype=bool)
        if suspect.size:
            bad[suspect] = ~(np.isfinite(mean[suspect]).all(-1) & np.isfinite(cov[suspect]).all((-1, -2)))
    # an innovation covariance that is not positive definite is a failed update, never a negative NIS
    indefinite = np.asarray(up["indefinite"], dtype=bool)
    bad = bad | indefinite | ~(np.isfinite(nis) & (nis >= 0.0))
    repaired, diverged = state.repaired, state.diverged
    if bad.any():
        fallback_ok = np.isfinite(mean_pred).all(-1) & np.isfinite(cov_pred).all((-1, -2))
        fb_mean = np.where(fallback_ok[:, None], mean_pred, state.mean)
        fb_cov = np.where(fallback_ok[:, None, None], cov_pred, state.cov)
        mean = np.where(bad[:, None], fb_mean, mean)
        cov = np.where(bad[:, None, None], fb_cov, cov)
        repaired = repaired + bad
        diverged = diverged | bad
        nis = np.where(bad, 0.0, nis)
        dof = np.where(bad, 0, dof)
        accepted = accepted & ~bad[:, None]  # a rolled-back update used no corner
    used = dof > 0
    r_scale = state.r_scale
    if cfg.adaptive_r:
        # covariance matching: E[y^T y] = tr(H P H^T) + r tr(R)  ->  r estimate, smoothed and bounded
        trR = np.einsum("rcii->r", R_c * accepted[..., None, None])
        r_est = (up["yy"] - up["trPzz"]) / np.maximum(trR, 1e-300)
        r_new = (1 - cfg.adaptive_r_rate) * r_scale + cfg.adaptive_r_rate * r_est
        r_scale = np.where(used, np.clip(r_new, *cfg.adaptive_r_bounds), r_scale)
    Q_adapt = state.Q_adapt
    if cfg.adaptive_q:
        Ky = up["Ky"]
        a = cfg.adaptive_q_memory
        Q_adapt = np.where(used[:, None, None], a * Q_adapt + (1 - a) * Ky[:, :, None] * Ky[:, None, :], Q_adapt)
    locked, confirmed, rejected = lockout_step(state.locked, state.confirmed, mask_k, accepted,
                                               POSE_CORNERS[setup.kind], state.k > 0)
    # divergence monitor: windowed NIS against its chi-square bound, armed at step max(settle, W - 1) as the NEES rule
    W, k = cfg.divergence_window, state.k
    win_nis, win_dof = state.win_nis.copy(), state.win_dof.copy()
    win_nis[k % W] = nis
    win_dof[k % W] = dof
    if k >= max(cfg.divergence_settle_steps, W - 1):  # k: this step's index (0-based), as the NEES rows
        d = win_dof.sum(0)
        bound = np.where(d > 0, _nis_bound(cfg.divergence_prob, np.maximum(d, 1)), np.inf)
        diverged = diverged | (win_nis.sum(0) > bound)
    return FilterState(t_s=float(meas.t_s), chaser=np.array(meas.chaser, dtype=float), k=k + 1, mean=mean, cov=cov,
                       r_scale=r_scale, Q_adapt=Q_adapt, starved=~used, locked=locked, confirmed=confirmed,
                       win_nis=win_nis, win_dof=win_dof, diverged=diverged, repaired=repaired, n_meas=accepted.sum(-1),
                       nis=nis, dof=dof, rejected=rejected, dropped=(measured & ~mask_k).sum(-1),
                       indefinite=indefinite)


def lockout_step(locked: np.ndarray, confirmed: np.ndarray, mask_k: np.ndarray, accepted: np.ndarray,
                 pose_corners: int, can_confirm: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gate's lockout bookkeeping after a step (FilterState.locked, .confirmed): (locked, confirmed, rejected)
    of R runs from the last ones and the corners that reached the gate, mask_k (R, K), and those it accepted.

    A lockout step: the gate rejected every corner it saw, or, in a run never confirmed, most of them and at least
    pose_corners (one wrong pose fits a corner or two, so "every corner" never came). Once confirmed (a step that
    accepted most corners and a pose's worth, can_confirm: not a run's first step, whose gate spans its initial
    covariance and accepts a wrong start's corners too), rejecting most corners is taken for faulty corners: a
    majority of outliers must not open the gate. Corners the visibility check dropped never reach the gate."""
    rejected, n_acc = (mask_k & ~accepted).sum(-1), accepted.sum(-1)
    wrong_start = ~confirmed & (rejected >= pose_corners) & (rejected > n_acc)
    locked = np.where((mask_k.any(-1) & (n_acc == 0)) | wrong_start, locked + 1, 0)
    return locked, confirmed | ((n_acc > rejected) & (n_acc >= pose_corners) & can_confirm), rejected


@functools.lru_cache(maxsize=8)
def _nis_bound_table(prob: float, n: int) -> np.ndarray:
    """chi2_bound(prob, d) for d = 0 .. n - 1 (entry 0 unused), computed once: the same values, per element."""
    return chi2_bound(prob, np.maximum(np.arange(n, dtype=float), 1.0))


def _nis_bound(prob: float, d: np.ndarray) -> np.ndarray:
    """chi2.isf(prob, d) for integer-valued dof counts d >= 1 (...,), from a table that grows as needed."""
    top = int(d.max(initial=1)) + 1
    n = 1024
    while n < top:
        n *= 2
    return _nis_bound_table(float(prob), n)[d.astype(np.int64)]


def run_filter(x0_hat: np.ndarray, P0: np.ndarray, t_s: np.ndarray, chaser: np.ndarray, z: np.ndarray,
               mask: np.ndarray, R_c: np.ndarray, kind: str, cfg: FilterConfig, camera: PinholeCamera | None = None,
               J_T: np.ndarray | None = None, mu_m3_s2: float = MU_EARTH_M3_S2, progress: bool = False,
               gravity_gradient: bool = False, target: Target | None = None) -> FilterResult:
    """Filter R runs at once: `filter_step` over the T measurement times.

    x0_hat (R, 12) initial estimates at t_s[0]; P0 (12, 12) or (R, 12, 12); t_s (T,) s; chaser (T, 4) the
    chaser's known orbit at t_s; z (R, T, K, m) measurements; mask (R, T, K) measured keypoints; R_c per-keypoint
    noise covariance, broadcastable to (R, T, K, m, m) (the detector's covariance when it gives one).
    mu_m3_s2 and gravity_gradient: the filter's model (take the truth's, when filtering a simulated truth).
    target: the measured target (make_setup; None: ENVISAT, K = 8).
    """
    setup = make_setup(cfg, kind, camera, J_T, mu_m3_s2, gravity_gradient, target)
    if z.shape[-2] != setup.num_keypoints:
        raise ValueError(f"z holds {z.shape[-2]} keypoints per step; the filter's target has {setup.num_keypoints}")
    R, T, m = z.shape[0], z.shape[1], z.shape[-1]
    R_c = np.broadcast_to(R_c, z.shape + (m,))
    mask = np.broadcast_to(mask, z.shape[:-1])
    state = init_state(x0_hat, P0, t_s[0], chaser[0], cfg)
    x_hat = np.empty((R, T, 12))
    P = np.empty((R, T, 12, 12))
    n_meas = np.zeros((R, T), dtype=np.int64)
    nis = np.zeros((R, T))
    dof = np.zeros((R, T), dtype=np.int64)
    rejected = np.zeros((R, T), dtype=np.int64)
    dropped = np.zeros((R, T), dtype=np.int64)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, unit="step", desc=f"estimate ({R} runs)", mininterval=0.5)
    for k in range(T):
        state = filter_step(state, Measurement(t_s[k], chaser[k], z[:, k], mask[:, k], R_c[:, k]), setup)
        x_hat[:, k], P[:, k] = state.mean, state.cov
        n_meas[:, k], nis[:, k], dof[:, k], rejected[:, k] = state.n_meas, state.nis, state.dof, state.rejected
        dropped[:, k] = state.dropped
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return FilterResult(x_hat, P, n_meas, nis, dof, rejected, state.diverged, state.repaired, state.r_scale, dropped)


def nees(x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray, chart: str = "additive") -> np.ndarray:
    """Normalized estimation error squared e^T P^-1 e, with the MRP error taken on the estimate's set.

    x_true broadcastable to x_hat (..., 12); P (..., 12, 12) in the filter's chart (FilterConfig.sigma_chart;
    "rotation" or "screw": the error of its local chart, filtering.ukf.CHART_MAPS). Returns (...,).
    """
    e = chart_error(x_true, x_hat, chart)
    return np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])


def diverged_against_truth(nis_diverged: np.ndarray, nees_rt: np.ndarray, cfg: FilterConfig) -> np.ndarray:
    """The divergence rule of runs whose truth is known (the one home of it): a run diverged when the filter's own
    NIS monitor flagged it, or when its NEES averaged over a sliding window of cfg.divergence_window steps is
    above cfg.nees_divergence_factor x 12 after the settle steps (envisat_pose.state.nees_window_diverged).

    Estimation errors are strongly correlated in time, so a chi-square bound on a window of NEES values (which
    assumes independent steps) would raise false alarms; the NIS monitor (white innovations) uses one.

    A run too short for a whole window is judged on the window it holds, shortened to the run; one that ends
    before step cfg.divergence_settle_steps is not judged (nor by its NIS monitor, armed from step
    max(settle_steps, window - 1) as the NEES rule; a failed update flags it at any step): False here unless
    flagged, and `unjudged_runs` counts it apart, never as "not diverged".

    nis_diverged (R,) bool (FilterResult.diverged, FilterState.diverged); nees_rt (R, T) (`nees`). Returns (R,) bool.
    """
    return nis_diverged | nees_window_diverged(nees_rt, cfg.divergence_window, cfg.divergence_settle_steps,
                                               cfg.nees_divergence_factor)


def unjudged_runs(diverged: np.ndarray, n_steps: int, cfg: FilterConfig) -> np.ndarray:
    """(R,) bool: the runs diverged_against_truth (diverged) left unflagged without judging them: all of them
    when a run of n_steps ends before step cfg.divergence_settle_steps, where the monitors are armed (a failed
    update flags a run at any step), else none. The callers report them apart from the runs not diverged."""
    diverged = np.asarray(diverged, bool)
    return ~diverged & (not nees_window_judged(n_steps, cfg.divergence_settle_steps))


def nis_alarms_alone(diverged: np.ndarray, nees_rt: np.ndarray, cfg: FilterConfig) -> np.ndarray:
    """(R,) bool: the runs diverged_against_truth flagged (diverged) by the filter alone (its NIS
    monitor, or an update that failed and was rolled back), their NEES within the window rule: false alarms as
    far as the truth can tell. The monitor's window bound has a false-alarm probability of cfg.divergence_prob
    each, so a run of many windows is flagged now and then with nothing wrong (docs/design.md, "Divergence").
    nees_rt (R, T) (`nees`)."""
    return np.asarray(diverged, bool) & ~nees_window_diverged(nees_rt, cfg.divergence_window,
                                                              cfg.divergence_settle_steps, cfg.nees_divergence_factor)
