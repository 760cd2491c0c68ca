"""The Tracker's frames before a bank runs (status "acquiring", pipelines/tracking/tracker.py's docstring): each lit
frame's named corners give a PnP pose into the window (robust_pnp: the keypoints a gross outlier's frame's pose
refuses are dropped from it and reported rejected), and a full window is fitted under every naming (the cold
start, pipelines/tracking/acquisition.py) until a fit passes its integrity tests and starts the bank. A part of the
Tracker (AcquiringSteps, one of its bases): its methods read and set the Tracker's own state."""

from __future__ import annotations

import time

import numpy as np

from envisat_pose.pipelines.tracking.acquisition import (
    BatchFit,
    FramePose,
    align_namings,
    appearance_log_likelihood,
    batch_fits,
    initial_guess,
    naming_state,
    renamed_window,
)
from envisat_pose.pipelines.tracking.focal_check import focal_problems, focal_reading
from envisat_pose.pipelines.tracking.integrity import fit_problems, state_problems
from envisat_pose.pipelines.tracking.noise import detection_measurement
from envisat_pose.pipelines.tracking.robust_pnp import robust_pnp
from envisat_pose.pipelines.tracking.tracker_config import ACQUIRING_SIGMA, TrackEstimate
from envisat_pose.state import N_STATE


class AcquiringSteps:
    """The Tracker's acquiring frames: _acquire (one frame without a bank) and _cold_start (the window fitted)."""

    def _acquire(self, t_s: float, image) -> TrackEstimate:
        events: list[str] = []
        fd, t_det = (None, 0.0) if image is None else self._detect(image)
        t0 = time.perf_counter()
        measured = rejected = np.zeros(self.K, bool)
        if fd is not None:
            z, cov, p_alt = detection_measurement(fd, self.inflation, self.bias_scale)
            measured = np.isfinite(z).all(-1)
            pose = robust_pnp(z, cov, self.keypoints_T_m, self.camera, self.cfg.fit.gate,
                              self.cfg.acquire.min_keypoints)
            if pose is not None:  # the keypoints the frame's pose refuses never reach the window's fit
                rejected = measured & ~pose.inliers
                z, cov = np.where(rejected[:, None], np.nan, z), np.where(rejected[:, None, None], np.nan, cov)
                if self.buffer and t_s - self.buffer[-1].t_s > self.cfg.acquire.max_gap_s:
                    self.buffer = []
                self.buffer.append(FramePose(t_s, self.chaser_at(t_s), z, cov, p_alt, pose.x))
                self.last_pose = pose.x
        if len(self.buffer) >= self.cfg.acquire.frames:
            events += self._cold_start()
        t_fit = time.perf_counter() - t0
        timing = {"detection": t_det, "filtering": t_fit}
        if self.state is not None:
            return self._estimate(t_s, fd=fd, naming=0, measured=measured, rejected=np.zeros(self.K, bool), roi=None,
                                  converged=False, events=tuple(events), timing=timing, status="acquiring")
        P = np.diag(np.repeat(np.square(ACQUIRING_SIGMA), 3))
        x = self.last_pose if self.last_pose is not None else np.full(N_STATE, np.nan)
        if self.last_pose is None:
            P = np.full((N_STATE, N_STATE), np.nan)
        return TrackEstimate(t_s=t_s, status="acquiring", x_hat=x.copy(), P=P, hypotheses=np.zeros((0, N_STATE)),
                             probabilities=np.zeros(0), detection=fd, naming=0 if measured.any() else -1,
                             measured=measured, rejected=rejected, nis=0.0, nis_dof=0, roi_px=None,
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
        frames, _ = align_namings(self.buffer, self.namings)
        guess = initial_guess(frames)
        nm = self.namings
        fits = batch_fits([renamed_window(frames, h, nm) for h in range(nm.count)],
                          np.stack([naming_state(guess, h, nm) for h in range(nm.count)]), self.chaser_at, self.camera,
                          self.dyn, self.cfg.fit.iterations, self.cfg.fit.huber, self.cfg.fit.gate, self.keypoints_T_m)

        def cost(f: BatchFit) -> float:
            return f.chi2 + self.cfg.fit.gate * f.rejected

        log_dyn = np.array([-0.5 * cost(f) for f in fits])
        log_app = appearance_log_likelihood(frames, self.cfg.bank.appearance_clip, self.namings) \
            / self.cfg.bank.appearance_frames
        state = [state_problems(f.x, f.P, self.camera, self.radius_m, self.cfg.integrity) if f.valid else []
                 for f in fits]  # an invalid fit's problem is fit_problems' own
        share = self.cold_start_reject_share()
        problems = [fit_problems(f, len(frames), self.cfg.integrity, self.cfg.acquire.min_keypoints, share) or s
                    for f, s in zip(fits, state)]
        ok = np.array([not p for p in problems])
        if ok.any() and self.cfg.integrity.focal_check:  # the frames' own focal length against the camera's
            best = int(np.argmin([cost(f) if good else np.inf for f, good in zip(fits, ok)]))
            focal = self._focal_problems(renamed_window(frames, best, nm), fits[best].used)
            if focal:  # every naming reads the same focal length: the window starts none
                ok[:], problems[0] = False, focal
        if not ok.any():
            self.buffer = self.buffer[len(self.buffer) // 2:]
            self.last_refusal = '; '.join(problems[0])
            return [f"cold start refused: {self.last_refusal}"]
        # Once one fit passes, every twin whose fit is valid and physical starts beside it, failed fit statistics
        # or not: the twins fit the same window, so a chi-square or rejection count just past its bound for one
        # and just inside it for another is the window's noise, not evidence between them (the four twins' costs
        # can lie within 1 % of each other; one started alone was claimed 180 deg off: docs/history.md). The bank
        # weighs them by their fit cost and appearance and drops at once those below 1 - bank.decided, so a far
        # worse fit never starts.
        start = np.array([f.valid and not s for f, s in zip(fits, state)])
        self.buffer = []
        # the fits' P (on additive differences at their states) starts a bank of either chart: at the mean the
        # rotation chart's coordinates are the additive ones to first order (ukf.chart_local's derivative is I)
        P = np.stack([f.P for f in fits])[start] * self.cfg.acquire.start_cov_factor
        self._start(np.stack([f.x for f in fits])[start], P, fits[0].t_s, log_dyn[start], log_app[start])
        return ["started"]

    def _focal_problems(self, window: list[FramePose], used: np.ndarray) -> list[str]:
        """Why the window's frames refuse the camera's focal length (focal_check.focal_problems; empty where they
        agree or cannot say), read from the keypoints the fit kept (used (N, K))."""
        cam = self.camera
        reading = focal_reading(np.stack([f.z_px for f in window]), np.stack([f.cov_px for f in window]), used,
                                self.keypoints_T_m, cam.f_px, cam.cu_px, cam.cv_px)
        return focal_problems(reading, self.cfg.integrity)
