"""Integrity monitoring: what the tracker's own evidence must show before it claims "tracking", checked every frame.

No truth: every test reads what the tracker itself has, the filter's state and covariance, its innovations and
the corners it was given, used and rejected.

The bounds are TrackerConfig.integrity's (IntegrityConfig: `window`, `prob`, ...), passed in as `cfg`.

- A cold-start fit starts a hypothesis only if it kept most of its window's corners (`fit_problems`: the fit's
  gate rejected no more than a correct fit would at the cold start's share, Tracker.cold_start_reject_share:
  the config's or DEFAULT_REJECT_SHARE, never the detector's measured one; and the kept ones are at least
  `acquire.min_keypoints` per frame on average), its reduced chi-square is inside its chi-square bound and its state
  is physical (`state_problems`).
- Each hypothesis carries a window of its last `window` frames (`EvidenceWindow`): the NIS and its
  degrees of freedom, the corners given to the filter and those rejected. Every frame, a hypothesis fails when its
  windowed NIS exceeds its bound at `prob` (nis_window_bound: the chi-square of the window's degrees of
  freedom, dispersed by the detector's frame-to-frame correlation), when the gate rejected more of the corners it
  was given over the window than a correct track would at the frames' expected shares (a binomial tail below
  `prob`), or when its state is not physical. The expected share of a tracked frame is the tracker's
  (Tracker.reject_share: `expected_reject_share` where the config sets it, else what the detector's calibration
  measured its gate to reject on held-out frames, else DEFAULT_REJECT_SHARE). A failed hypothesis is dropped; the
  track is lost when none is left.
- A state is physical when the target's centre is in front of the camera, farther than the box's own radius
  (the camera cannot be inside the target) and near enough for the image to show the box
  (`IntegrityConfig.min_target_px`), its rate and speed inside the configured bounds, its covariance positive
  definite and its position and attitude sigmas inside `lost_pos_sigma_share` x range and `lost_att_sigma_deg`.
- A claim at the tracking accuracy (`claim_holds`): the 3-sigma position within `claim_pos_share` of the range and
  the 3-sigma attitude within `claim_att_deg` (the same tolerances a benchmark scores a false lock by).
- A re-acquired claim against the lost track's memory (`recall_says_twin`): the last confirmed state, propagated
  to now, that puts the candidate at one of its twins (a naming's symmetry, not an equivalent) withholds it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.config import check
from envisat_pose.filtering.measurements import to_camera_K
from envisat_pose.gates import chi2_bound
from envisat_pose.geometry import PinholeCamera
from envisat_pose.state import MRP, POS, RATE, VEL

DEFAULT_REJECT_SHARE = 0.1  # the corners a correct track's gate rejects, for a detector that measured none


def pose_sigmas(cov: np.ndarray) -> tuple[float, float]:
    """(largest position sigma, m; largest attitude sigma, deg) of a covariance (12, 12); the MRP sigma is a
    rotation angle of 4 sigma_p rad (small angles). NaN where the blocks are not finite. Either chart of the sigma
    points (FilterConfig.sigma_chart): the position block is the same, and the rotation chart's MRP block (of
    B(p) a, a the error MRP) is the additive one's to first order at the mean."""
    if not np.isfinite(cov).all():
        return float("nan"), float("nan")
    pos = float(np.sqrt(max(np.max(np.linalg.eigvalsh(cov[POS, POS])), 0.0)))
    att = float(np.degrees(4.0 * np.sqrt(max(np.max(np.linalg.eigvalsh(cov[MRP, MRP])), 0.0))))
    return pos, att


def target_radius_m(corners_T_m: np.ndarray) -> float:
    """The box's radius about the centre of mass, m: no camera can be nearer than this to the centre."""
    return float(np.max(np.linalg.norm(corners_T_m, axis=-1)))


def check_min_target_px(min_target_px: float, f_px: float, field: str, radius_m: float | None = None) -> None:
    """ConfigError unless IntegrityConfig.min_target_px (given as `field`) is below what the box (twice its radius)
    spans at its closest range, its own radius (state_problems: nearer, the camera is inside it): 2 f_px whatever
    the radius. At or above it the range bound f_px 2 radius / min_target_px lies inside the box, every state fails
    it, and nothing is ever tracked (no word said: each cold start's fit refused as out of range). radius_m, where
    known, is named in the message."""
    bound_px = 2.0 * f_px
    radius = f" ({radius_m:.3g} m)" if radius_m is not None else ""
    check(min_target_px < bound_px, field, min_target_px,
          f"a size below {bound_px:.4g} px: the box's apparent size at its closest range, its own radius{radius}, is "
          f"2 f = {bound_px:.4g} px under the camera's focal length f = {f_px:.4g} px (a larger one bounds the range "
          "inside the box: nothing is ever tracked)")


