"""The tracker's types: its config (TrackerConfig, one section per component), what it says after each frame
(TrackEstimate), and the filter settings it starts from (TRACKER_FILTER).

In a TOML file the sections are tables under [tracker]: `[tracker.acquire]`, `[tracker.bank]`, `[tracker.fit]`,
`[tracker.array_cue]`, `[tracker.roi]`, `[tracker.integrity]`, `[tracker.noise]`, `[tracker.gate]`. A key of the
old flat layout directly under [tracker] is refused with one line naming its new home (MOVED_KEYS); a renamed key
(`min_corners`, now `min_keypoints` for any target's keypoints) is taken for one release with a warning naming its
new name (config.renamed_fields)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from envisat_pose.config import Config, check, renamed_fields
from envisat_pose.filtering.filter_config import SIGMA_MAX, SIGMA_MIN
from envisat_pose.gates import GATE_PROB, chi2_gate
from envisat_pose.pipelines.tracking import tracker_bounds as B
from envisat_pose.pipelines.tracking.noise import CORRELATION_IN, CORRELATION_MODELS

# the covariance reported while acquiring (no filter yet): position m, velocity m/s, MRP, rate rad/s (1-sigma)
ACQUIRING_SIGMA = (5.0, 1.0, 0.5, 0.1)
# the filter settings the tracker starts from (under a scenario's [filter] table and the user's): adaptive R that
# only ever raises R above the detector's modelled covariance, and no gate lockout (a lost track is re-acquired
# from the images instead of taking one frame ungated)
# visibility_from "mean": the detector's names of keypoints the prior mean hides are mislabels (a twin's names),
# which the spread of a wide acquisition prior lets through (FilterConfig.visibility_from)
TRACKER_FILTER = {"adaptive_r": True, "adaptive_r_bounds": (1.0, 100.0), "gate_lockout_steps": 1_000_000,
                  "visibility_from": "mean"}


def _dot(prefix: str) -> str:
    return f"{prefix}." if prefix else ""


@renamed_fields(min_corners="min_keypoints")
@dataclass(frozen=True)
class AcquireConfig(Config):
    """The cold start (pipelines/tracking/acquisition.py).

    frames: lit frames with a PnP pose in the cold-start window; min_keypoints: named keypoints a frame needs for
    a pose (and the keypoints a cold-start fit must keep per frame on average: integrity.fit_problems; its old name
    min_corners taken one release, deprecated); max_gap_s: a longer gap between buffered frames restarts the
    window.
    start_cov_factor: the cold-start fit's covariance is multiplied by this when a bank starts. The window's
    frames are fewer than the errors' correlation allows a fit to average (twenty frames against a 13 s
    correlation time); without it the first ~30 s after a start were over-confident (NEES per block 10-30 of 3 on
    slow-tumble seeds 0 and 7) while the state was right.
    """

    frames: int = 20
    min_keypoints: int = 4
    max_gap_s: float = 30.0
    start_cov_factor: float = 4.0

    def validate(self, prefix: str = "tracker.acquire") -> None:
        p = _dot(prefix)
        check(self.frames >= 3, f"{p}frames", self.frames, "at least 3 frames")
        check(self.min_keypoints >= 4, f"{p}min_keypoints", self.min_keypoints,
              "at least 4 keypoints (PnP's least; at most the target's, which the Tracker checks)")
        check(B.MIN_FRAME_DT_S <= self.max_gap_s <= B.MAX_PREDICTION_S, f"{p}max_gap_s", self.max_gap_s,
              f"a gap in [{B.MIN_FRAME_DT_S:g}, {B.MAX_PREDICTION_S:g}] s (the least frame interval; the longest a "
              "track is predicted over, as the cold start's fit is across its gaps)")
        check(1.0 <= self.start_cov_factor <= B.MAX_COV_FACTOR, f"{p}start_cov_factor", self.start_cov_factor,
              f"a factor in [1, {B.MAX_COV_FACTOR:g}] (the widest ratio of the variances the filter takes)")


@dataclass(frozen=True)
class FitConfig(Config):
    """The cold start's batch fit (acquisition.batch_fit).

    iterations, huber (whitened px), gate_prob (the probability a corner's 2-dof chi-square passes the fit's
    gate; `gate` the bound): the batch fit.
    """

    iterations: int = 15
    huber: float = 3.0
    gate_prob: float = GATE_PROB

    @property
    def gate(self) -> float:
        """The batch fit's chi-square gate per corner (2 dof) at gate_prob (23.03 at the default)."""
        return chi2_gate(self.gate_prob, 2)

    def validate(self, prefix: str = "tracker.fit") -> None:
        p = _dot(prefix)
        check(self.iterations >= 1, f"{p}iterations", self.iterations, "at least 1")
        check(B.MIN_HUBER <= self.huber <= B.MAX_HUBER, f"{p}huber", self.huber, f"a whitened residual in "
              f"[{B.MIN_HUBER:g}, {B.MAX_HUBER:g}] (below, the fit never leaves its guess; at {B.MAX_HUBER:g} "
              "every corner counts fully: least squares)")
        check(0.5 < self.gate_prob < 1.0, f"{p}gate_prob", self.gate_prob, "a probability in (0.5, 1)")


