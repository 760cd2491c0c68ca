"""The Tracker's frames of a started bank (pipelines/tracking/tracker.py's docstring): every hypothesis predicted,
the frame looked at (its region of interest: predicted_roi) and measured for each hypothesis (FrameMeasurement),
the bank updated, then judged (integrity, pruning, the claim). A part of the Tracker (TrackingSteps, one of its
bases): its methods read and set the Tracker's own state."""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.filtering.estimator import FilterState, Measurement, filter_step, predict_to
from envisat_pose.filtering.measurements import measure, to_camera_K
from envisat_pose.filtering.ukf import chart_sigma_points
from envisat_pose.geometry import PinholeCamera
from envisat_pose.pipelines.tracking.bank import (
    array_log_likelihood,
    bounded_frame_evidence,
    choose_namings,
    frame_discriminates,
    same_array_end,
    update_cost,
)
from envisat_pose.pipelines.tracking.integrity import (
    claim_holds,
    pose_sigmas,
    recall_says_twin,
    state_problems,
    window_problems,
)
from envisat_pose.pipelines.tracking.noise import detection_measurement, filter_memory, nis_sum_dispersion
from envisat_pose.pipelines.tracking.tracker_bounds import MAX_PREDICTION_S  # the longest gap predicted over
from envisat_pose.pipelines.tracking.tracker_config import RoiConfig, TrackEstimate
from envisat_pose.state import MRP, N_STATE, POS, RATE


def predicted_roi(mean: np.ndarray, cov: np.ndarray, camera: PinholeCamera, cfg: RoiConfig,
                  keypoints_T_m: np.ndarray | None = None) -> np.ndarray | None:
    """The detector's region of interest (x0, y0, side) px from a prior (12,), (12, 12): the predicted keypoints'
    (keypoints_T_m (K, 3); None: ENVISAT's corners) extent x cfg.margin plus 6 x the prior's position sigma in
    pixels; None when no keypoint is predicted in view."""

    uv = measure(mean[None], "pixels", camera, keypoints_T_m)[0]
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


@dataclasses.dataclass(frozen=True)
class FramePlan:
    """What a started bank predicts of a frame at t_s before seeing it (TrackingSteps._plan): prior (means (H, 12),
    covariances (H, 12, 12)), best (the best hypothesis), finite (its prediction is), converged (tight enough for
    the region of interest), roi (x0, y0, side) px the detector will look at, None for the whole frame."""

    prior: tuple
    best: int
    finite: bool
    converged: bool
    roi: np.ndarray | None