def check_min_keypoints(cfg, num_keypoints: int, prefix: str = "tracker") -> None:
    """ConfigError unless the keypoints a frame needs (cfg: a TrackerConfig; acquire.min_keypoints for a
    cold-start pose, roi.min_keypoints in the region of interest) are at most the target's num_keypoints: more, and
    no frame ever has enough (ENVISAT's 8 corners; another target's K)."""
    for field, value in (("acquire.min_keypoints", cfg.acquire.min_keypoints),
                         ("roi.min_keypoints", cfg.roi.min_keypoints)):
        check(value <= num_keypoints, f"{prefix}.{field}", value,
              f"at most the target's {num_keypoints} keypoints (more: no frame ever holds enough)")


def state_problems(x: np.ndarray, P: np.ndarray, camera: PinholeCamera, radius_m: float, cfg) -> list[str]:
    """Why the state x (12,) with covariance P (12, 12) is not a physical track (empty when it is). cfg: the
    IntegrityConfig (min_target_px, max_rate_deg_s, max_speed_m_s, lost_pos_sigma_share, lost_att_sigma_deg)."""

    if not (np.isfinite(x).all() and np.isfinite(P).all()):
        return ["the state or its covariance is not finite"]
    out = []
    depth_m = float(to_camera_K(x[POS], camera)[2])
    range_m = float(np.linalg.norm(x[POS]))
    max_range_m = camera.f_px * 2.0 * radius_m / cfg.min_target_px
    if depth_m <= radius_m:
        out.append(f"target not in front of the camera (depth {depth_m:.2f} m, the box's radius {radius_m:.2f} m)")
    elif range_m > max_range_m:
        out.append(f"range {range_m:.0f} m beyond the {max_range_m:.0f} m at which the box spans "
                   f"{cfg.min_target_px:g} px")
    rate = float(np.degrees(np.linalg.norm(x[RATE])))
    if rate > cfg.max_rate_deg_s:
        out.append(f"tumble rate {rate:.1f} deg/s beyond {cfg.max_rate_deg_s:g} deg/s")
    speed = float(np.linalg.norm(x[VEL]))
    if speed > cfg.max_speed_m_s:
        out.append(f"relative speed {speed:.2f} m/s beyond {cfg.max_speed_m_s:g} m/s")
    if np.linalg.eigvalsh(0.5 * (P + P.T)).min() <= 0.0:
        out.append("covariance not positive definite")
        return out
    pos_sig, att_sig = pose_sigmas(P)
    if pos_sig > cfg.lost_pos_sigma_share * max(range_m, radius_m):
        out.append(f"position sigma {pos_sig:.3g} m beyond {cfg.lost_pos_sigma_share:.0%} of the {range_m:.1f} m range")
    if att_sig > cfg.lost_att_sigma_deg:
        out.append(f"attitude sigma {att_sig:.1f} deg beyond {cfg.lost_att_sigma_deg:g} deg")
    return out


def claim_holds(x: np.ndarray, P: np.ndarray, cfg) -> bool:
    """The covariance backs a claim at the tracking accuracy: 3-sigma position within claim_pos_share of the
    range and 3-sigma attitude within claim_att_deg."""
    pos_sig, att_sig = pose_sigmas(P)
    range_m = float(np.linalg.norm(x[POS]))
    return bool(3.0 * pos_sig <= cfg.claim_pos_share * range_m and 3.0 * att_sig <= cfg.claim_att_deg)


def recall_says_twin(x: np.ndarray, x_recall: np.ndarray, recall_att_sigma_deg: float, namings) -> tuple | None:
    """(angle to the recalled pose, angle to its nearest twin), deg, when the recalled state x_recall (12,) (the lost
    track's last confirmed state propagated to x's time, its attitude sigma recall_att_sigma_deg) says the candidate
    x (12,) is a twin of it: x nearer one of its twins (namings.relabel_S of a naming other than the detector's own)
    than to it (the identity or an equivalent rotation), and farther from it than 3 sigma. None otherwise (it
    agrees, cannot tell, or the target has no twins)."""
    twin = np.asarray(namings.relabel_class) > 0
    if not twin.any():
        return None
    G = mrp_to_dcm(np.asarray(x, float)[MRP])
    G_recall = np.einsum("rij,jk->rik", namings.relabel_S, mrp_to_dcm(np.asarray(x_recall, float)[MRP]))
    cos = (np.einsum("ij,rij->r", G, G_recall) - 1.0) / 2.0  # trace(G G_r^T): the rotation between them
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    d_self, d_twin = float(np.min(angle[~twin])), float(np.min(angle[twin]))
    if d_twin < d_self and d_self > 3.0 * recall_att_sigma_deg:
        return d_self, d_twin
    return None


def rejections_improbable(rejected: int, given: int, share: float, prob: float) -> float | None:
    """The probability of rejecting at least `rejected` of `given` corners when each is rejected with the
    expected `share` (a binomial tail), where that tail is below prob; None where the rejections are as a correct
    track makes them."""
    from scipy.stats import binom

    if given <= 0 or rejected <= 0:
        return None
    p = float(binom.sf(rejected - 1, given, min(max(float(share), 0.0), 1.0)))
    return p if p < prob else None