@dataclass(frozen=True)
class BankConfig(Config):
    """The bank of half-turn hypotheses and the evidence between them (pipelines/tracking/bank.py).

    decided: a half-turn hypothesis whose probability exceeds this wins and the other is dropped.
    evidence_prob: a frame whose innovations every hypothesis finds beyond the chi-square bound at this tail
    probability adds nothing to their dynamics' log-likelihoods (bank.frame_discriminates): it contradicts them
    all, so their NIS differences are the detector's error, not evidence between the twins.
    appearance_clip: the detector's per-frame half-turn probability is clipped to [clip, 1 - clip].
    appearance_frames: consecutive frames whose appearance cues count as one independent look (each frame's
    log-likelihood is divided by it): the detector's half-turn errors repeat while the view changes little (wrong
    in 16 of 20 consecutive frames of a default sequence), so independent sums would let one look outvote the
    dynamics.
    appearance_max_log: the most (nats) the detector's appearance counts between two hypotheses however many
    frames repeat it (3.0: one confident look, a likelihood ratio of 20), below the 6.9 a decision at 0.999 needs:
    the appearance never decides a half-turn alone, the dynamics must agree (its errors persist over a whole
    view: without the cap a slow-tumble trial claimed the twin 180 deg off for 61 s; docs/history.md).
    evidence_memory: the memory at which the detector's frame-to-frame error correlation is counted in the
    dynamics' log-likelihoods. "filter": as the filter's update counts it, at the filter's own memory (R x
    tau(lambda)); "long": as a sum over every frame of the bank needs it, each frame's cost weighted by
    tau(lambda) / tau(1) (noise.evidence_weight). Twins whose predicted corners differ by a fraction of a pixel
    gain evidence mostly from the detector's repeated errors projected on that difference (0.25 px apart: 1.8 nats
    of separation at most over 17 frames, against NIS sums 9.6 nats apart; docs/history.md).
    frame_max_log: the most (nats) one frame's dynamics evidence (its cost: NIS, rejected and dropped keypoints)
    moves a hypothesis against that frame's best: a frame is taken as one the model does not hold (a keypoint
    named as its twin, an outlier the gate rejects) with a few per cent probability, so its likelihood ratio is
    bounded (3.0: a ratio of 20) and a decision at 0.999 (6.9 nats) needs three frames that agree. Without it one
    misnamed keypoint of a target whose twins only the inertia tells apart gave the wrong twin 8.4 nats in one
    frame, decided at once and claimed 39 frames 180 deg off (docs/history.md). 0: no bound.
    appearance_veto: a hypothesis the detector's appearance alone would decide for against the bank's best (its
    summed log-likelihoods, as counted before the cap, ahead by more than log(decided / (1 - decided)), 6.9 nats)
    stays open however unlikely the rest makes it: the dynamics never decide a half-turn against what the
    detector's look alone would decide, as the look never decides one alone (appearance_max_log). On default
    seed 3 at 512 px the twins' dynamics drew 9.6 nats apart on the detector's repeated errors while its
    appearance favoured the truth by 9-10 nats; the truth was dropped and the twin claimed (docs/history.md).
    """

    decided: float = 0.999
    evidence_prob: float = 0.01
    appearance_clip: float = 0.05
    appearance_frames: float = 10.0
    appearance_max_log: float = 3.0
    evidence_memory: str = "filter"
    frame_max_log: float = 3.0
    appearance_veto: bool = True

    def validate(self, prefix: str = "tracker.bank") -> None:
        p = _dot(prefix)
        check(0.5 < self.decided < 1.0, f"{p}decided", self.decided, "a probability in (0.5, 1)")
        check(0.0 < self.evidence_prob < 0.5, f"{p}evidence_prob", self.evidence_prob, "a probability in (0, 0.5)")
        check(0.0 < self.appearance_clip < 0.5, f"{p}appearance_clip", self.appearance_clip,
              "a probability in (0, 0.5)")
        check(0.0 <= self.appearance_max_log <= B.MAX_LOG_NATS, f"{p}appearance_max_log", self.appearance_max_log,
              f"a log-likelihood in [0, {B.MAX_LOG_NATS:.1f}] nats (beyond, its likelihood ratio overflows)")
        check(0.0 <= self.frame_max_log <= B.MAX_LOG_NATS, f"{p}frame_max_log", self.frame_max_log,
              f"a log-likelihood in [0, {B.MAX_LOG_NATS:.1f}] nats (0: no bound; beyond, its ratio overflows)")
        check(self.appearance_frames >= 1.0, f"{p}appearance_frames", self.appearance_frames, "at least 1 frame")
        check(self.evidence_memory in ("filter", "long"), f"{p}evidence_memory", self.evidence_memory,
              "'filter' or 'long'")


