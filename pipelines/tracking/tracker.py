"""The tracker: a corner detector and the UKF joined into one object that takes a user's frames and no truth.

    tracker = Tracker(camera, detector, chaser_at, TrackerConfig())
    for t_s, image in frames:
        est = tracker.step(t_s, image)      # TrackEstimate: state, covariance, status, hypotheses, detections

No truth enters anywhere: the API takes images, their times, the camera, the detector and the chaser's own orbit
(known on board: `chaser_at(t_s) -> (r_m, rdot_m_s, theta_rad, thetadot_rad_s)`). The detector is any object with
`detect(image, K, roi_px=None, prior_R_cam_from_target=None, prior_t_cam_from_target_m=None) -> FrameDetection`
(perception.detect.Detector; the priors are the tracker's prediction, in the camera frame K). A caller may hand
in a prior (`prior=(x0, P0, t0)`, `envisat run --warm-start` for filter studies); by default the tracker starts
cold. Whatever starts a bank, it claims "tracking" only once its own evidence backs the claim.

Statuses (envisat_pose/status.py), per frame:
- "acquiring": no claim. Either no bank yet: each lit frame's named corners give a PnP pose
  (pipelines/tracking/acquisition.py); once `acquire.frames` frames with a pose are buffered (a gap longer than
  `acquire.max_gap_s` restarts the buffer), the window is aligned to one naming and a hypothesis per naming (that one and its
  renaming by each of the box's three half-turns) is batch-fitted with the filter's dynamics; the bank starts
  once a fit passes its integrity tests (it kept most of its window's corners, its chi-square is inside its
  bound, its state is physical: pipelines/tracking/integrity.py), with every twin whose fit is valid and physical beside
  it (a twin just past a bound the passing one is just inside is the window's noise, not evidence); when none
  passes the older half of the window is dropped and acquisition goes on. Or a bank runs but has not yet
  earned a claim: its half-turn is still open, or it has not yet passed `integrity.confirm_frames` frames with
  corners used and a covariance inside the claim.
- "tracking": the bank is decided (one hypothesis) and confirmed, this frame used corners, and the covariance backs
  the claim (3-sigma within `integrity.claim_pos_share` of the range and `integrity.claim_att_deg`).
- "coasting": the confirmed bank predicts without a usable measurement (no image, nothing found, every corner
  rejected) or its covariance is wider than the claim (after an outage). A prediction, never a fix.
- "lost": the evidence contradicted the state this frame: every hypothesis failed its integrity tests (windowed
  NIS beyond its chi-square bound, too many corners rejected, a state that is not physical, an innovation
  covariance that is not positive definite, the filter's divergence monitor), or `integrity.lost_after_frames`
  frames in a row with an image used no corner. The bank is dropped and the tracker acquires again from the images.
Each frame every hypothesis takes the naming nearest its predicted corners and the bank is updated at once
(pipelines/tracking/bank.py); a hypothesis below 1 - `bank.decided` is dropped, and so is one that fails its integrity tests.
Once the best prior is tight the detector looks only in the predicted region of interest, with the predicted pose
as its naming's start and half-turn prior when one hypothesis is left.

The filter's R is the detector's calibrated covariance at the error model's scale, inflated for the errors'
frame-to-frame correlation at the filter's own memory (pipelines/tracking/noise.py). The detector's mean apparent scale
(measured on held-out sequences) is undone in every frame's corners; what a run's own scale leaves (the spread
between looks, x range) is added to the reported variance along the line of sight, never to the gain
(noise.range_consider, TrackerConfig.noise.range_floor and correct_scale).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.config import to_dict
from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2, load_inertia_T_kg_m2
from envisat_pose.filtering.estimator import (
    FilterConfig,
    FilterState,
    Measurement,
    filter_step,
    init_state,
    make_setup,
    predict_to,
)
from envisat_pose.filtering.measurements import measure, predicted_visible, to_camera_K
from envisat_pose.filtering.ukf import sigma_points
from envisat_pose.geometry import PinholeCamera, load_geometry
from envisat_pose.pipelines.tracking.acquisition import (
    NAMINGS,
    BatchFit,
    FramePose,
    align_namings,
    appearance_log_likelihood,
    batch_fit,
    initial_guess,
    naming_state,
    pnp_state,
    renamed_window,
)
from envisat_pose.pipelines.tracking.bank import (
    array_log_likelihood,
    choose_namings,
    frame_discriminates,
    probabilities,
    same_array_end,
    select_runs,
    update_cost,
)
from envisat_pose.pipelines.tracking.build import chaser_from_orbit, tracker_camera, tracker_detector, tracker_filter
from envisat_pose.pipelines.tracking.integrity import (
    EvidenceWindow,
    claim_holds,
    fit_problems,
    pose_sigmas,
    state_problems,
    target_radius_m,
    window_problems,
)
from envisat_pose.pipelines.tracking.noise import (
    correlation_inflation,
    detection_measurement,
    detector_error_model,
    evidence_weight,
    filter_memory,
    nis_sum_dispersion,
    range_consider,
    scale_sigma,
    sequence_cov_factor,
    window_memory,
)
from envisat_pose.pipelines.tracking.onboard import onboard_physics
from envisat_pose.pipelines.tracking.tracker_config import (
    ACQUIRING_SIGMA,
    TRACKER_FILTER,
    RoiConfig,
    TrackerConfig,
    TrackEstimate,
)
from envisat_pose.state import MRP, N_STATE, POS, RATE
from envisat_pose.status import STATUSES

__all__ = ["Tracker", "TrackerConfig", "TrackEstimate", "TRACKER_FILTER", "STATUSES", "predicted_roi",
           "tracker_from_scenario"]


def predicted_roi(mean: np.ndarray, cov: np.ndarray, camera: PinholeCamera, cfg: RoiConfig) -> np.ndarray | None:
    """The detector's region of interest (x0, y0, side) px from a prior (12,), (12, 12): the predicted corners'
    extent x cfg.margin plus 6 x the prior's position sigma in pixels; None when no corner is predicted in view."""

    uv = measure(mean[None], "pixels", camera)[0]
    w, h = camera.width_px, camera.height_px
    inside = np.isfinite(uv).all(-1) & (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) \
        & (uv[:, 1] < h - 0.5)
    if not inside.any():
        return None
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    sigma_px = camera.f_px * pose_sigmas(cov)[0] / max(float(np.linalg.norm(mean[POS])), 1.0)
    side = max(float(np.max(hi - lo)) * cfg.margin + 6.0 * sigma_px, float(cfg.min_side_px))
    side = int(np.ceil(min(side, 2.0 * max(w, h))))
    x0, y0 = np.round((lo + hi) / 2 - side / 2).astype(int)
    return np.array([x0, y0, side], dtype=np.int64)


