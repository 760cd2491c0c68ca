"""The tracker: a corner detector and the UKF joined into one object that takes a user's frames and no truth.

    tracker = Tracker(camera, detector, chaser_at, TrackerConfig())
    for t_s, image in frames:
        est = tracker.step(t_s, image)      # TrackEstimate: state, covariance, status, hypotheses, detections

No truth enters anywhere: the API takes images, their times, the camera, the detector and the chaser's own orbit
(known on board: `chaser_at(t_s) -> (r_m, rdot_m_s, theta_rad, thetadot_rad_s)`). The detector is any object with
`detect(image, K, roi_px=None, prior_R_cam_from_target=None, prior_t_cam_from_target_m=None) -> FrameDetection`
(perception.detect.Detector; the priors are the tracker's prediction, in the camera frame K). A caller may hand
in a prior (`prior=(x0, P0, t0)`, `envisat run --warm-start` for filter studies); by default the tracker starts
cold.

States (TrackEstimate.status):
- "acquiring": no filter yet. Each lit frame's named corners give a PnP pose (pipelines/acquisition.py); once
  `acquire_frames` frames with a pose are buffered (a gap longer than `max_gap_s` restarts the buffer), the
  window is aligned to one naming, both half-turn hypotheses are batch-fitted with the filter's dynamics, and a
  bank of UKFs starts, one run per hypothesis whose fit is valid, with the fits' states and covariances and
  their log weights (fit chi-square, the gate's bound per rejected corner, and the detector's appearance cues);
  when neither fit is valid (every corner rejected: no covariance to start from) the older half of the window
  is dropped and acquisition goes on. The estimate while acquiring is the last PnP pose with a
  wide covariance (ACQUIRING_SIGMA).
- "tracking": each frame the bank predicts; once the best hypothesis' prior is tight the detector looks only in
  the predicted region of interest, with the predicted pose as its naming's start and half-turn prior. Each
  hypothesis takes the naming (the detector's or its half-turn) nearest its predicted corners, filter_step
  updates all of them at once (gate, visibility check, adaptive R), and its log weight gains -cost/2 (cost: NIS
  plus the gate bound per rejected or dropped corner, ~ -2 log likelihood) plus the appearance log-likelihood of
  the naming it took.
  A hypothesis whose probability falls below 1 - `decided` is dropped.
- "lost": the best hypothesis' windowed NIS exceeded its chi-square bound (the filter's divergence monitor), or
  the gate rejected every corner for `lost_after_frames` frames with corners found: the bank is discarded and the
  tracker acquires again from the images (no covariance widening).

The filter's R is the detector's calibrated covariance, rescaled to the error model's own scale (measured on
held-out sequences in the loop's regime, where the errors are not those of the random views the detector's
scale was fitted on: `sequence_scale`), times an inflation for the errors' frame-to-frame
correlation, from the error model `envisat calibrate` measured and stored in the weights' metadata
(`detector.error_model`: white noise plus an AR(1) part of share a and correlation time T). The inflation a
filter needs depends on how many frames it averages (perception/errormodel.memory_inflation): with the
`correlation_model` "filter_memory" (default) the tracker reads its memory lambda from its own last update,
lambda = (det P_post / det P_prior)^(1/6) over position and attitude (1 - K for a scalar filter), and takes
tau(lambda) = 1 + 2 a phi lambda / (1 - phi lambda). The errors' correlation falls with the view's rotation
rather than with time (measured: `envisat calibrate` fits rho(theta) = a exp(-theta / theta_c) over the angle
the view turned between two frames): with `correlation_in` "rotation" phi = exp(-|w_r| dt / theta_c) at the
tracked rate |w_r| (the camera is fixed in C, so the view turns at the target's rate relative to C); with "time"
(default) and while acquiring, before any rate is estimated, phi = exp(-dt / T) at the frame interval from the
model's time fit (the more conservative for a fast tumble: the TrackerConfig doc says why it is the default). The cold start's window of n frames uses lambda = (n - 1) / (n + 1), the exponential
average of the same effective length. "long_memory" takes the limit lambda = 1 (conservative), "white" no
inflation. A detector without an error model is taken at its covariance.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from envisat_pose.config import check
from envisat_pose.filtering.estimator import FilterConfig, FilterState, Measurement, filter_step, init_state, \
    make_setup, predict_to
from envisat_pose.filtering.measurements import to_camera_K
from envisat_pose.geometry import PinholeCamera, load_geometry
from envisat_pose.pipelines.acquisition import (BatchFit, FramePose, align_namings, appearance_log_likelihood,
                                                 batch_fit, half_turn_naming, half_turn_state, initial_guess,
                                                 pnp_state)
from envisat_pose.state import MRP, N_STATE, POS, RATE
from envisat_pose.status import STATUSES  # noqa: F401 (re-exported for callers of the tracker)

CORRELATION_MODELS = ("filter_memory", "long_memory", "white")
CORRELATION_IN = ("rotation", "time")
POSE = np.r_[POS, MRP]  # the directions each frame measures: position and attitude
# the covariance reported while acquiring (no filter yet): position m, velocity m/s, MRP, rate rad/s (1-sigma)
ACQUIRING_SIGMA = (5.0, 1.0, 0.5, 0.1)
# the filter settings the tracker starts from (under a scenario's [filter] table and the user's): adaptive R that
# only ever raises R above the detector's modelled covariance, and no gate lockout (a lost track is re-acquired
# from the images instead of taking one frame ungated)
TRACKER_FILTER = {"adaptive_r": True, "adaptive_r_bounds": (1.0, 100.0), "gate_lockout_steps": 1_000_000}


@dataclass(frozen=True)
class TrackerConfig:
    """How the tracker uses the detector and the filter.

    acquire_frames: lit frames with a PnP pose in the cold-start window; acquire_min_corners: named corners a
    frame needs for a pose; max_gap_s: a longer gap between buffered frames restarts the window.
    decided: a half-turn hypothesis whose probability exceeds this wins and the other is dropped.
    appearance_clip: the detector's per-frame half-turn probability is clipped to [clip, 1 - clip].
    appearance_frames: consecutive frames whose appearance cues count as one independent look (each frame's
    log-likelihood is divided by it): the detector's half-turn errors repeat from frame to frame while the view
    changes little (measured: on a default-scenario sequence it preferred the wrong half-turn at 0.6-0.98 in 16
    of 20 consecutive frames), so summing them as independent would let one look outvote the dynamics.
    fit_iterations, fit_huber (whitened px), fit_gate (chi-square per corner): the batch fit.
    roi: look only in the predicted region of interest once converged; roi_margin: its side over the predicted
    corners' extent (plus 6 x the prior's pixel sigma); roi_min_side_px; roi_min_corners: fewer corners found
    there and the coarse pass runs again. converged_pos_sigma_m / converged_att_sigma_deg: the prior counts as
    converged (ROI, attitude prior) below these. prior_attitude: give the detector the predicted attitude;
    prior_pose: with it, the predicted position too, so its naming starts from the predicted pose instead of
    searching every face hypothesis (half of the detector's time in the loop; the search still runs when the
    predicted pose matches fewer than 4 corners).
    lost_after_frames: frames in a row with every corner rejected that declare the track lost.
    correlation_model: how R allows for the errors' frame-to-frame correlation (module doc): "filter_memory",
    "long_memory" or "white".
    correlation_in: what the correlation falls with between frames: "time" (default: the time fit, one
    correlation time pooled over the held-out tumble rates) or "rotation" (the view's, at the tracked rate |w_r|,
    where the error model measured it; time while acquiring, before a rate is estimated). "rotation" fits the
    held-out sequences better but was over-confident in the closed loop on a seed where the detector's bias was
    larger (bench/results/tracking_rotation_seed12.json: mean NEES 31.8 on stress-tumble against 17.7 with "time").
    correct_scale: undo the detector's measured apparent scale (error model's bias_scale) about the corners'
    centroid. Off by default: the scale depends on the look (measured on a held-out default sequence, seed 5:
    range bias +0.6 cm without the correction, +9.3 cm with the then shipped 1.0013).
    """

    acquire_frames: int = 20
    acquire_min_corners: int = 4
    max_gap_s: float = 30.0
    decided: float = 0.999
    appearance_clip: float = 0.05
    appearance_frames: float = 10.0
    fit_iterations: int = 15
    fit_huber: float = 3.0
    fit_gate: float = 23.0
    roi: bool = True
    roi_margin: float = 1.4
    roi_min_side_px: int = 64
    roi_min_corners: int = 4
    converged_pos_sigma_m: float = 0.2
    converged_att_sigma_deg: float = 2.0
    prior_attitude: bool = True
    prior_pose: bool = True
    lost_after_frames: int = 10
    correct_scale: bool = False
    correlation_model: str = "filter_memory"
    correlation_in: str = "time"

    def validate(self, prefix: str = "tracker") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.acquire_frames >= 3, f"{p}acquire_frames", self.acquire_frames, "at least 3 frames")
        check(4 <= self.acquire_min_corners <= 8, f"{p}acquire_min_corners", self.acquire_min_corners, "4 to 8 corners")
        check(self.max_gap_s > 0, f"{p}max_gap_s", self.max_gap_s, "a positive gap in s")
        check(0.5 < self.decided < 1.0, f"{p}decided", self.decided, "a probability in (0.5, 1)")
        check(0.0 < self.appearance_clip < 0.5, f"{p}appearance_clip", self.appearance_clip, "a probability in (0, 0.5)")
        check(self.appearance_frames >= 1.0, f"{p}appearance_frames", self.appearance_frames, "at least 1 frame")
        check(self.fit_iterations >= 1, f"{p}fit_iterations", self.fit_iterations, "at least 1")
        check(self.fit_huber > 0, f"{p}fit_huber", self.fit_huber, "a positive whitened residual")
        check(self.fit_gate > 0, f"{p}fit_gate", self.fit_gate, "a positive chi-square bound")
        check(self.roi_margin >= 1.0, f"{p}roi_margin", self.roi_margin, "a factor >= 1")
        check(16 <= self.roi_min_side_px <= 4096, f"{p}roi_min_side_px", self.roi_min_side_px, "a side in [16, 4096] px")
        check(1 <= self.roi_min_corners <= 8, f"{p}roi_min_corners", self.roi_min_corners, "1 to 8 corners")
        check(self.converged_pos_sigma_m > 0, f"{p}converged_pos_sigma_m", self.converged_pos_sigma_m,
              "a positive sigma in m")
        check(self.converged_att_sigma_deg > 0, f"{p}converged_att_sigma_deg", self.converged_att_sigma_deg,
              "a positive sigma in deg")
        check(self.lost_after_frames >= 1, f"{p}lost_after_frames", self.lost_after_frames, "at least 1 frame")
        check(self.correlation_model in CORRELATION_MODELS, f"{p}correlation_model", self.correlation_model,
              f"one of {', '.join(CORRELATION_MODELS)}")
        check(self.correlation_in in CORRELATION_IN, f"{p}correlation_in", self.correlation_in,
              f"one of {', '.join(CORRELATION_IN)}")


@dataclass(frozen=True)
class TrackEstimate:
    """What the tracker says after one frame.

    t_s: frame time, s. status: one of STATUSES. x_hat (12,): the best hypothesis' state (rho_C_m, rhodot_C_m_s,
    p_mrp, w_r_T_rad_s); P (12, 12) its covariance (ACQUIRING_SIGMA while acquiring; NaN before any pose).
    hypotheses (H, 12) and probabilities (H,): the half-turn hypotheses still open (H = 0 while acquiring).
    detection: the detector's FrameDetection (None when no image); naming: which naming the best hypothesis took
    (0 the detector's, 1 its half-turn, -1 none); measured (8,) bool: corners given to the filter; rejected (8,)
    bool: of those, rejected by the gate; nis, nis_dof: the best hypothesis' update. roi_px (3,) or None.
    converged: the prior was tight enough for the region of interest. events: what happened this frame
    ("started", "hypothesis decided", "lost", ...). timing_s: detection and filtering, s.
    """

    t_s: float
    status: str
    x_hat: np.ndarray
    P: np.ndarray
    hypotheses: np.ndarray
    probabilities: np.ndarray
    detection: object | None
    naming: int
    measured: np.ndarray
    rejected: np.ndarray
    nis: float
    nis_dof: int
    roi_px: np.ndarray | None
    converged: bool
    events: tuple[str, ...] = ()
    timing_s: dict = field(default_factory=dict)


def prior_sigmas(cov: np.ndarray) -> tuple[float, float]:
    """(largest position sigma, m; largest attitude sigma, deg) of a covariance (12, 12); the MRP sigma is a
    rotation angle of 4 sigma_p rad (small angles)."""
    pos = float(np.sqrt(np.max(np.linalg.eigvalsh(cov[POS, POS]))))
    att = float(np.degrees(4.0 * np.sqrt(np.max(np.linalg.eigvalsh(cov[MRP, MRP])))))
    return pos, att


def predicted_roi(mean: np.ndarray, cov: np.ndarray, camera: PinholeCamera, cfg: TrackerConfig) -> np.ndarray | None:
    """The detector's region of interest (x0, y0, side) px from a prior (12,), (12, 12): the predicted corners'
    extent x roi_margin plus 6 x the prior's position sigma in pixels; None when no corner is predicted in view."""
    from envisat_pose.filtering.measurements import measure

    uv = measure(mean[None], "pixels", camera)[0]
    w, h = camera.width_px, camera.height_px
    inside = np.isfinite(uv).all(-1) & (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) \
        & (uv[:, 1] < h - 0.5)
    if not inside.any():
        return None
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    sigma_px = camera.f_px * prior_sigmas(cov)[0] / max(float(np.linalg.norm(mean[POS])), 1.0)
    side = max(float(np.max(hi - lo)) * cfg.roi_margin + 6.0 * sigma_px, float(cfg.roi_min_side_px))
    side = int(np.ceil(min(side, 2.0 * max(w, h))))
    x0, y0 = np.round((lo + hi) / 2 - side / 2).astype(int)
    return np.array([x0, y0, side], dtype=np.int64)


def select_runs(state: FilterState, idx: np.ndarray) -> FilterState:
    """The FilterState of the runs idx only (a bank of hypotheses pruned)."""
    idx = np.asarray(idx)
    out = {}
    for f in dataclasses.fields(state):
        v = getattr(state, f.name)
        if f.name in ("win_nis", "win_dof"):
            v = v[:, idx]
        elif isinstance(v, np.ndarray) and f.name != "chaser":
            v = v[idx]
        out[f.name] = v
    return FilterState(**out)


def detector_error_model(detector):
    """The detector's ErrorModel (`envisat calibrate`), or the white default when it has none."""
    from envisat_pose.perception.errormodel import ErrorModel

    em = getattr(detector, "error_model", None)
    return em if isinstance(em, ErrorModel) else ErrorModel()


def sequence_scale(em, detector) -> float:
    """em.cov_scale / the detector's cov_scale: the factor that takes the detector's covariance (calibrated on
    random views) to the scale the error model measured on held-out sequences; 1 without a measured model."""
    det_scale = getattr(getattr(detector, "cfg", None), "cov_scale", None)
    if not em.n_frames or not det_scale or not em.cov_scale > 0:
        return 1.0
    return float(em.cov_scale / det_scale)


def correlation_inflation(em, model: str, lam: float, dt_s: float, rate_rad_s: float | None = None) -> float:
    """The factor on the detector's covariance for the errors' frame-to-frame correlation (module doc): the error
    model em's white + AR(1) errors at frame interval dt_s (s) for a filter of memory lam in [0, 1]. With the
    view turning at rate_rad_s (rad/s) and a correlation in rotation in em, the AR(1) part's coefficient is that
    of the angle turned in dt_s (errormodel.phi_at_rotation); otherwise that of the time (phi_at)."""
    from envisat_pose.perception.errormodel import memory_inflation, phi_at, phi_at_rotation

    if model == "white":
        return 1.0
    if rate_rad_s is not None and em.corr_angle_rad > 0.0:
        a, phi = em.angle_share, phi_at_rotation(em.corr_angle_rad, rate_rad_s, dt_s)
    else:
        a, phi = em.ar1_share, phi_at(em.ar1_phi, em.corr_time_s, dt_s)
    if a <= 0.0:
        return 1.0
    return max(memory_inflation(a, phi, 1.0 if model == "long_memory" else lam), 1.0)


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


class Tracker:
    """Detector + UKF over a user's frames (module docstring). One object per image sequence."""

    def __init__(self, camera: PinholeCamera, detector, chaser_at: Callable[[float], np.ndarray],
                 config: TrackerConfig = TrackerConfig(), filter_config: FilterConfig | None = None,
                 J_T: np.ndarray | None = None, mu_m3_s2: float | None = None, gravity_gradient: bool = False,
                 prior: tuple[np.ndarray, np.ndarray, float] | None = None):
        from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2, load_inertia_T_kg_m2

        config.validate()
        self.cfg = config
        from envisat_pose.pipelines.build import tracker_filter  # only the fields given override the tracker's
        self.fcfg = tracker_filter(filter_config)
        self.fcfg.validate()
        self.camera = camera
        self.detector = detector
        self.chaser_at = chaser_at
        J_T = load_inertia_T_kg_m2() if J_T is None else J_T
        mu = MU_EARTH_M3_S2 if mu_m3_s2 is None else float(mu_m3_s2)
        self.setup = make_setup(self.fcfg, "pixels", camera, J_T=J_T, mu_m3_s2=mu, gravity_gradient=gravity_gradient)
        self.dyn = {"J_T": J_T, "mu_m3_s2": mu, "gravity_gradient": gravity_gradient,
                    "max_step_s": self.fcfg.max_rk4_step_s}
        self.corners_T_m = load_geometry().corners_T_m
        self.error_model = detector_error_model(detector)
        self.cov_factor = sequence_scale(self.error_model, detector)
        self.bias_scale = self.error_model.bias_scale if config.correct_scale else 1.0
        self.memory = window_memory(config.acquire_frames)  # until the filter's first update
        self.dt_s = 0.0  # the last frame interval, s
        self.rate_rad_s: float | None = None  # the tracked |w_r| (the view's rotation rate), rad/s; None acquiring
        self.state: FilterState | None = None
        self.log_w = np.zeros(0)
        self.buffer: list[FramePose] = []
        self.locked_frames = 0
        self.last_pose: np.ndarray | None = None
        self.t_last: float | None = None
        if prior is not None:
            x0, P0, t0 = prior
            self._start(np.asarray(x0, float)[None], np.asarray(P0, float)[None], float(t0), np.zeros(1))

    @property
    def status(self) -> str:
        return "acquiring" if self.state is None else "tracking"

    # ------------------------------------------------------------------ the step

    def step(self, t_s: float, image: np.ndarray | None) -> TrackEstimate:
        """One frame: t_s (s, increasing), image (H, W) uint8 gray, or None (no frame: the filter predicts)."""
        t_s = float(t_s)
        if self.t_last is not None and not t_s > self.t_last:
            raise ValueError(f"frame times must increase: t = {t_s} s after t = {self.t_last} s")
        if self.t_last is not None:
            self.dt_s = t_s - self.t_last
        self.t_last = t_s
        if self.state is None:
            return self._acquire(t_s, image)
        return self._track(t_s, image)

    @property
    def inflation(self) -> float:
        """The factor on the detector's covariance this frame: the sequences' scale times correlation_inflation
        at the filter's memory."""
        rate = self.rate_rad_s if self.cfg.correlation_in == "rotation" else None
        return self.cov_factor * correlation_inflation(self.error_model, self.cfg.correlation_model, self.memory,
                                                       self.dt_s, rate)

    def _detect(self, image, roi=None, R_prior=None, t_prior=None):
        t0 = time.perf_counter()
        pose = {} if t_prior is None else {"prior_t_cam_from_target_m": t_prior}
        fd = self.detector.detect(image, self.camera.K, roi_px=roi, prior_R_cam_from_target=R_prior, **pose)
        return fd, time.perf_counter() - t0

    def _acquire(self, t_s: float, image) -> TrackEstimate:
        events: list[str] = []
        fd, t_det = (None, 0.0) if image is None else self._detect(image)
        t0 = time.perf_counter()
        measured = np.zeros(8, bool)
        if fd is not None:
            z, cov, p_alt = detection_measurement(fd, self.inflation, self.bias_scale)
            measured = np.isfinite(z).all(-1)
            x_pnp = pnp_state(z, self.corners_T_m, self.camera, self.cfg.acquire_min_corners)
            if x_pnp is not None:
                if self.buffer and t_s - self.buffer[-1].t_s > self.cfg.max_gap_s:
                    self.buffer = []
                self.buffer.append(FramePose(t_s, self.chaser_at(t_s), z, cov, p_alt, x_pnp))
                self.last_pose = x_pnp
        if len(self.buffer) >= self.cfg.acquire_frames and self._cold_start():
            events.append("started")
        t_fit = time.perf_counter() - t0
        if self.state is not None:
            return self._estimate(t_s, fd, 0, measured, np.zeros(8, bool), None, False, tuple(events),
                                  {"detection": t_det, "filtering": t_fit})
        P = np.diag(np.repeat(np.square(ACQUIRING_SIGMA), 3))
        x = self.last_pose if self.last_pose is not None else np.full(N_STATE, np.nan)
        if self.last_pose is None:
            P = np.full((N_STATE, N_STATE), np.nan)
        return TrackEstimate(t_s, "acquiring", x.copy(), P, np.zeros((0, N_STATE)), np.zeros(0), fd,
                             0 if measured.any() else -1, measured, np.zeros(8, bool), 0.0, 0, None, False,
                             tuple(events), {"detection": t_det, "filtering": t_fit})

    def _cold_start(self) -> bool:
        """Both half-turn hypotheses fitted over the buffered window; the bank starts at its last frame with the
        hypotheses whose fit is valid (BatchFit.valid), weighted by their fit cost (chi-square plus the gate's
        bound per corner the fit rejected, as while tracking) and appearance. When neither fit is valid the older
        half of the window is dropped and acquisition goes on (False)."""
        frames, _ = align_namings(self.buffer)
        alt = [FramePose(f.t_s, f.chaser, *half_turn_naming(f.z_px, f.cov_px), 1.0 - f.p_alt, half_turn_state(f.x_pnp))
               for f in frames]
        guess = initial_guess(frames)
        fits: list[BatchFit] = []
        for hyp_frames, x_guess in ((frames, guess), (alt, half_turn_state(guess))):
            fits.append(batch_fit(hyp_frames, x_guess, self.chaser_at, self.camera, self.dyn,
                                  self.cfg.fit_iterations, self.cfg.fit_huber, self.cfg.fit_gate))
        log_w = np.array([-0.5 * (f.chi2 + self.cfg.fit_gate * f.rejected) for f in fits]) \
            + appearance_log_likelihood(frames, self.cfg.appearance_clip) / self.cfg.appearance_frames
        ok = np.array([f.valid for f in fits])
        if not ok.any():
            self.buffer = self.buffer[len(self.buffer) // 2:]
            return False
        self.buffer = []
        self._start(np.stack([f.x for f in fits])[ok], np.stack([f.P for f in fits])[ok], fits[0].t_s, log_w[ok])
        return True

    def _reset(self) -> None:
        """Back to acquiring: the bank, the window and the memory dropped."""
        self.state, self.log_w, self.buffer, self.locked_frames = None, np.zeros(0), [], 0
        self.memory = window_memory(self.cfg.acquire_frames)
        self.rate_rad_s = None

    def _start(self, x: np.ndarray, P: np.ndarray, t0: float, log_w: np.ndarray) -> None:
        self.state = init_state(x, P, t0, self.chaser_at(t0), self.fcfg)
        self.log_w = log_w - np.max(log_w)
        self.locked_frames = 0
        self._prune()

    def _prune(self) -> bool:
        p = self.probabilities
        keep = p >= 1.0 - self.cfg.decided
        if keep.all():
            return False
        self.state = select_runs(self.state, np.flatnonzero(keep))
        self.log_w = self.log_w[keep] - np.max(self.log_w[keep])
        return True

    @property
    def probabilities(self) -> np.ndarray:
        w = np.exp(self.log_w - np.max(self.log_w)) if self.log_w.size else self.log_w
        return w / w.sum() if w.size else w

    def _track(self, t_s: float, image) -> TrackEstimate:
        t0 = time.perf_counter()
        events: list[str] = []
        chaser = self.chaser_at(t_s)
        prior = predict_to(self.state, t_s, self.setup)
        best = int(np.argmax(self.log_w))
        if not (np.isfinite(prior[0][best]).all() and np.isfinite(prior[1][best]).all()):
            # a prediction gone non-finite (a long gap through a bad state): the track is lost, acquire again
            fd = None if image is None else self._detect(image)[0]
            est = TrackEstimate(t_s, "lost", np.full(N_STATE, np.nan), np.full((N_STATE, N_STATE), np.nan),
                                np.zeros((0, N_STATE)), np.zeros(0), fd, -1, np.zeros(8, bool), np.zeros(8, bool),
                                0.0, 0, None, False, ("lost",), {})
            self._reset()
            return est
        pos_sig, att_sig = prior_sigmas(prior[1][best])
        self.rate_rad_s = float(np.linalg.norm(prior[0][best, RATE]))  # the view's rotation rate, predicted
        converged = bool(pos_sig < self.cfg.converged_pos_sigma_m and att_sig < self.cfg.converged_att_sigma_deg)
        H = self.state.mean.shape[0]
        z = np.full((H, 8, 2), np.nan)
        cov = np.broadcast_to(np.eye(2), (H, 8, 2, 2)).copy()
        namings = np.full(H, -1)
        appearance = np.zeros(H)
        fd, roi, t_det = None, None, 0.0
        t_filter = time.perf_counter() - t0
        if image is not None:
            if self.cfg.roi and converged:
                roi = predicted_roi(prior[0][best], prior[1][best], self.camera, self.cfg)
            R_prior = t_prior = None
            if converged and self.cfg.prior_attitude and H == 1:  # a prior would decide the open half-turn
                from envisat_pose.attitude import mrp_to_dcm

                R_prior = self.camera.R_K_from_C @ mrp_to_dcm(prior[0][best, MRP]).T  # R_K_from_T
                if self.cfg.prior_pose:
                    t_prior = to_camera_K(prior[0][best, POS], self.camera)  # T's origin in K, m
            fd, t_det = self._detect(image, roi, R_prior, t_prior)
            if roi is not None and int(np.sum(fd.visible)) < self.cfg.roi_min_corners:
                fd, t2 = self._detect(image, None, R_prior, t_prior)
                t_det += t2
                roi = None
            t1 = time.perf_counter()
            zd, cd, p_alt = detection_measurement(fd, self.inflation, self.bias_scale)
            if np.isfinite(zd).all(-1).any():
                za, ca = half_turn_naming(zd, cd)
                uv = self.setup.hx(prior[0])  # (H, 8, 2) predicted corners per hypothesis
                for h in range(H):
                    d0 = np.nanmean(np.linalg.norm(zd - uv[h], axis=-1))
                    d1 = np.nanmean(np.linalg.norm(za - uv[h], axis=-1))
                    namings[h] = int(d1 < d0)
                    z[h], cov[h] = (za, ca) if namings[h] else (zd, cd)
                    clip = self.cfg.appearance_clip
                    pa = float(np.clip(p_alt, clip, 1.0 - clip))
                    appearance[h] = (np.log(pa) if namings[h] else np.log1p(-pa)) / self.cfg.appearance_frames
                cov = np.where(np.isfinite(z).all(-1)[..., None, None], cov, np.eye(2))
            t_filter += time.perf_counter() - t1
        t1 = time.perf_counter()
        mask = np.isfinite(z).all(-1)
        meas = Measurement(t_s, chaser, np.nan_to_num(z), mask, cov)
        rejected = self._rejected(prior, np.nan_to_num(z), mask, cov, best)
        new = filter_step(self.state, meas, self.setup, prior=prior)
        thr = self.setup.gate_threshold if self.setup.gate_threshold is not None else 23.0
        # ~ -2 log likelihood: NIS, the gate's bound per rejected or dropped corner, and log det of the adaptive R
        # scale (a hypothesis that explains its misfit by a larger R pays for it)
        cost = new.nis + thr * (new.rejected + new.dropped) + new.dof * np.log(new.r_scale)
        used = mask.any(-1)
        self.log_w = self.log_w + np.where(used, -0.5 * cost + appearance, 0.0)
        self.log_w -= np.max(self.log_w)
        self.state = new
        b = int(np.argmax(self.log_w))  # the best hypothesis of this frame, before pruning
        if new.n_meas[b] > 0:
            lam = filter_memory(prior[1][b], new.cov[b])
            self.memory = self.memory if lam is None else lam
        found, accepted_none = bool(mask[b].any()), bool(mask[b].any() and new.n_meas[b] == 0)
        self.locked_frames = self.locked_frames + 1 if accepted_none else (0 if found else self.locked_frames)
        lost = bool(new.diverged[b]) or self.locked_frames >= self.cfg.lost_after_frames
        timing = {"detection": t_det, "filtering": t_filter + time.perf_counter() - t1}
        out = dict(fd=fd, naming=int(namings[b]), measured=mask[b], rejected=rejected, roi=roi,
                   converged=converged, timing=timing, nis=float(new.nis[b]), nis_dof=int(new.dof[b]))
        if lost:
            events.append("lost")
            est = self._estimate(t_s, events=tuple(events), status="lost", **out)
            self._reset()
            return est
        if H > 1 and self._prune():
            events.append("hypothesis decided")
        return self._estimate(t_s, events=tuple(events), **out)

    def _rejected(self, prior, z, mask, cov, best) -> np.ndarray:
        """Corners of the best hypothesis the chi-square gate rejects (its own per-corner rule from the prior's
        sigma points; the visibility check's drops count as rejected too)."""
        from envisat_pose.filtering.measurements import predicted_visible
        from envisat_pose.filtering.ukf import sigma_points

        if not mask[best].any() or self.setup.gate_threshold is None:
            return np.zeros(8, bool)
        S = sigma_points(prior[0][best], prior[1][best], self.setup.weights)  # (25, 12)
        uv = self.setup.hx(S)  # (25, 8, 2)
        Wm, Wc = self.setup.weights.Wm, self.setup.weights.Wc
        mu = np.einsum("s,skj->kj", Wm, uv)
        d = uv - mu
        Pzz = np.einsum("s,ski,skj->kij", Wc, d, d) + cov[best] * self.state.r_scale[best]
        y = z[best] - mu
        d2 = np.einsum("ki,ki->k", y, np.linalg.solve(Pzz, y[..., None])[..., 0])
        vis = predicted_visible(prior[0][best]) if self.fcfg.visibility_check else np.ones(8, bool)
        return mask[best] & ((d2 > self.setup.gate_threshold) | ~vis)

    def _estimate(self, t_s, fd, naming, measured, rejected, roi, converged, events, timing, status="tracking",
                  nis=0.0, nis_dof=0) -> TrackEstimate:
        """The best hypothesis' state as a TrackEstimate (the bank as it stands after this frame)."""
        best = int(np.argmax(self.log_w))
        return TrackEstimate(t_s, status, self.state.mean[best].copy(), self.state.cov[best].copy(),
                             self.state.mean.copy(), self.probabilities, fd, naming, np.asarray(measured, bool),
                             np.asarray(rejected, bool), nis, nis_dof, roi, converged, events, timing)

    @classmethod
    def from_scenario(cls, scenario: str = "default", weights: str | None = None, **kw) -> "Tracker":
        """A Tracker for the named scenario's geometry (pipelines.build.tracker_from_scenario: its orbit and
        dynamics, the shipped detector unless weights, the MJCF camera unless camera=)."""
        from envisat_pose.pipelines.build import tracker_from_scenario

        return tracker_from_scenario(scenario, weights, **kw)