@dataclass(frozen=True)
class ArrayCueConfig(Config):
    """The solar array cue (perception/arraycue.py, bank.array_log_likelihood).

    enabled: weigh the twins by the half-turn about y or z by where the image shows the solar array
    (perception/arraycue.py; read under the best hypothesis' predicted pose once it is converged, while the bank
    holds hypotheses at both ends): per_frame nats a frame to the hypotheses at the end it shows, at most
    max_log (nats) between two hypotheses in all. Those twins put the corners where the truth does and differ
    from it in the dynamics only by the signs of two small products of inertia (the y twin keeps Ixz, the
    largest), so the dynamics take tens of seconds to part them on a slow tumble. The cue is read right or not at
    all: under the true pose 0 wrong readings of 1742 given (1619 of 3600 loop frames, 123 of 300 random views; it
    abstains on the rest, the Earth behind the target among them; docs/history.md). Capped below the 6.9 nats a
    decision needs, so the dynamics and the detector's appearance must not contradict it. With one hypothesis left
    the cue is read on every whole converged frame (not on a frame made as a window alone: Tracker.step's
    window_px; the closed loop makes every frame whole until the claim is confirmed, then one in
    RunConfig.full_frame_every) as an integrity test: lost_readings readings in a row against it (abstentions
    between them allowed) lose the track (a decided y or z twin would claim a pose 180 deg off while every corner
    fits).
    """

    enabled: bool = True
    per_frame: float = 1.0
    max_log: float = 6.0
    lost_readings: int = 3

    def validate(self, prefix: str = "tracker.array_cue") -> None:
        p = _dot(prefix)
        for name in ("per_frame", "max_log"):
            check(0.0 <= getattr(self, name) <= B.MAX_LOG_NATS, f"{p}{name}", getattr(self, name),
                  f"a log-likelihood in [0, {B.MAX_LOG_NATS:.1f}] nats (beyond, its likelihood ratio overflows)")
        check(self.lost_readings >= 1, f"{p}lost_readings", self.lost_readings, "at least 1 reading")