class TrackingSteps:
    """The Tracker's frames of a started bank: _track (one frame) and its steps _plan, _detect_predicted,
    _measure, _update_bank, _judge."""

    def _plan(self, t_s: float) -> FramePlan:
        """The bank predicted to t_s and what the frame will be looked at with (FramePlan); pure, and kept for
        the bank as it stands, so that asking ahead (Tracker.planned_window) and the step share one prediction."""
        cached = self._plan_cache
        if cached is not None and cached[0] == t_s and cached[1] is self.state:
            return cached[2]
        prior = predict_to(self.state, t_s, self.setup)
        best = int(np.argmax(self.log_w))
        finite = bool(np.isfinite(prior[0][best]).all() and np.isfinite(prior[1][best]).all())
        converged, roi = False, None
        if finite:
            pos_sig, att_sig = pose_sigmas(prior[1][best])
            converged = bool(pos_sig < self.cfg.roi.converged_pos_sigma_m
                             and att_sig < self.cfg.roi.converged_att_sigma_deg)
            if self.cfg.roi.enabled and converged:
                roi = predicted_roi(prior[0][best], prior[1][best], self.camera, self.cfg.roi, self.keypoints_T_m)
        plan = FramePlan(prior, best, finite, converged, roi)
        self._plan_cache = (t_s, self.state, plan)
        return plan

    def _detect_predicted(self, image, prior, best: int, converged: bool, roi: np.ndarray | None):
        """Detect in this frame with the bank's prediction: the region of interest roi (the plan's: once
        converged), the predicted pose as the naming's start and half-turn prior when one hypothesis is left.
        Returns (fd, roi, t_det)."""
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
        self.window_fell_short = False
        if roi is not None and int(np.sum(fd.visible)) < rc.min_keypoints:
            fd, t2 = self._detect(image, None, R_prior, t_prior, decided)
            t_det += t2
            roi = None
            self.window_fell_short = True  # the next frame is looked at whole (planned_window)
        return fd, roi, t_det

    def _track(self, t_s: float, image) -> TrackEstimate:
        """One frame of a started bank: every hypothesis predicted to t_s, then the frame measured under the
        prediction (_measure), the bank updated (_update_bank) and judged (_judge: integrity, pruning, the claim)."""
        t0 = time.perf_counter()
        gap_s = t_s - float(self.state.t_s)
        if gap_s > MAX_PREDICTION_S:
            return self._lost_prediction(t_s, image, f"{gap_s:.3g} s since the track's last frame, beyond the "
                                         f"{MAX_PREDICTION_S:.0f} s a track is predicted over")
        chaser = self.chaser_at(t_s)
        plan = self._plan(t_s)
        prior, best, converged = plan.prior, plan.best, plan.converged
        if not plan.finite:
            return self._lost_prediction(t_s, image)
        self.rate_rad_s = float(np.linalg.norm(prior[0][best, RATE]))  # the view's rotation rate, predicted
        t_predict = time.perf_counter() - t0
        m = self._measure(image, prior, best, converged, plan.roi)
        t1 = time.perf_counter()
        events: list[str] = []
        new, b = self._update_bank(Measurement(t_s, chaser, np.nan_to_num(m.z), m.mask, m.cov), prior, best,
                                   converged, image, m, events)
        out = dict(fd=m.fd, naming=int(m.namings[b]), measured=m.mask[b] | m.pre[b], rejected=m.rejected, roi=m.roi,
                   converged=converged, nis=float(new.nis[b]), nis_dof=int(new.dof[b]))
        return self._judge(t_s, image, new, b, events, out, lambda: {
            "detection": m.t_det, "filtering": t_predict + m.t_filter + time.perf_counter() - t1})

    def _lost_prediction(self, t_s: float, image, why: str = "the prediction is not finite") -> TrackEstimate:
        """A prediction gone non-finite (a long gap through a bad state), or none made (a gap beyond
        MAX_PREDICTION_S): the track is lost, acquire again."""
        fd = None if image is None else self._detect(image)[0]
        est = TrackEstimate(t_s=t_s, status="lost", x_hat=np.full(N_STATE, np.nan),
                            P=np.full((N_STATE, N_STATE), np.nan), hypotheses=np.zeros((0, N_STATE)),
                            probabilities=np.zeros(0), detection=fd, naming=-1, measured=np.zeros(self.K, bool),
                            rejected=np.zeros(self.K, bool), nis=0.0, nis_dof=0, roi_px=None, converged=False,
                            events=(f"lost: {why}",), timing_s={})
        self._reset()
        return est

    def _measure(self, image, prior, best: int, converged: bool, roi: np.ndarray | None = None) -> FrameMeasurement:
        """The frame measured for every hypothesis under the bank's prediction prior (means (H, 12), covariances
        (H, 12, 12)): detected (_detect_predicted, in the region of interest roi where one is planned), its corners named per hypothesis (choose_namings), gated against
        the detector's own covariance (gate.raw) and the best hypothesis' rejected corners flagged. No image: nothing
        measured."""
        t0 = time.perf_counter()
        H = self.state.mean.shape[0]
        z = np.full((H, self.K, 2), np.nan)
        cov = np.broadcast_to(np.eye(2), (H, self.K, 2, 2)).copy()
        namings, appearance = np.full(H, -1), np.zeros(H)
        fd, detected_in, t_det = None, None, 0.0  # the region of interest the frame was detected in
        if image is not None:
            fd, detected_in, t_det = self._detect_predicted(image, prior, best, converged, roi)
            zd, cd, p_alt = detection_measurement(fd, self.inflation, self.bias_scale)
            if np.isfinite(zd).all(-1).any():
                z, cov, namings, appearance = choose_namings(zd, cd, p_alt, self.setup.hx(prior[0]),
                                                             self.cfg.bank.appearance_clip,
                                                             self.cfg.bank.appearance_frames, self.namings)
        mask = np.isfinite(z).all(-1)
        seen = mask.any(-1)
        pre = np.zeros(mask.shape, bool)  # corners gated against the detector's own covariance (cfg.gate.raw)
        if self.cfg.gate.raw and self.setup.gate_threshold is not None and mask.any():
            raw = cov * (self.cov_factor / self.inflation)
            pre = np.stack([mask[h] & (self._corner_d2(prior, np.nan_to_num(z), raw, h) > self.setup.gate_threshold)
                            for h in range(H)])
            mask = mask & ~pre
        rejected = self._rejected(prior, np.nan_to_num(z), mask, cov, best) | pre[best]
        return FrameMeasurement(fd=fd, roi=detected_in, z=z, cov=cov, mask=mask, pre=pre, seen=seen, namings=namings,
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
            self.log_dyn = self.log_dyn + bounded_frame_evidence(-0.5 * cost * self.evidence_weight, m.seen,
                                                                 self.cfg.bank.frame_max_log)
        elif H > 1:
            events.append("no evidence between the hypotheses: the frame's innovations contradict them all")
        self.log_app = self.log_app + np.where(m.seen, m.appearance, 0.0)
        if image is not None and converged:
            self._array_cue(image, prior[0], best)
        self.log_dyn -= np.max(self.log_dyn)
        self.log_app -= np.max(self.log_app)
        self.log_array -= np.max(self.log_array)
        # the detector's covariance at the scale the gate read it (gate.raw: without the correlation's inflation)
        scale = (self.cov_factor if self.cfg.gate.raw else self.inflation) * self.state.r_scale
        self.state = new
        self.evidence = self.evidence.push(np.where(used, new.nis, 0.0), new.dof, m.mask.sum(-1) + n_pre,
                                           new.rejected + new.dropped + n_pre, self.reject_share(self.gate_bound, scale))
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
                p.append(f"no keypoint used in {self.coasting_frames} frames with an image")
        failed = np.array([bool(p) for p in problems])
        prob = self.probabilities
        held, best = float(prob[failed].sum()), int(np.argmax(prob))
        if failed.any() and not failed.all() and (failed[best] or ((~failed).sum() == 1
                                                                   and held > 1.0 - self.cfg.bank.decided)):
            # the integrity tests remove a hypothesis, never promote one: twins predict a frame's corners within a
            # fraction of a pixel, so a bound one crosses and another does not is the bound's noise, not evidence
            # between them. Where the bank's best fails, or those failing held more than 1 - bank.decided and leave
            # one, the whole bank is lost rather than a twin decided by their fall (on motion-blurred frames the
            # truth, at p 0.995, crossed its windowed-NIS bound and its twin left alone was claimed at once)
            worst = int(np.argmax(np.where(failed, prob, -1.0)))
            why = problems[worst] + [f"its twins not decided by its fall (it held {100 * prob[worst]:.1f} %)"]
            problems, failed = [why] * H, np.ones(H, bool)
        if failed.all():
            events.append(f"lost: {'; '.join(problems[b])}")
            est = self._estimate(t_s, events=tuple(events), status="lost", timing=timing(), **out)
            self._reset()
            return est
        if failed.any():
            events += [f"hypothesis dropped: {'; '.join(p)}" for p in problems if p]
            self.log_dyn = np.where(failed, -np.inf, self.log_dyn)
            self._keep(~failed)
        open_ = self.open_hypotheses()
        if (open_ & (self.probabilities < 1.0 - self.cfg.bank.decided)).any():
            events.append("undecided: the detector's appearance favours a hypothesis the dynamics would drop")
        if self._keep(open_):
            events.append("hypothesis decided")
        status = self._claim(events)  # may add "confirmed" to the events
        return self._estimate(t_s, events=tuple(events), status=status, timing=timing(), **out)

    def _pose_K(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The target's pose in the camera frame K of a state x (12,): R_K_from_T (3, 3) and T's origin in K (3,), m."""

        return self.camera.R_K_from_C @ mrp_to_dcm(x[MRP]).T, to_camera_K(x[POS], self.camera)

    @property
    def array_cue_on(self) -> bool:
        """Whether the tracker reads the array cue: ENVISAT's box (no other target) with the cue enabled. The cue
        reads the whole frame (the array at both ends of the body and the sky around it, beyond the region of
        interest): frames made as a window alone (step's window_px) are not read."""
        return self.cfg.array_cue.enabled and self.target is None

    def _array_cue(self, image, x_prior: np.ndarray, best: int) -> None:
        """Read the array cue (perception/arraycue.py) under the best hypothesis' predicted pose: while the bank
        holds hypotheses at both ends of the body, they gain its log-likelihoods (bank.array_log_likelihood); with
        one hypothesis left, a reading against it counts into array_against (one for it resets the count, an
        abstention leaves it). Nothing when the cue is off, the frame is a window alone, or the open hypotheses
        all put the array at one end."""
        H = x_prior.shape[0]
        both_ends = H > 1 and not same_array_end(x_prior, x_prior[best]).all()
        if not self.array_cue_on or self.image_window is not None or not (both_ends or H == 1):
            return
        from envisat_pose.perception.arraycue import array_end

        cue, _ = array_end(image, self.camera.K, *self._pose_K(x_prior[best]), self.keypoints_T_m)
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
            withheld = self._recall_veto(mean)
            if withheld:
                events.append(withheld)
                return "acquiring"
            self.confirmed = True
            events.append("confirmed")
        self.recall = (self.state, float(self.state.t_s))  # the confirmed track and its time, kept through a loss
        return "tracking" if backed else "coasting"

    def _recall_veto(self, mean: np.ndarray) -> str | None:
        """Why a bank about to be confirmed with the state mean (12,) is not, or None: the last confirmed track
        (lost within integrity.recall_s), propagated to now with the filter's dynamics (its covariance times
        recall_cov_factor, its attitude sigma still within recall_att_sigma_deg), puts the claim at its twin
        (integrity.recall_says_twin). A memory too old or too wide is forgotten; none (a cold start) vetoes nothing."""
        if self.recall is None:
            return None
        ic, (rec, t_confirmed) = self.cfg.integrity, self.recall
        t_s = float(self.state.t_s)
        age = t_s - t_confirmed
        if age > ic.recall_s:
            self.recall = None
            return None
        m, P = predict_to(rec, t_s, self.setup) if age > 0 else (rec.mean, rec.cov)
        sigma = pose_sigmas(P[0] * ic.recall_cov_factor)[1]
        if not (np.isfinite(m[0]).all() and sigma <= ic.recall_att_sigma_deg):
            self.recall = None
            return None
        self.recall = (dataclasses.replace(rec, t_s=t_s, chaser=self.state.chaser, mean=m, cov=P), t_confirmed)
        said = recall_says_twin(mean, m[0], sigma, self.namings)
        if said is None:
            return None
        return (f"claim withheld: the track lost {age:.0f} s ago, propagated, puts this pose at its twin "
                f"({said[1]:.0f} deg from the twin, {said[0]:.0f} deg from itself)")

    def _rejected(self, prior, z, mask, cov, best) -> np.ndarray:
        """Corners of the best hypothesis the chi-square gate rejects (its own per-corner rule from the prior's
        sigma points; the visibility check's drops count as rejected too)."""

        if not mask[best].any() or self.setup.gate_threshold is None:
            return np.zeros(self.K, bool)
        d2 = self._corner_d2(prior, z, cov, best)
        vis = (self.setup.visible_by_prior(prior[0][best], prior[1][best]) if self.fcfg.visibility_check
               else np.ones(self.K, bool))
        return mask[best] & ((d2 > self.setup.gate_threshold) | ~vis)

    def _corner_d2(self, prior, z, cov, h) -> np.ndarray:
        """(8,) each corner's squared Mahalanobis distance from hypothesis h's predicted corner, under the prior's
        spread (its sigma points through the measurement model) plus cov[h] (8, 2, 2) at the filter's R scale."""

        # the filter's own sigma points (its chart's: in 'rotation' the gate's Pzz is that of chart_retract's)
        S = chart_sigma_points(prior[0][h], prior[1][h], self.setup.weights, self.setup.cfg.sigma_chart)  # (25, 12)
        uv = self.setup.hx(S)  # (25, 8, 2)
        Wm, Wc = self.setup.weights.Wm, self.setup.weights.Wc
        mu = np.einsum("s,skj->kj", Wm, uv)
        d = uv - mu
        Pzz = np.einsum("s,ski,skj->kij", Wc, d, d) + cov[h] * self.state.r_scale[h]
        y = z[h] - mu
        return np.einsum("ki,ki->k", y, np.linalg.solve(Pzz, y[..., None])[..., 0])
