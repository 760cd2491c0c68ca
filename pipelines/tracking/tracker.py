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
  bound, its state is physical: pipelines/tracking/integrity.py) and its frames read the camera's focal length
  (pipelines/tracking/focal_check.py), with every twin whose fit is valid and physical beside
  it (a twin just past a bound the passing one is just inside is the window's noise, not evidence); when none
  passes the older half of the window is dropped and acquisition goes on (the reason: `last_refusal`). Or a bank runs but has not yet
  earned a claim: its half-turn is still open, or it has not yet passed `integrity.confirm_frames` frames with
  corners used and a covariance inside the claim, or the last confirmed track (lost within `integrity.recall_s`),
  propagated to now, puts it at its own twin (TrackingSteps._recall_veto).
- "tracking": the bank is decided (one hypothesis) and confirmed, this frame used corners, and the covariance backs
  the claim (3-sigma within `integrity.claim_pos_share` of the range and `integrity.claim_att_deg`).
- "coasting": the confirmed bank predicts without a usable measurement (no image, nothing found, every corner
  rejected) or its covariance is wider than the claim (after an outage). A prediction, never a fix.
- "lost": the evidence contradicted the state this frame: every hypothesis failed its integrity tests (windowed
  NIS beyond its chi-square bound, too many corners rejected, a state that is not physical, an innovation
  covariance that is not positive definite, the filter's divergence monitor), or `integrity.lost_after_frames`
  frames in a row with an image used no corner. The bank is dropped and the tracker acquires again from the images.
Each frame every hypothesis takes the naming nearest its predicted corners and the bank is updated at once
(pipelines/tracking/bank.py); a hypothesis below 1 - `bank.decided` is dropped, and so is one that fails its integrity tests
(never promoting one: where the best fails, or those failing held more than 1 - `bank.decided` and leave one, the
whole bank is lost).
Once the best prior is tight the detector looks only in the predicted region of interest, with the predicted pose
as its naming's start and half-turn prior when one hypothesis is left.

Another target than ENVISAT (`target=`, a Target or its MJCF file; `envisat track --target`, `envisat run
--target`): its keypoint detector (perception.keypoint_detect.KeypointFrameDetector, K keypoints named by channel),
the filter over its K keypoints, inertia and visibility table, and the namings of its own symmetries
(pipelines/tracking/namings.py: one hypothesis per symmetry something tells apart, for the box's half-turns above;
poses that nothing tells apart are one pose, the target's `equivalent` rotations). The rest is as for ENVISAT, but
the solar-array cue, which is ENVISAT's.

The filter's R is the detector's calibrated covariance at the error model's scale, inflated for the errors'
frame-to-frame correlation at the filter's own memory (pipelines/tracking/noise.py). The detector's mean apparent scale
(measured on held-out sequences) is undone in every frame's corners; what a run's own scale leaves (the spread
between sequences, x range) is added to the reported variance along the line of sight, never to the gain
(noise.range_consider, TrackerConfig.noise.range_floor and correct_scale).
"""

from __future__ import annotations

import dataclasses
import numbers
import os
import time
from typing import Callable

import numpy as np

from envisat_pose.config import InputError, config_arg, to_dict
from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2, load_inertia_T_kg_m2
from envisat_pose.filtering.estimator import (
    FilterConfig,
    FilterState,
    filter_inertia_T_kg_m2,
    init_state,
    make_setup,
)
from envisat_pose.filtering.kernel_warmup import load_in_background
from envisat_pose.geometry import PinholeCamera
from envisat_pose.perception.keypoint_cov import reject_share
from envisat_pose.pipelines.tracking.acquisition import FramePose
from envisat_pose.pipelines.tracking.bank import probabilities, select_runs
from envisat_pose.pipelines.tracking.build import chaser_from_orbit, tracker_camera, tracker_detector, tracker_filter
from envisat_pose.pipelines.tracking.detection_arg import DetectionRefused, detection_arg
from envisat_pose.pipelines.tracking.integrity import (
    DEFAULT_REJECT_SHARE,
    EvidenceWindow,
    check_min_keypoints,
    check_min_target_px,
    target_radius_m,
)
from envisat_pose.pipelines.tracking.namings import box_namings, target_namings
from envisat_pose.pipelines.tracking.noise import (
    correlation_inflation,
    detector_error_model,
    evidence_weight,
    range_consider,
    scale_sigma,
    sequence_cov_factor,
    window_memory,
)
from envisat_pose.pipelines.tracking.onboard import onboard_physics
from envisat_pose.pipelines.tracking.tracker_acquire import AcquiringSteps
from envisat_pose.pipelines.tracking.tracker_config import TRACKER_FILTER, TrackerConfig, TrackEstimate
from envisat_pose.pipelines.tracking.tracker_frame import MAX_PREDICTION_S, TrackingSteps
from envisat_pose.state import N_STATE
from envisat_pose.status import STATUSES
from envisat_pose.target import Target, load_target, other_target

__all__ = ["Tracker", "TrackerConfig", "TrackEstimate", "TRACKER_FILTER", "STATUSES", "tracker_from_scenario"]


class Tracker(AcquiringSteps, TrackingSteps):
    """Detector + UKF over a user's frames (module docstring). One object per image sequence. Its frames before a
    bank runs are AcquiringSteps' (tracker_acquire.py), those of a started bank TrackingSteps' (tracker_frame.py)."""


    def __init__(self, camera: PinholeCamera, detector, chaser_at: Callable[[float], np.ndarray],
                 config: TrackerConfig = TrackerConfig(), filter_config: FilterConfig | dict | None = None,
                 J_T: np.ndarray | None = None, mu_m3_s2: float | None = None, gravity_gradient: bool = False,
                 prior: tuple[np.ndarray, np.ndarray, float] | None = None, target: Target | str | None = None):
        config = config_arg(config, TrackerConfig, "config")
        config.validate()
        target = target_arg(target)
        if target is not None and not target.keypoint_detector:
            target = None  # ENVISAT's: its corner network and the box's filter, as without a target
        check_detector_target(detector, target)
        self.target = target
        self.cfg = config
        fcfg = tracker_filter(filter_config)  # only the fields given override the tracker's
        q = fcfg.q_sigma
        q_detector = config.noise.detector_q_sigma
        self.fcfg = dataclasses.replace(fcfg, q_sigma=tuple(max(a, b) for a, b in zip(q, q_detector)))
        self.fcfg.validate()
        self.camera = camera
        self.detector = detector
        self.chaser_at = chaser_at
        if J_T is None:
            J_T = load_inertia_T_kg_m2() if target is None else filter_inertia_T_kg_m2(target)
        mu = MU_EARTH_M3_S2 if mu_m3_s2 is None else float(mu_m3_s2)
        self.setup = make_setup(self.fcfg, "pixels", camera, J_T=J_T, mu_m3_s2=mu, gravity_gradient=gravity_gradient,
                                target=target)
        self.dyn = {"J_T": J_T, "mu_m3_s2": mu, "gravity_gradient": gravity_gradient,
                    "max_step_s": self.fcfg.max_rk4_step_s}
        load_in_background(self.setup)  # the fused filter's code loaded while the first frames are detected
        self.keypoints_T_m = self.setup.keypoints_T_m
        self.K = self.setup.num_keypoints
        check_min_keypoints(config, self.K)
        self.namings = box_namings() if target is None else target_namings(target, J_T)
        self.radius_m = target_radius_m(self.keypoints_T_m)
        check_min_target_px(config.integrity.min_target_px, camera.f_px, "integrity.min_target_px", self.radius_m)
        self.error_model = detector_error_model(detector)
        self.reject_curve = getattr(detector, "reject_curve", None)  # what its gate rejects (calibrate --target)
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
        # the last confirmed track (predicted on while it vetoes) and its time, kept through a loss (_recall_veto)
        self.recall: tuple[FilterState, float] | None = None
        self.buffer: list[FramePose] = []
        self.last_refusal: str | None = None  # why the last cold start started no bank (its problems), None: none
        self.coasting_frames = 0
        self.array_against = 0  # array-cue readings in a row against the one hypothesis left
        self.last_pose: np.ndarray | None = None
        self.t_last: float | None = None
        self._plan_cache = None  # (t_s, the bank's state, its FramePlan): TrackingSteps._plan
        self.window_fell_short = False  # the last frame's region of interest held too few keypoints
        self.image_window: np.ndarray | None = None  # the frame's made pixels (x0, y0, side) px; None: whole
        if prior is not None:
            x0, P0, t0 = prior_arg(prior)
            self._start(x0[None], P0[None], t0, np.zeros(1), np.zeros(1))

    @property
    def status(self) -> str:
        """"acquiring" until a bank is confirmed, then "tracking" (the last frame's own status is in its
        TrackEstimate)."""
        return "tracking" if self.state is not None and self.confirmed else "acquiring"

    def planned_window(self, t_s: float) -> np.ndarray | None:
        """The window (x0, y0, side) px of a frame at t_s that the tracker will look at and at nothing outside it,
        or None when it needs the whole frame: while acquiring, with twins still open (the array cue weighs them
        on whole frames), before its claim is confirmed, when not converged or the region of interest is off, and
        after a frame whose window held too few keypoints. The frame's maker may then make that window alone (the
        closed loop) and say so (step's window_px); the array cue's integrity test then reads the whole frames it
        makes between (RunConfig.full_frame_every). Pure: step(t_s, ...) uses the same prediction."""
        if self.state is None or not self.confirmed or self.state.mean.shape[0] != 1 or self.window_fell_short:
            return None
        if self.t_last is not None and not t_s > self.t_last:
            return None
        if t_s - self.state.t_s > MAX_PREDICTION_S:  # step loses the track without a prediction
            return None
        plan = self._plan(float(t_s))
        return None if plan.roi is None else plan.roi.copy()

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

    def open_hypotheses(self) -> np.ndarray:
        """(H,) bool the hypotheses the bank keeps open: probability at least 1 - bank.decided, or, with
        bank.appearance_veto, one the detector's appearance alone would decide for against the best (ahead by
        more than the decision's log odds)."""
        decided = self.cfg.bank.decided
        keep = self.probabilities >= 1.0 - decided
        if self.cfg.bank.appearance_veto and not keep.all():
            best = int(np.argmax(self.log_w))
            keep |= self.log_app - self.log_app[best] > np.log(decided / (1.0 - decided))
        return keep

    @property
    def gate_bound(self) -> float:
        """The filter's chi-square gate per corner (the cost of a corner it rejects)."""
        return self.setup.gate_threshold if self.setup.gate_threshold is not None else self.cfg.fit.gate

    def reject_share(self, gate: float, scale) -> np.ndarray:
        """The share of a correct track's corners a chi-square gate `gate` per corner rejects, the detector's
        covariance taken at `scale` (a number or (H,) per hypothesis: the inflation times the filter's R scale):
        integrity.expected_reject_share where the config sets it, else the detector's calibrated reject curve at
        that radius (perception/keypoint_cov.reject_share: a bound, the prior's spread only widens the gate),
        else integrity.DEFAULT_REJECT_SHARE."""
        fixed = self.cfg.integrity.expected_reject_share
        if fixed is None and self.reject_curve is None:
            fixed = DEFAULT_REJECT_SHARE
        if fixed is not None:
            return np.full(np.shape(scale), float(fixed))
        return np.vectorize(lambda c: reject_share(self.reject_curve, gate, c), otypes=[float])(scale)

    def cold_start_reject_share(self) -> float:
        """The share of a cold-start fit's corners its gate may reject: integrity.expected_reject_share where the
        config sets it, else integrity.DEFAULT_REJECT_SHARE, never the detector's measured share (reject_share):
        a start is where a wrong pose gets in, and a fit 13 deg off that rejected more than 10 % of its corners
        started and was claimed for 5 s under the upper stage's measured share (slow-tumble seed 204,
        docs/history.md); a started track's window is tested against the measured share."""
        fixed = self.cfg.integrity.expected_reject_share
        return float(DEFAULT_REJECT_SHARE if fixed is None else fixed)

    # ------------------------------------------------------------------ the step

    def step(self, t_s: float, image: np.ndarray | None, window_px: np.ndarray | None = None) -> TrackEstimate:
        """One frame: t_s (s, increasing), image (H, W) uint8 gray, or None (no frame: the filter predicts); a
        time or frame refused is an InputError (a ValueError) naming it, and changes nothing; so is a detector's
        answer that is not a FrameDetection of the tracker's K keypoints (detection_arg.py).
        window_px: (x0, y0, side) px when only that window of the image was made (the rest black: a frame made
        for planned_window), None for a whole frame; nothing that reads beyond the window (the array cue) reads
        such a frame."""
        if isinstance(t_s, (str, bytes, bool)) or not isinstance(t_s, numbers.Real):
            raise InputError(f"t_s = {t_s!r}: expected the frame's time, s (a number)")
        t_s = float(t_s)
        if not np.isfinite(t_s):
            raise InputError(f"t_s = {t_s}: expected a finite frame time, s")
        if self.t_last is not None and not t_s > self.t_last:
            raise InputError(f"t_s = {t_s}: expected a time after the last frame's, {self.t_last} s (frame times "
                             "must increase)")
        if self.t_last is None and self.state is not None and t_s < self.state.t_s:
            raise InputError(f"t_s = {t_s}: expected a time at or after the prior's t0 = {self.state.t_s} s (the "
                             "first frame of a tracker given a prior)")
        want = (self.camera.height_px, self.camera.width_px)
        if image is not None and (not isinstance(image, np.ndarray) or image.shape != want or image.dtype != np.uint8):
            raise InputError(frame_refusal(image, want))
        if window_px is not None:
            window_px = np.asarray(window_px)
            if window_px.shape != (3,) or window_px[2] < 1:
                raise InputError(f"window_px: {window_px.tolist()}; expected (x0, y0, side) px with side >= 1")
        before = (self.image_window, self.dt_s, self.t_last)
        self.image_window = window_px
        if self.t_last is not None:
            self.dt_s = t_s - self.t_last
        self.t_last = t_s
        try:
            return self._acquire(t_s, image) if self.state is None else self._track(t_s, image)
        except DetectionRefused:  # the detector's answer refused before anything read it: the frame never was
            self.image_window, self.dt_s, self.t_last = before
            raise

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
        return detection_arg(fd, self.K), time.perf_counter() - t0

    # ------------------------------------------------------------------ the bank: started, pruned, reset

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
        self._keep(self.open_hypotheses())

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


def frame_refusal(image, want: tuple[int, int]) -> str:
    """Why Tracker.step refuses image (want: the camera's (height, width)), with the way to the frame it takes: gray
    from colour, 8 bits from 16, or a camera of the frame's size."""
    if not isinstance(image, np.ndarray):
        got, how = type(image).__name__, "a numpy array"
    else:
        got = f"{image.dtype} {image.shape}"
        if image.ndim == 3 and image.shape[:2] == want and image.shape[2] in (1, 2):  # cvtColor takes 3 or 4
            how = "the gray channel alone: image[..., 0]"
        elif image.ndim == 3 and image.shape[:2] == want:
            how = ("gray from colour: cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) (OpenCV's order; cv2.COLOR_RGB2GRAY "
                   "for an RGB array; BGRA2GRAY or RGBA2GRAY with alpha)")
        elif image.shape[:2] != want:
            how = "a frame of another size needs its own camera (tracker_camera, camera_file)"
        elif image.dtype == np.uint16:
            how = "8 bits from 16-bit data: envisat_pose.pipelines.runs.frames.to_u8(image, bit_depth)"
        else:
            how = "8-bit pixels: image.astype(np.uint8) after scaling to 0-255"
    return f"image: {got}; expected a uint8 gray frame of the camera's size {want} (height, width): {how}"


def prior_arg(prior) -> tuple[np.ndarray, np.ndarray, float]:
    """A Tracker's `prior` (x0 (12,), P0 (12, 12), t0 s) as arrays and a float; InputError naming it otherwise
    (a prior that is not finite, or a P0 not symmetric positive definite, would be lost at the first frame)."""
    if not isinstance(prior, (tuple, list)) or len(prior) != 3:
        raise InputError(f"prior: {prior!r:.80}; expected (x0, P0, t0): the state (12,), its covariance (12, 12) "
                         "and its time, s")
    try:
        x0, P0, t0 = np.asarray(prior[0], float), np.asarray(prior[1], float), float(prior[2])
    except (TypeError, ValueError) as err:
        raise InputError(f"prior: expected (x0, P0, t0) of numbers ({err})") from None
    if x0.shape != (N_STATE,) or P0.shape != (N_STATE, N_STATE):
        raise InputError(f"prior: x0 {x0.shape}, P0 {P0.shape}; expected x0 ({N_STATE},) and P0 ({N_STATE}, "
                         f"{N_STATE}) (envisat_pose.state's layout)")
    if not (np.isfinite(x0).all() and np.isfinite(P0).all() and np.isfinite(t0)):
        raise InputError("prior: expected finite x0, P0 and t0 (a NaN or inf in one of them)")
    if not np.allclose(P0, P0.T) or np.linalg.eigvalsh(0.5 * (P0 + P0.T)).min() <= 0:
        raise InputError("prior: P0 is not symmetric positive definite; expected a covariance")
    return x0, P0, t0


def target_arg(target) -> Target | None:
    """A Tracker's `target`: a Target, its MJCF file (a str or pathlib.Path, load_target), or None (ENVISAT);
    InputError naming it otherwise."""
    if target is None or isinstance(target, Target):
        return target
    if isinstance(target, (str, os.PathLike)):
        return load_target(os.fspath(target))
    raise InputError(f"target: {target!r:.60}; expected a Target (load_target(FILE.xml)), its MJCF file's path or "
                     "None (ENVISAT)")


def check_detector_target(detector, target: Target | None) -> None:
    """InputError in one line when a detector that records its target (`trained_for`: a keypoint detector's
    name and sha256) was trained for another target than the tracker's (None: ENVISAT, whose detector is the
    corner network), or when ENVISAT's corner network is given for another target (it names the box's 8 corners,
    not the target's keypoints). A detector that records none (a user's own object) is taken as given."""
    record = getattr(detector, "trained_for", None)
    if not record:
        if target is not None:
            from envisat_pose.perception.detect import Detector

            if isinstance(detector, Detector):
                raise InputError(f"detector: ENVISAT's corner detector (the box's 8 corners A-H), not one of target "
                                 f"{target.name!r}'s {len(target.keypoint_names)} keypoints: give its keypoint "
                                 "detector (tracker_detector(weights, target=FILE.xml))")
        return
    if target is None:
        raise InputError(f"the detector is a keypoint detector of target {record.get('name')!r}: give the tracker "
                         "that target (target=load_target(FILE.xml), --target FILE.xml)")
    if record.get("sha256") != target.sha256:
        raise InputError(f"the detector was trained for target {record.get('name')!r} (sha256 "
                         f"{str(record.get('sha256'))[:12]}), not for {target.name!r} (sha256 {target.sha256[:12]})")


def tracker_from_scenario(scenario: str = "default", weights: str | None = None, camera=None,
                          config=None, filter_config: FilterConfig | dict | None = None, size_px=None,
                          target: str | Target | None = None) -> Tracker:
    """A Tracker for frames of the named scenario's geometry: the chaser's orbit and the target's dynamics
    (gravity gradient, mu) from the scenario, the detector of `weights` (None: shipped), `camera` (None: the
    MJCF's chaser_cam, at size_px = (width, height) when given; a camera TOML file of ideal frames, a str or a
    pathlib.Path; or a PinholeCamera), TrackerConfig `config` (None: defaults), the
    tracker's filter settings with `filter_config`'s fields over them (pipelines.build.tracker_filter); target:
    another target's MJCF file or its Target (None: ENVISAT; its keypoint detector's `weights`, by default its own
    beside its file: perception.weights.default_target_weights)."""
    from types import SimpleNamespace

    if target is not None:
        target = target_arg(target).path  # a file given is read (and refused) here
    scen = scenario_config(scenario)
    physics = onboard_physics(SimpleNamespace(config=to_dict(scen)), f"scenario {scenario!r}")
    if camera is None or isinstance(camera, (str, os.PathLike)):  # the MJCF's, or a camera TOML file's pinhole
        camera = tracker_camera(None if camera is None else os.fspath(camera), size_px=size_px)
    elif not isinstance(camera, PinholeCamera):
        raise InputError(f"camera: expected a camera TOML file or a PinholeCamera, got {type(camera).__name__}")
    config = config_arg(TrackerConfig() if config is None else config, TrackerConfig, "config")
    return Tracker(camera, tracker_detector(os.fspath(weights) if weights is not None else None, target=target),
                   chaser_from_orbit(scen.orbit), config,
                   dataclasses.asdict(tracker_filter(filter_config, scenario)),
                   mu_m3_s2=physics.mu_m3_s2, gravity_gradient=physics.gravity_gradient,
                   target=None if other_target(target) is None else load_target(target))