@renamed_fields(min_corners="min_keypoints")
@dataclass(frozen=True)
class RoiConfig(Config):
    """The region of interest and the priors the detector is given (tracker.predicted_roi,
    Tracker._detect_predicted).

    enabled: look only in the predicted region of interest once converged; margin: its side over the predicted
    corners' extent (plus 6 x the prior's pixel sigma); min_side_px; min_keypoints: fewer keypoints found there and
    the coarse pass runs again (its old name min_corners taken one release, deprecated). converged_pos_sigma_m /
    converged_att_sigma_deg: the prior counts as converged (ROI, attitude prior) below these. prior_attitude: give
    the detector the predicted attitude; prior_pose: with it, the predicted position too, so its naming starts from
    the predicted pose instead of searching every face hypothesis (half of the detector's time in the loop; the
    search still runs when the predicted pose matches fewer than 4 corners). prior_pose_twins: while the bank still
    holds a pose and its symmetric twins, the best one's predicted pose seeds the naming too, without weighing the
    half-turn (the twins are one physical pose; the detector's half-turn probability stays the image's own).
    Without it the detector searches every face on its own in those frames and, on near end-on views, names four
    corners of one face wrongly for frames in a row: enough rejections in a young bank's window to lose a correct
    start (docs/history.md).
    """

    enabled: bool = True
    margin: float = 1.4
    min_side_px: int = 64
    min_keypoints: int = 4
    converged_pos_sigma_m: float = 0.2
    converged_att_sigma_deg: float = 2.0
    prior_attitude: bool = True
    prior_pose: bool = True
    prior_pose_twins: bool = True

    def validate(self, prefix: str = "tracker.roi") -> None:
        p = _dot(prefix)
        check(self.margin >= 1.0, f"{p}margin", self.margin, "a factor >= 1")
        check(16 <= self.min_side_px <= 4096, f"{p}min_side_px", self.min_side_px, "a side in [16, 4096] px")
        check(self.min_keypoints >= 1, f"{p}min_keypoints", self.min_keypoints,
              "at least 1 keypoint (at most the target's, which the Tracker checks)")
        check(0 < self.converged_pos_sigma_m <= SIGMA_MAX, f"{p}converged_pos_sigma_m", self.converged_pos_sigma_m,
              f"a positive sigma in m, at most {SIGMA_MAX:g} (the widest the filter takes)")
        check(0 < self.converged_att_sigma_deg <= 180.0, f"{p}converged_att_sigma_deg", self.converged_att_sigma_deg,
              "a positive sigma in deg, at most 180 (a wider one knows nothing of the attitude)")