@dataclasses.dataclass(frozen=True)
class FrameMeasurement:
    """One frame measured for the bank's H hypotheses (Tracker._measure). fd: the FrameDetection (None: no
    image); roi: the region of interest it was detected in, px (None: the whole frame); z: (H, 8, 2) px, each
    hypothesis' naming of the corners (NaN: not measured); cov: (H, 8, 2, 2) px^2; mask: (H, 8) bool corners
    given to the filter; pre: (H, 8) bool corners gated before it (gate.raw); seen: (H,) bool any corner
    measured; namings: (H,) the naming each hypothesis chose (-1: none); appearance: (H,) its appearance
    log-likelihood, nats; rejected: (8,) bool the best hypothesis' rejected corners; t_det, t_filter: s spent
    detecting and in the rest of the measurement."""

    fd: object
    roi: np.ndarray | None
    z: np.ndarray
    cov: np.ndarray
    mask: np.ndarray
    pre: np.ndarray
    seen: np.ndarray
    namings: np.ndarray
    appearance: np.ndarray
    rejected: np.ndarray
    t_det: float
    t_filter: float


class Tracker:
    """Detector + UKF over a user's frames (module docstring). One object per image sequence."""

    def __init__(self, camera: PinholeCamera, detector, chaser_at: Callable[[float], np.ndarray],
                 config: TrackerConfig = TrackerConfig(), filter_config: FilterConfig | dict | None = None,
                 J_T: np.ndarray | None = None, mu_m3_s2: float | None = None, gravity_gradient: bool = False,
                 prior: tuple[np.ndarray, np.ndarray, float] | None = None):
        config.validate()
        self.cfg = config
        fcfg = tracker_filter(filter_config)  # only the fields given override the tracker's
        q = fcfg.q_sigma
        q_detector = config.noise.detector_q_sigma
        self.fcfg = dataclasses.replace(fcfg, q_sigma=tuple(max(a, b) for a, b in zip(q, q_detector)))
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
        self.radius_m = target_radius_m(self.corners_T_m)
        self.error_model = detector_error_model(detector)
        self.cov_factor = sequence_cov_factor(self.error_model, detector)
        self.bias_scale = self.error_model.bias_scale if config.noise.correct_scale else 1.0
        # the range error no frame averages away (noise.scale_sigma), in the reported covariance (range_consider)
        self.scale_sigma = scale_sigma(self.error_model, config.noise.correct_scale) if config.noise.range_floor \
            else 0.0
        self.memory = window_memory(config.acquire.frames)  # until the filter's first update
        self.dt_s = 0.0  # the last frame interval, s
        self.rate_rad_s: float | None = None  # the tracked |w_r| (the view's rotation rate), rad/s; None acquiring
        self.state: FilterState | None = None
        self.log_dyn = np.zeros(0)  # per hypothesis: log-likelihood of its fit and innovations
        self.log_app = np.zeros(0)  # per hypothesis: the detector's appearance log-likelihood, summed
        self.log_array = np.zeros(0)  # per hypothesis: the array cue's log-likelihood, summed
        self.evidence: EvidenceWindow | None = None
        self.confirmed = False
        self.buffer: list[FramePose] = []
        self.coasting_frames = 0
        self.array_against = 0  # array-cue readings in a row against the one hypothesis left
        self.last_pose: np.ndarray | None = None
        self.t_last: float | None = None
        if prior is not None:
            x0, P0, t0 = prior
            self._start(np.asarray(x0, float)[None], np.asarray(P0, float)[None], float(t0), np.zeros(1), np.zeros(1))

    @property
    def status(self) -> str:
        """"acquiring" until a bank is confirmed, then "tracking" (the last frame's own status is in its
        TrackEstimate)."""
        return "tracking" if self.state is not None and self.confirmed else "acquiring"

    @property
    def log_w(self) -> np.ndarray:
        """(H,) the hypotheses' log weights: their fits' and innovations' log-likelihood plus the detector's
        appearance and the array cue, each relative to its best and never below -bank.appearance_max_log and
        -array_cue.max_log (module docstring)."""
        if not self.log_app.size:
            return self.log_dyn
        app = self.log_app - np.max(self.log_app)
        arr = self.log_array - np.max(self.log_array)
        return self.log_dyn + np.maximum(app, -self.cfg.bank.appearance_max_log) \
            + np.maximum(arr, -self.cfg.array_cue.max_log)

    @property
    def probabilities(self) -> np.ndarray:
        return probabilities(self.log_w)

    @property
    def gate_bound(self) -> float:
        """The filter's chi-square gate per corner (the cost of a corner it rejects)."""
        return self.setup.gate_threshold if self.setup.gate_threshold is not None else self.cfg.fit.gate

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
        return self.cov_factor * correlation_inflation(self.error_model, self.cfg.noise.correlation_model, self.memory,
                                                       self.dt_s, self.rate_rad_s, self.cfg.noise.correlation_in)

    @property
    def evidence_weight(self) -> float:
        """The weight of this frame's cost in the bank's dynamics log-likelihoods (bank.evidence_memory)."""
        if self.cfg.bank.evidence_memory == "filter":
            return 1.0
        return evidence_weight(self.error_model, self.cfg.noise.correlation_model, self.memory, self.dt_s,
                               self.rate_rad_s, self.cfg.noise.correlation_in)

    def _detect(self, image, roi=None, R_prior=None, t_prior=None, weigh_namings=True):
        t0 = time.perf_counter()
        pose = {} if t_prior is None else {"prior_t_cam_from_target_m": t_prior}
        if R_prior is not None and not weigh_namings:
            pose["prior_weighs_namings"] = False
        fd = self.detector.detect(image, self.camera.K, roi_px=roi, prior_R_cam_from_target=R_prior, **pose)
        return fd, time.perf_counter() - t0

    # ------------------------------------------------------------------ acquiring

    def _acquire(self, t_s: float, image) -> TrackEstimate:
        events: list[str] = []
        fd, t_det = (None, 0.0) if image is None else self._detect(image)
        t0 = time.perf_counter()
        measured = np.zeros(8, bool)
        if fd is not None:
            z, cov, p_alt = detection_measurement(fd, self.inflation, self.bias_scale)
            measured = np.isfinite(z).all(-1)
            x_pnp = pnp_state(z, self.corners_T_m, self.camera, self.cfg.acquire.min_corners)
            if x_pnp is not None:
                if self.buffer and t_s - self.buffer[-1].t_s > self.cfg.acquire.max_gap_s:
                    self.buffer = []
                self.buffer.append(FramePose(t_s, self.chaser_at(t_s), z, cov, p_alt, x_pnp))
                self.last_pose = x_pnp
        if len(self.buffer) >= self.cfg.acquire.frames:
            events += self._cold_start()
        t_fit = time.perf_counter() - t0
        timing = {"detection": t_det, "filtering": t_fit}
        if self.state is not None:
            return self._estimate(t_s, fd=fd, naming=0, measured=measured, rejected=np.zeros(8, bool), roi=None,
                                  converged=False, events=tuple(events), timing=timing, status="acquiring")
        P = np.diag(np.repeat(np.square(ACQUIRING_SIGMA), 3))
        x = self.last_pose if self.last_pose is not None else np.full(N_STATE, np.nan)
        if self.last_pose is None:
            P = np.full((N_STATE, N_STATE), np.nan)
        return TrackEstimate(t_s=t_s, status="acquiring", x_hat=x.copy(), P=P, hypotheses=np.zeros((0, N_STATE)),
                             probabilities=np.zeros(0), detection=fd, naming=0 if measured.any() else -1,
                             measured=measured, rejected=np.zeros(8, bool), nis=0.0, nis_dof=0, roi_px=None,
                             converged=False, events=tuple(events), timing_s=timing)

    def _cold_start(self) -> list[str]:
        """Every naming of the aligned window fitted (the detector's and its renaming by each of the box's three
        half-turns: acquisition.NAMINGS; a window aligned to a naming off by the y or z half-turn has its truth
        there, which a pair of long-axis twins would miss). When a fit passes its integrity tests
        (integrity.fit_problems, state_problems), the bank starts at the window's last frame with every hypothesis
        whose fit is valid and physical, weighted by their fit cost (chi-square plus the gate's bound per corner
        the fit rejected, as while tracking) and appearance; those below 1 - bank.decided are dropped at once.
        When none passes the older half of the window is dropped and acquisition goes on. Returns the frame's
        events."""
        frames, _ = align_namings(self.buffer)
        guess = initial_guess(frames)
        fits = [batch_fit(renamed_window(frames, h), naming_state(guess, h), self.chaser_at, self.camera, self.dyn,
                          self.cfg.fit.iterations, self.cfg.fit.huber, self.cfg.fit.gate)
                for h in range(len(NAMINGS))]

        def cost(f: BatchFit) -> float:
            return f.chi2 + self.cfg.fit.gate * f.rejected

        log_dyn = np.array([-0.5 * cost(f) for f in fits])
        log_app = appearance_log_likelihood(frames, self.cfg.bank.appearance_clip) / self.cfg.bank.appearance_frames
        state = [state_problems(f.x, f.P, self.camera, self.radius_m, self.cfg.integrity) if f.valid else []
                 for f in fits]  # an invalid fit's problem is fit_problems' own
        problems = [fit_problems(f, len(frames), self.cfg.integrity, self.cfg.acquire.min_corners) or s
                    for f, s in zip(fits, state)]
        ok = np.array([not p for p in problems])
        if not ok.any():
            self.buffer = self.buffer[len(self.buffer) // 2:]
            return [f"cold start refused: {'; '.join(problems[0])}"]
        # Once one fit passes, every twin whose fit is valid and physical starts beside it, failed fit statistics
        # or not: the twins fit the same window, so a chi-square or rejection count just past its bound for one
        # and just inside it for another is the window's noise, not evidence between them (the four twins' costs
        # can lie within 1 % of each other; one started alone was claimed 180 deg off: docs/history.md). The bank
        # weighs them by their fit cost and appearance and drops at once those below 1 - bank.decided, so a far
        # worse fit never starts.
        start = np.array([f.valid and not s for f, s in zip(fits, state)])
        self.buffer = []
        P = np.stack([f.P for f in fits])[start] * self.cfg.acquire.start_cov_factor
        self._start(np.stack([f.x for f in fits])[start], P, fits[0].t_s, log_dyn[start], log_app[start])
        return ["started"]

    def _reset(self) -> None:
        """Back to acquiring: the bank, its evidence, the window and the memory dropped."""
        self.state, self.buffer, self.coasting_frames = None, [], 0
        self.log_dyn, self.log_app, self.log_array = np.zeros(0), np.zeros(0), np.zeros(0)
        self.evidence, self.confirmed = None, False
        self.array_against = 0
        self.memory = window_memory(self.cfg.acquire.frames)
        self.rate_rad_s = None

    def _start(self, x: np.ndarray, P: np.ndarray, t0: float, log_dyn: np.ndarray, log_app: np.ndarray) -> None:
        self.state = init_state(x, P, t0, self.chaser_at(t0), self.fcfg)
        self.log_dyn, self.log_app = log_dyn - np.max(log_dyn), log_app - np.max(log_app)
        self.log_array = np.zeros(len(log_dyn))
        self.evidence = EvidenceWindow.empty(len(log_dyn), self.cfg.integrity.window)
        self.confirmed = False
        self.coasting_frames = 0
        self._keep(self.probabilities >= 1.0 - self.cfg.bank.decided)

    def _keep(self, keep: np.ndarray) -> bool:
        """Keep the hypotheses `keep` (H,) bool of the bank (at least one); True when any was dropped."""
        if keep.all():
            return False
        idx = np.flatnonzero(keep)
        self.state = select_runs(self.state, idx)
        self.evidence = self.evidence.select(idx)
        self.log_dyn = self.log_dyn[keep] - np.max(self.log_dyn[keep])
        self.log_app = self.log_app[keep] - np.max(self.log_app[keep])
        self.log_array = self.log_array[keep] - np.max(self.log_array[keep])
        return True

    # ------------------------------------------------------------------ tracking

    def _look(self, image, prior, best: int, converged: bool):
        """Detect in this frame with the bank's prediction: the region of interest once converged, the predicted
        pose as the naming's start and half-turn prior when one hypothesis is left. Returns (fd, roi, t_det)."""
        roi = predicted_roi(prior[0][best], prior[1][best], self.camera, self.cfg.roi) \
            if self.cfg.roi.enabled and converged else None
        R_prior = t_prior = None
        decided = prior[0].shape[0] == 1
        # one hypothesis: its attitude weighs the detector's half-turn and its pose seeds the naming; twins still
        # open: the best one's pose only seeds the naming (they are one physical pose, their corners the same
        # points under other names), the half-turn's probability comes from the image alone, never from the
        # prior it is to test
        rc = self.cfg.roi
        if converged and rc.prior_attitude and (decided or (rc.prior_pose and rc.prior_pose_twins)):
            R_K, t_K = self._pose_K(prior[0][best])
            R_prior = R_K
            if rc.prior_pose:
                t_prior = t_K
        fd, t_det = self._detect(image, roi, R_prior, t_prior, decided)
        if roi is not None and int(np.sum(fd.visible)) < rc.min_corners:
            fd, t2 = self._detect(image, None, R_prior, t_prior, decided)
            t_det += t2
            roi = None
        return fd, roi, t_det

    def _track(self, t_s: float, image) -> TrackEstimate:
        """One frame of a started bank: every hypothesis predicted to t_s, then the frame measured under the
        prediction (_measure), the bank updated (_update_bank) and judged (_judge: integrity, pruning, the claim)."""
        t0 = time.perf_counter()
        chaser = self.chaser_at(t_s)
        prior = predict_to(self.state, t_s, self.setup)
        best = int(np.argmax(self.log_w))
        if not (np.isfinite(prior[0][best]).all() and np.isfinite(prior[1][best]).all()):
            return self._lost_prediction(t_s, image)
        pos_sig, att_sig = pose_sigmas(prior[1][best])
        self.rate_rad_s = float(np.linalg.norm(prior[0][best, RATE]))  # the view's rotation rate, predicted
        converged = bool(pos_sig < self.cfg.roi.converged_pos_sigma_m
                         and att_sig < self.cfg.roi.converged_att_sigma_deg)
        t_predict = time.perf_counter() - t0
        m = self._measure(image, prior, best, converged)
        t1 = time.perf_counter()
        events: list[str] = []
        new, b = self._update_bank(Measurement(t_s, chaser, np.nan_to_num(m.z), m.mask, m.cov), prior, best,
                                   converged, image, m, events)
        out = dict(fd=m.fd, naming=int(m.namings[b]), measured=m.mask[b] | m.pre[b], rejected=m.rejected, roi=m.roi,
                   converged=converged, nis=float(new.nis[b]), nis_dof=int(new.dof[b]))
        return self._judge(t_s, image, new, b, events, out, lambda: {
            "detection": m.t_det, "filtering": t_predict + m.t_filter + time.perf_counter() - t1})

    def _lost_prediction(self, t_s: float, image) -> TrackEstimate:
        """A prediction gone non-finite (a long gap through a bad state): the track is lost, acquire again."""
        fd = None if image is None else self._detect(image)[0]
        est = TrackEstimate(t_s=t_s, status="lost", x_hat=np.full(N_STATE, np.nan),
                            P=np.full((N_STATE, N_STATE), np.nan), hypotheses=np.zeros((0, N_STATE)),
                            probabilities=np.zeros(0), detection=fd, naming=-1, measured=np.zeros(8, bool),
                            rejected=np.zeros(8, bool), nis=0.0, nis_dof=0, roi_px=None, converged=False,
                            events=("lost: the prediction is not finite",), timing_s={})
        self._reset()
        return est

    def _measure(self, image, prior, best: int, converged: bool) -> FrameMeasurement:
        """The frame measured for every hypothesis under the bank's prediction prior (means (H, 12), covariances
        (H, 12, 12)): detected (_look), its corners named per hypothesis (choose_namings), gated against the
        detector's own covariance (gate.raw) and the best hypothesis' rejected corners flagged. No image: nothing
        measured."""
        t0 = time.perf_counter()
        H = self.state.mean.shape[0]
        z = np.full((H, 8, 2), np.nan)
        cov = np.broadcast_to(np.eye(2), (H, 8, 2, 2)).copy()
        namings, appearance = np.full(H, -1), np.zeros(H)
        fd, roi, t_det = None, None, 0.0
        if image is not None:
            fd, roi, t_det = self._look(image, prior, best, converged)
            zd, cd, p_alt = detection_measurement(fd, self.inflation, self.bias_scale)
            if np.isfinite(zd).all(-1).any():
                z, cov, namings, appearance = choose_namings(zd, cd, p_alt, self.setup.hx(prior[0]),
                                                             self.cfg.bank.appearance_clip,
                                                             self.cfg.bank.appearance_frames)
        mask = np.isfinite(z).all(-1)
        seen = mask.any(-1)
        pre = np.zeros(mask.shape, bool)  # corners gated against the detector's own covariance (cfg.gate.raw)
        if self.cfg.gate.raw and self.setup.gate_threshold is not None and mask.any():
            raw = cov * (self.cov_factor / self.inflation)
            pre = np.stack([mask[h] & (self._corner_d2(prior, np.nan_to_num(z), raw, h) > self.setup.gate_threshold)
                            for h in range(H)])
            mask = mask & ~pre
        rejected = self._rejected(prior, np.nan_to_num(z), mask, cov, best) | pre[best]
        return FrameMeasurement(fd=fd, roi=roi, z=z, cov=cov, mask=mask, pre=pre, seen=seen, namings=namings,
                                appearance=appearance, rejected=rejected, t_det=t_det,
                                t_filter=time.perf_counter() - t0 - t_det)

    def _update_bank(self, meas: Measurement, prior, best: int, converged: bool, image, m: FrameMeasurement,
                     events: list[str]) -> tuple[FilterState, int]:
        """The bank updated with the frame: every hypothesis' UKF step, its dynamics log-likelihood (the frame's
        cost, where the frame discriminates), the detector's appearance and the array cue, the evidence windows
        and the filter's memory. Returns (the updated state, this frame's best hypothesis before pruning)."""
        H = self.state.mean.shape[0]
        new = filter_step(self.state, meas, self.setup, prior=prior)
        used = new.dof > 0
        n_pre = m.pre.sum(-1)
        if frame_discriminates(new.nis, new.dof, self.cfg.bank.evidence_prob):
            cost = update_cost(new, self.gate_bound) + self.gate_bound * n_pre
            self.log_dyn = self.log_dyn + np.where(m.seen, -0.5 * cost * self.evidence_weight, 0.0)
        elif H > 1:
            events.append("no evidence between the hypotheses: the frame's innovations contradict them all")
        self.log_app = self.log_app + np.where(m.seen, m.appearance, 0.0)
        if image is not None and converged:
            self._array_cue(image, prior[0], best)
        self.log_dyn -= np.max(self.log_dyn)
        self.log_app -= np.max(self.log_app)
        self.log_array -= np.max(self.log_array)
        self.state = new
        self.evidence = self.evidence.push(np.where(used, new.nis, 0.0), new.dof, m.mask.sum(-1) + n_pre,
                                           new.rejected + new.dropped + n_pre)
        b = int(np.argmax(self.log_w))  # the best hypothesis of this frame, before pruning
        if used[b]:
            lam = filter_memory(prior[1][b], new.cov[b])
            self.memory = self.memory if lam is None else lam
        return new, b

    def _judge(self, t_s: float, image, new: FilterState, b: int, events: list[str], out: dict,
               timing: Callable[[], dict]) -> TrackEstimate:
        """Integrity: every hypothesis against its own evidence (and, one left, the array cue; the bank against
        integrity.lost_after_frames frames without a corner used); a failed one is dropped, none left is lost;
        a decided bank is pruned to its winner; then the frame's claim (_claim). timing() gives the frame's
        timing_s when the outcome is known."""
        H = new.mean.shape[0]
        problems = self._problems(new)
        if H == 1 and self.array_against >= self.cfg.array_cue.lost_readings:
            problems[0].append(f"the image shows the solar array at the other end of the body ({self.array_against} "
                               "readings in a row)")
        if image is not None:
            self.coasting_frames = 0 if new.dof[b] > 0 else self.coasting_frames + 1
        if self.coasting_frames >= self.cfg.integrity.lost_after_frames:
            # the bank's, not one hypothesis's: dropping the best alone would hand its twin the claim by
            # elimination, with no evidence for it (a 20 m acquisition trial claimed a 180-deg twin for 55 s so)
            for p in problems:
                p.append(f"no corner used in {self.coasting_frames} frames with an image")
        failed = np.array([bool(p) for p in problems])
        if failed.all():
            events.append(f"lost: {'; '.join(problems[b])}")
            est = self._estimate(t_s, events=tuple(events), status="lost", timing=timing(), **out)
            self._reset()
            return est
        if failed.any():
            events += [f"hypothesis dropped: {'; '.join(p)}" for p in problems if p]
            self.log_dyn = np.where(failed, -np.inf, self.log_dyn)
            self._keep(~failed)
        if self._keep(self.probabilities >= 1.0 - self.cfg.bank.decided):
            events.append("hypothesis decided")
        status = self._claim(events)  # may add "confirmed" to the events
        return self._estimate(t_s, events=tuple(events), status=status, timing=timing(), **out)

    def _pose_K(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The target's pose in the camera frame K of a state x (12,): R_K_from_T (3, 3) and T's origin in K (3,), m."""

        return self.camera.R_K_from_C @ mrp_to_dcm(x[MRP]).T, to_camera_K(x[POS], self.camera)

    def _array_cue(self, image, x_prior: np.ndarray, best: int) -> None:
        """Read the array cue (perception/arraycue.py) under the best hypothesis' predicted pose: while the bank
        holds hypotheses at both ends of the body, they gain its log-likelihoods (bank.array_log_likelihood); with
        one hypothesis left, a reading against it counts into array_against (one for it resets the count, an
        abstention leaves it). Nothing when the cue is off or the open hypotheses all put the array at one end."""
        H = x_prior.shape[0]
        both_ends = H > 1 and not same_array_end(x_prior, x_prior[best]).all()
        if not self.cfg.array_cue.enabled or not (both_ends or H == 1):
            return
        from envisat_pose.perception.arraycue import array_end

        cue, _ = array_end(image, self.camera.K, *self._pose_K(x_prior[best]), self.corners_T_m)
        if both_ends:
            self.log_array = self.log_array + array_log_likelihood(cue, x_prior, x_prior[best],
                                                                   self.cfg.array_cue.per_frame)
        elif cue:
            self.array_against = self.array_against + 1 if cue < 0 else 0

    def _problems(self, new: FilterState) -> list[list[str]]:
        """Per hypothesis, why this frame's evidence contradicts it (integrity.py); empty where it does not."""
        kappa = nis_sum_dispersion(self.error_model, self.dt_s, self.cfg.integrity.window, self.rate_rad_s,
                                   self.cfg.noise.correlation_in)
        problems = window_problems(self.evidence, self.cfg.integrity, kappa)
        for h, p in enumerate(problems):
            if new.indefinite[h]:
                p.insert(0, "innovation covariance not positive definite (the update failed)")
            elif new.diverged[h]:
                p.insert(0, "the filter's windowed NIS beyond its bound (divergence monitor)")
            p += state_problems(new.mean[h], new.cov[h], self.camera, self.radius_m, self.cfg.integrity)
        return problems

    def _claim(self, events: list[str]) -> str:
        """This frame's status of a bank that survived its integrity tests: "acquiring" until it is decided and
        confirmed (events gains "confirmed" the frame it is), then "tracking" when it used corners and its
        covariance backs the claim, else "coasting"."""
        mean, cov = self.state.mean[0], self.state.cov[0]
        backed = bool(self.state.dof[0] > 0) and claim_holds(mean, cov, self.cfg.integrity)
        if not self.confirmed:
            if self.state.mean.shape[0] > 1 or not backed \
                    or self.evidence.used_frames()[0] < self.cfg.integrity.confirm_frames:
                return "acquiring"
            self.confirmed = True
            events.append("confirmed")
        return "tracking" if backed else "coasting"

    def _rejected(self, prior, z, mask, cov, best) -> np.ndarray:
        """Corners of the best hypothesis the chi-square gate rejects (its own per-corner rule from the prior's
        sigma points; the visibility check's drops count as rejected too)."""

        if not mask[best].any() or self.setup.gate_threshold is None:
            return np.zeros(8, bool)
        d2 = self._corner_d2(prior, z, cov, best)
        vis = predicted_visible(prior[0][best]) if self.fcfg.visibility_check else np.ones(8, bool)
        return mask[best] & ((d2 > self.setup.gate_threshold) | ~vis)

    def _corner_d2(self, prior, z, cov, h) -> np.ndarray:
        """(8,) each corner's squared Mahalanobis distance from hypothesis h's predicted corner, under the prior's
        spread (its sigma points through the measurement model) plus cov[h] (8, 2, 2) at the filter's R scale."""

        S = sigma_points(prior[0][h], prior[1][h], self.setup.weights)  # (25, 12)
        uv = self.setup.hx(S)  # (25, 8, 2)
        Wm, Wc = self.setup.weights.Wm, self.setup.weights.Wc
        mu = np.einsum("s,skj->kj", Wm, uv)
        d = uv - mu
        Pzz = np.einsum("s,ski,skj->kij", Wc, d, d) + cov[h] * self.state.r_scale[h]
        y = z[h] - mu
        return np.einsum("ki,ki->k", y, np.linalg.solve(Pzz, y[..., None])[..., 0])

    def _estimate(self, t_s, *, fd, naming, measured, rejected, roi, converged, events, timing, status,
                  nis=0.0, nis_dof=0) -> TrackEstimate:
        """The best hypothesis' state as a TrackEstimate (the bank as it stands after this frame)."""
        best = int(np.argmax(self.log_w))
        P = range_consider(self.state.mean[best], self.state.cov[best], self.scale_sigma)
        return TrackEstimate(t_s=t_s, status=status, x_hat=self.state.mean[best].copy(), P=P,
                             hypotheses=self.state.mean.copy(), probabilities=self.probabilities, detection=fd,
                             naming=naming, measured=np.asarray(measured, bool), rejected=np.asarray(rejected, bool),
                             nis=nis, nis_dof=nis_dof, roi_px=roi, converged=converged, events=events,
                             timing_s=timing, confirmed=self.confirmed, coasting_frames=self.coasting_frames)

    @classmethod
    def from_scenario(cls, scenario: str = "default", weights: str | None = None, **kw) -> "Tracker":
        """A Tracker for the named scenario's geometry (tracker_from_scenario: its orbit and dynamics, the shipped
        detector unless weights, the MJCF camera unless camera=)."""
        return tracker_from_scenario(scenario, weights, **kw)


def tracker_from_scenario(scenario: str = "default", weights: str | None = None, camera=None,
                          config=None, filter_config: FilterConfig | dict | None = None, size_px=None) -> Tracker:
    """A Tracker for frames of the named scenario's geometry: the chaser's orbit and the target's dynamics
    (gravity gradient, mu) from the scenario, the detector of `weights` (None: shipped), `camera` (None: the
    MJCF's chaser_cam, at size_px = (width, height) when given), TrackerConfig `config` (None: defaults), the
    tracker's filter settings with `filter_config`'s fields over them (pipelines.build.tracker_filter)."""
    from types import SimpleNamespace

    scen = scenario_config(scenario)
    physics = onboard_physics(SimpleNamespace(config=to_dict(scen)), f"scenario {scenario!r}")
    return Tracker(camera if camera is not None else tracker_camera(size_px=size_px), tracker_detector(weights),
                   chaser_from_orbit(scen.orbit), config or TrackerConfig(),
                   dataclasses.asdict(tracker_filter(filter_config, scenario)),
                   mu_m3_s2=physics.mu_m3_s2, gravity_gradient=physics.gravity_gradient)