def fit_problems(fit, frames: int, cfg, min_keypoints: int, share: float = DEFAULT_REJECT_SHARE) -> list[str]:
    """Why a cold-start BatchFit (pipelines/tracking/acquisition.py) over `frames` frames starts no hypothesis (empty when
    it may): not valid, more corners rejected than a correct fit would at `share` (rejections_improbable), fewer than
    min_keypoints (AcquireConfig.min_keypoints) kept a frame on average, a chi-square beyond its bound at cfg.prob
    (cfg: the IntegrityConfig)."""
    if not fit.valid:
        return ["the fit has no positive-definite covariance"]
    kept = int(np.sum(fit.used))
    measured = kept + int(fit.rejected)
    out = []
    p = rejections_improbable(int(fit.rejected), measured, share, cfg.prob)
    if p is not None:
        out.append(f"the fit rejected {fit.rejected} of {measured} keypoints (p = {p:.1g} at the expected "
                   f"{share:.0%})")
    if kept < min_keypoints * frames:
        out.append(f"the fit kept {kept / frames:.1f} keypoints a frame (at least {min_keypoints})")
    if fit.dof > 0 and fit.chi2 > chi2_bound(cfg.prob, int(fit.dof)):
        out.append(f"the fit's chi-square {fit.chi2:.0f} beyond its bound {chi2_bound(cfg.prob, int(fit.dof)):.0f} "
                   f"({fit.dof} dof)")
    return out


@dataclass(frozen=True)
class EvidenceWindow:
    """The last W frames of evidence of H hypotheses (ring buffers, slot k % W; never mutated).

    nis, dof (H, W): each frame's NIS and its degrees of freedom (0 where no corner was used); given, rejected
    (H, W): corners given to the filter and, of those, rejected by the gate or the visibility check; expected
    (H, W): the rejections a correct track expects of those given (its share times given); used (H, W) bool: the
    frame used a corner; k: frames pushed so far."""

    nis: np.ndarray
    dof: np.ndarray
    given: np.ndarray
    rejected: np.ndarray
    expected: np.ndarray
    used: np.ndarray
    k: int = 0

    @staticmethod
    def empty(H: int, W: int) -> "EvidenceWindow":
        z = np.zeros((H, W))
        return EvidenceWindow(z, z.copy(), z.copy(), z.copy(), z.copy(), np.zeros((H, W), bool))

    def push(self, nis, dof, given, rejected, share=DEFAULT_REJECT_SHARE) -> "EvidenceWindow":
        """A new window with this frame's (H,) values in the oldest slot; share (H,) or a number: the share of the
        given corners a correct track's gate rejects this frame."""
        s = self.k % self.nis.shape[1]
        arrays = {}
        expected = np.asarray(given, float) * np.broadcast_to(np.asarray(share, float), np.shape(given))
        for name, v in (("nis", nis), ("dof", dof), ("given", given), ("rejected", rejected), ("expected", expected)):
            a = getattr(self, name).copy()
            a[:, s] = np.asarray(v, dtype=float)
            arrays[name] = a
        used = self.used.copy()
        used[:, s] = np.asarray(dof) > 0
        return EvidenceWindow(**arrays, used=used, k=self.k + 1)

    def select(self, idx: np.ndarray) -> "EvidenceWindow":
        """The windows of hypotheses idx only."""
        return dataclasses.replace(self, **{f: getattr(self, f)[idx] for f in ("nis", "dof", "given", "rejected",
                                                                                "expected", "used")})

    def used_frames(self) -> np.ndarray:
        """(H,) frames of the window that used a corner."""
        return self.used.sum(-1)


def nis_window_bound(prob: float, dof: int, kappa: float = 1.0) -> float:
    """The bound a window's NIS sum over dof degrees of freedom exceeds with probability prob, the frames'
    correlation taken as a sum dispersed kappa times the chi-square's (kappa x chi2(dof / kappa): the same mean,
    kappa times the variance; noise.nis_sum_dispersion)."""
    if kappa <= 1.0:
        return chi2_bound(prob, dof)
    return float(kappa * chi2_bound(prob, dof / kappa))


def window_problems(win: EvidenceWindow, cfg, kappa: float = 1.0) -> list[list[str]]:
    """Per hypothesis, why its window contradicts it (empty lists where it does not): the windowed NIS beyond
    its bound at cfg.prob (nis_window_bound, kappa the frames' correlation), or more of the corners
    given rejected than a correct track would at the window's expected share (rejections_improbable)."""
    out = []
    for h in range(win.nis.shape[0]):
        p = []
        d = int(win.dof[h].sum())
        if d > 0:
            bound = nis_window_bound(cfg.prob, d, kappa)
            if win.nis[h].sum() > bound:
                p.append(f"innovations inconsistent: windowed NIS {win.nis[h].sum():.0f} beyond {bound:.0f} "
                         f"({d} dof)")
        given, rejected = int(win.given[h].sum()), int(win.rejected[h].sum())
        share = float(win.expected[h].sum() / given) if given else DEFAULT_REJECT_SHARE
        tail = rejections_improbable(rejected, given, share, cfg.prob)
        if tail is not None:
            p.append(f"the gate rejected {rejected} of the last {given} keypoints (p = {tail:.1g} at the expected "
                     f"{share:.0%})")
        out.append(p)
    return out