@dataclass(frozen=True)
class IntegrityConfig(Config):
    """Integrity and loss (pipelines/tracking/integrity.py): the tests a hypothesis' own evidence must pass every frame,
    the claim's bounds, and when a track is lost.

    lost_after_frames: frames in a row with an image and no corner used by the best hypothesis (coasting: nothing
    found, or every corner rejected) that declare the track lost, every hypothesis of the bank with it. Frames
    without an image (eclipse, gaps) coast until the covariance leaves the lost bounds below.
    window: frames of evidence per hypothesis (20: a burst of 4 frames of mis-named corners, which the gate
    rejects while the state stays right, does not lose a correct track, as it did with 8; a track that disagrees
    with the images for good still fails within ~5 frames); prob: the false-alarm probability of each
    test (the cold-start fit's chi-square, the windowed NIS, the rejections); expected_reject_share: the share of
    the corners given that a correct track's gate rejects, against which a window's rejections are tested (a
    binomial tail); unset (None), a started track's window expects the detector's own, measured by its calibration
    where it carries one (a keypoint detector calibrated by `calibrate --target`: at the frame's gate and
    inflation, Tracker.reject_share), and the cold start integrity.DEFAULT_REJECT_SHARE (0.1: ENVISAT's corner
    network mis-names 3-13 % on random views, fewer in the loop's region of interest with the predicted pose as the
    naming's start); set, both take it; confirm_frames frames with corners used, after the
    half-turn is decided and with the claim's covariance, before a new bank claims "tracking"; claim_pos_share
    (of the range) and claim_att_deg bound the 3-sigma position and attitude a "tracking" frame claims (beyond
    them a running track reports "coasting"); lost_pos_sigma_share and lost_att_sigma_deg bound the 1-sigma a
    track may reach before it is lost; min_target_px the smallest apparent size of the box (twice its radius) the
    image can show, which bounds the range; max_rate_deg_s and max_speed_m_s the tumble rate and relative speed a
    state may have. recall_s: how long after its last confirmed frame a lost track is remembered (0: never): a
    re-acquired bank whose claim the memory, propagated with the filter's dynamics and its covariance times
    recall_cov_factor, puts at the memory's twin is not confirmed while that attitude sigma is within
    recall_att_sigma_deg (slow-tumble seed 7 claimed the half-turn twin 25 s after losing a correct track, 119 s).
    focal_check: a cold start is refused when its window's frames read another focal length than the camera's, off
    by more than focal_tolerance (a share) with the evidence beyond its bound at prob
    (pipelines/tracking/focal_check.py); off, a wrong focal length is tracked at a range as far off. 0.15: a
    camera's calibration is good to a few per cent, and correct windows read up to 1.08 (ENVISAT at 20 m, the
    upper stage's weak detector at ratio 34.6, past the ratio's bound: docs/design.md): a wrong lens, a crop or a
    typed focal length is refused, not a calibration.
    """

    lost_after_frames: int = 10
    window: int = 20
    prob: float = 1e-6
    expected_reject_share: float | None = None
    confirm_frames: int = 5
    claim_pos_share: float = 0.02
    claim_att_deg: float = 5.0
    lost_pos_sigma_share: float = 0.1
    lost_att_sigma_deg: float = 20.0
    min_target_px: float = 8.0
    max_rate_deg_s: float = 30.0
    max_speed_m_s: float = 5.0
    recall_s: float = 300.0
    recall_att_sigma_deg: float = 30.0
    recall_cov_factor: float = 4.0
    focal_check: bool = True
    focal_tolerance: float = 0.15

    def validate(self, prefix: str = "tracker.integrity") -> None:
        p = _dot(prefix)
        check(self.lost_after_frames >= 1, f"{p}lost_after_frames", self.lost_after_frames, "at least 1 frame")
        check(2 <= self.window <= B.MAX_RUN_FRAMES, f"{p}window", self.window,
              f"2 to {B.MAX_RUN_FRAMES} frames (the longest run's; a longer window never fills)")
        check(0.0 < self.prob < 0.5, f"{p}prob", self.prob, "a probability in (0, 0.5)")
        check(self.expected_reject_share is None or 0.0 < self.expected_reject_share < 1.0,
              f"{p}expected_reject_share", self.expected_reject_share, "a share in (0, 1), or unset: the detector's")
        check(1 <= self.confirm_frames <= self.window, f"{p}confirm_frames", self.confirm_frames,
              f"1 to window ({self.window}) frames")
        check(0.0 < self.claim_pos_share < self.lost_pos_sigma_share * 3.0, f"{p}claim_pos_share",
              self.claim_pos_share, "a share of the range in (0, 3 x lost_pos_sigma_share)")
        check(0.0 < self.claim_att_deg < 3.0 * self.lost_att_sigma_deg, f"{p}claim_att_deg", self.claim_att_deg,
              "an angle in deg in (0, 3 x lost_att_sigma_deg)")
        check(0.0 < self.lost_pos_sigma_share <= 1.0, f"{p}lost_pos_sigma_share", self.lost_pos_sigma_share,
              "a share of the range in (0, 1]")
        check(0.0 < self.lost_att_sigma_deg <= 90.0, f"{p}lost_att_sigma_deg", self.lost_att_sigma_deg,
              "an angle in (0, 90] deg")
        check(B.MIN_TARGET_PX <= self.min_target_px <= B.MAX_TARGET_PX, f"{p}min_target_px", self.min_target_px,
              f"a size in [{B.MIN_TARGET_PX:g}, {B.MAX_TARGET_PX:g}] px (a pixel; the largest image side)")
        check(0 < self.max_rate_deg_s <= B.MAX_RATE_DEG_S, f"{p}max_rate_deg_s", self.max_rate_deg_s,
              f"a positive rate of at most {B.MAX_RATE_DEG_S:.0f} deg/s (the fastest tumble the truth's RK4 follows)")
        check(0 < self.max_speed_m_s <= B.MAX_SPEED_M_S, f"{p}max_speed_m_s", self.max_speed_m_s,
              f"a positive speed of at most {B.MAX_SPEED_M_S:.0f} m/s (twice the escape speed: no two orbits meet "
              "faster)")
        check(0 <= self.recall_s <= B.MAX_PREDICTION_S, f"{p}recall_s", self.recall_s, f"a time in [0, "
              f"{B.MAX_PREDICTION_S:g}] s (0: no memory; the memory is predicted as a track is, at most that far)")
        check(0.0 < self.recall_att_sigma_deg <= 60.0, f"{p}recall_att_sigma_deg", self.recall_att_sigma_deg,
              "an angle in (0, 60] deg")
        check(1.0 <= self.recall_cov_factor <= B.MAX_COV_FACTOR, f"{p}recall_cov_factor", self.recall_cov_factor,
              f"a factor in [1, {B.MAX_COV_FACTOR:g}] (the widest ratio of the variances the filter takes)")
        check(0.0 < self.focal_tolerance < 1.0, f"{p}focal_tolerance", self.focal_tolerance, "a share in (0, 1)")


@dataclass(frozen=True)
class NoiseConfig(Config):
    """The filter's R and process noise from the detector (pipelines/tracking/noise.py).

    correlation_model: how R allows for the errors' frame-to-frame correlation (module doc): "filter_memory",
    "long_memory" or "white".
    correlation_in: what the correlation falls with between frames (noise.ar1_at): "rotation" (default: the
    view's, at the tracked rate |w_r|, where the error model measured it; time while acquiring, before a rate is
    estimated), "time" (the time fit, one correlation time pooled over the held-out tumble rates) or "slower"
    (whichever of the two lasts longer at the tracked rate). The detector's errors persist while the view has not
    turned: their correlation angle stays near 30 deg (26-33) while their correlation time runs from 7.6 s at 5
    deg/s to 14.9 s at 1.6 deg/s, so one pooled time over-inflates a fast tumble and under-inflates a slow one.
    range_floor: report the position variance along the line of sight plus (noise.scale_sigma x range)^2, the
    range error of the detector's apparent scale that no number of frames averages away (pipelines/tracking/noise.
    range_consider: a consider term in the reported covariance, not in the filter's gain: in the gain the filter
    follows each frame's range instead of averaging them). Without it the loops are over-confident in range (mean
    NEES 50.9 on a slow tumble).
    detector_q_sigma: process noise per sqrt(s) in filter.q_sigma's groups (position m, velocity m/s, MRP, rad/s)
    that stands for the detector's errors the error model does not carry: view-dependent biases that persist for
    tens of seconds on a slow tumble and that a filter with a torque-free model and an exactly known relative
    orbit (the scenarios' q_sigma 1e-8, 1e-8, 1e-9, 1e-10) would read as attitude, rate and velocity; the
    filter's own q_sigma is raised to at least these: on a slow tumble, mean NEES 36.5 -> 18.4 with the attitude
    and rate terms, then 19.6 -> 13.9 with the velocity term, at the same RMSE.
    correct_scale: undo the detector's mean apparent scale (the error model's bias_scale) about the corners'
    centroid in every frame; what is left, a run's own scale about that mean (bias_scale_sd), stays in the
    reported covariance. The mean must be measured in the loop's regime (lit sequences of every scenario, the
    labels' region of interest, the patch pass): a mean off by 5.5e-4 moves the range 2.7 cm at 50 m.
    """

    correlation_model: str = "filter_memory"
    correlation_in: str = "rotation"
    range_floor: bool = True
    detector_q_sigma: tuple[float, float, float, float] = (0.0, 3e-6, 1e-5, 3e-6)
    correct_scale: bool = True

    def validate(self, prefix: str = "tracker.noise") -> None:
        p = _dot(prefix)
        check(self.correlation_model in CORRELATION_MODELS, f"{p}correlation_model", self.correlation_model,
              f"one of {', '.join(CORRELATION_MODELS)}")
        check(self.correlation_in in CORRELATION_IN, f"{p}correlation_in", self.correlation_in,
              f"one of {', '.join(CORRELATION_IN)}")
        check(len(self.detector_q_sigma) == 4 and all(q == 0 or SIGMA_MIN <= q <= SIGMA_MAX
                                                      for q in self.detector_q_sigma),
              f"{p}detector_q_sigma", list(self.detector_q_sigma), f"four sigmas per sqrt(s), each 0 or in "
              f"[{SIGMA_MIN:g}, {SIGMA_MAX:g}], as filter.q_sigma (m, m/s, MRP, rad/s)")


@dataclass(frozen=True)
class GateConfig(Config):
    """Which covariance the tracker gates a corner against before the filter's update.

    raw: gate each corner against the detector's own covariance at the error model's scale (without the
    correlation's inflation) plus the prior's spread, before the update; a corner beyond the gate is dropped and
    counts as rejected. The inflation says how little a filter may average the errors, not how large one
    frame's error may be: gated against the inflated R (x 5-8 at the filter's memory), corners 4-5 px off with a
    0.5-0.9 px covariance pass and can pull the range 16 cm off. Off by default: measured as an ablation
    (docs/history.md).
    """

    raw: bool = False

    def validate(self, prefix: str = "tracker.gate") -> None:
        pass


SECTIONS = ("acquire", "fit", "bank", "array_cue", "roi", "integrity", "noise", "gate")
# the flat layout's keys (before the sections) -> their section.key, for the one-line hint on an old file
MOVED_KEYS = {
    "acquire_frames": "acquire.frames", "acquire_min_corners": "acquire.min_keypoints",
    "max_gap_s": "acquire.max_gap_s", "start_cov_factor": "acquire.start_cov_factor",
    "fit_iterations": "fit.iterations", "fit_huber": "fit.huber", "fit_gate_prob": "fit.gate_prob",
    "decided": "bank.decided", "evidence_prob": "bank.evidence_prob", "appearance_clip": "bank.appearance_clip",
    "appearance_frames": "bank.appearance_frames", "appearance_max_log": "bank.appearance_max_log",
    "array_cue": "array_cue.enabled", "array_cue_per_frame": "array_cue.per_frame",
    "array_cue_max_log": "array_cue.max_log", "array_lost_readings": "array_cue.lost_readings",
    "roi": "roi.enabled", "roi_margin": "roi.margin", "roi_min_side_px": "roi.min_side_px",
    "roi_min_corners": "roi.min_keypoints", "converged_pos_sigma_m": "roi.converged_pos_sigma_m",
    "converged_att_sigma_deg": "roi.converged_att_sigma_deg", "prior_attitude": "roi.prior_attitude",
    "prior_pose": "roi.prior_pose", "prior_pose_twins": "roi.prior_pose_twins",
    "lost_after_frames": "integrity.lost_after_frames", "integrity_window": "integrity.window",
    "integrity_prob": "integrity.prob", "expected_reject_share": "integrity.expected_reject_share",
    "confirm_frames": "integrity.confirm_frames", "claim_pos_share": "integrity.claim_pos_share",
    "claim_att_deg": "integrity.claim_att_deg", "lost_pos_sigma_share": "integrity.lost_pos_sigma_share",
    "lost_att_sigma_deg": "integrity.lost_att_sigma_deg", "min_target_px": "integrity.min_target_px",
    "max_rate_deg_s": "integrity.max_rate_deg_s", "max_speed_m_s": "integrity.max_speed_m_s",
    "correlation_model": "noise.correlation_model", "correlation_in": "noise.correlation_in",
    "range_floor": "noise.range_floor", "detector_q_sigma": "noise.detector_q_sigma",
    "correct_scale": "noise.correct_scale", "gate_raw": "gate.raw",
}


@dataclass(frozen=True)
class TrackerConfig(Config):
    """How the tracker uses the detector and the filter, one frozen section per component (each documents its
    fields and their measured justifications): acquire (the cold start's window), fit (its batch fit), bank (the
    half-turn hypotheses and the evidence between them), array_cue (the solar array cue), roi (the region of
    interest and the priors given to the detector), integrity (the tests of a hypothesis' evidence, the claim and
    loss), noise (R and the process noise from the detector's error model), gate (what a corner is gated
    against). In TOML: [tracker.acquire], [tracker.fit], ... (module docstring)."""

    acquire: AcquireConfig = field(default_factory=AcquireConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    bank: BankConfig = field(default_factory=BankConfig)
    array_cue: ArrayCueConfig = field(default_factory=ArrayCueConfig)
    roi: RoiConfig = field(default_factory=RoiConfig)
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    gate: GateConfig = field(default_factory=GateConfig)

    moved_keys: ClassVar[dict[str, str]] = MOVED_KEYS  # config.from_dict's hint for a flat file's key

    def validate(self, prefix: str = "tracker") -> None:
        for name in SECTIONS:
            getattr(self, name).validate(f"{_dot(prefix)}{name}")


@dataclass(frozen=True, kw_only=True)
class TrackEstimate:
    """What the tracker says after one frame (built by keywords only).

    t_s: frame time, s. status: one of envisat_pose.status.STATUSES ("tracking" only when the frame's evidence
    backs it: pipelines/tracking/integrity.py). x_hat (12,): the best hypothesis' state (rho_C_m, rhodot_C_m_s,
    p_mrp, w_r_T_rad_s); P (12, 12) its covariance, in the filter's sigma_chart (NEES: filtering.estimator.nees
    with that chart; ACQUIRING_SIGMA while acquiring; NaN before any pose).
    hypotheses (H, 12) and probabilities (H,): the symmetry twins still open (H = 0 while acquiring).
    detection: the detector's FrameDetection (None when no image); naming: which naming the best hypothesis took
    (an index of the tracker's namings, pipelines/tracking/namings.py: 0 the detector's, for ENVISAT 1-3 its x, y,
    z half-turn; -1 none); measured (K,) bool: keypoints given to the filter (ENVISAT's corners: K = 8);
    rejected (K,) bool: of those, rejected by the gate; nis, nis_dof: the best hypothesis' update. roi_px (3,) or None.
    converged: the prior was tight enough for the region of interest. events: what happened this frame
    ("started", "hypothesis decided", "confirmed", "lost: <why>", "hypothesis dropped: <why>", ...), in words a
    user can act on. timing_s: detection and filtering, s. confirmed: the bank passed its confirmation (its
    evidence backed a claim once); coasting_frames: frames in a row with an image and no corner used.
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
    confirmed: bool = False
    coasting_frames: int = 0
