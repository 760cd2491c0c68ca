"""Whether a campaign's measurements fix the target's pose from the start, said before its runs are trusted.

An unscented update from a wide prior (P0) is taken along every direction the measured keypoints move; where one
or two keypoints, or keypoints on one line, are measured, the rotation about that line is not measured at all,
yet the sigma points' curvature leaks information into it: the covariance turns overconfident and the run can
diverge later, when more keypoints come into view (a 30 m rod whose first 80 s show two keypoints near its axis:
mean NEES 478, 13 of 20 runs diverged; the same rod from a start with 3-4 keypoints in view: median NEES 15;
docs/history.md, 2026-12-05, fourth session). No tuning of P0's width for one target is made for it; holding
every update until the first step that fixes the pose was measured there (mean NEES 28, median 12, 1 of 20
diverged) and not adopted: a study that measures two markers on purpose would get no update at all. The campaign
says it in one warning."""

from __future__ import annotations

import warnings

import numpy as np

from envisat_pose.filtering.measurements import POSE_CORNERS, limit_markers, outage_mask, pose_fixed
from envisat_pose.filtering.montecarlo import MeasurementConfig


def unfixed_start(t_s: np.ndarray, keypoints_T_m: np.ndarray, base_mask: np.ndarray,
                  mcfg: MeasurementConfig) -> tuple[int, float | None]:
    """The measured steps before the first one whose keypoints fix the pose (filtering.measurements.pose_fixed: as
    many as the filter's own rule for mcfg.kind, POSE_CORNERS: 3 markers, 4 pixels), and that step's time (None:
    no step fixes it). The measured set is the truth's measurable keypoints (t_s (T,) s, base_mask (T, K)) less
    the outages, at most max_markers: what every run measures before its random failures."""
    mask = limit_markers(np.asarray(base_mask, bool) & ~outage_mask(np.asarray(t_s), mcfg.outages_s)[:, None],
                         mcfg.max_markers)
    fixed = pose_fixed(keypoints_T_m, mask, POSE_CORNERS[mcfg.kind])
    first = int(np.argmax(fixed)) if fixed.any() else len(t_s)
    return int(mask[:first].any(axis=-1).sum()), (float(t_s[first]) if first < len(t_s) else None)


def warn_if_unfixed_start(t_s: np.ndarray, keypoints_T_m: np.ndarray, base_mask: np.ndarray,
                          mcfg: MeasurementConfig) -> None:
    """A UserWarning when steps with measurements come before the first whose keypoints fix the pose
    (unfixed_start): the filter's covariance over the runs that follow may not be trusted."""
    n, first_s = unfixed_start(t_s, keypoints_T_m, base_mask, mcfg)
    if n == 0:
        return
    fewest = POSE_CORNERS[mcfg.kind]
    when = "at no step" if first_s is None else f"only from t = {first_s:g} s"
    warnings.warn(f"the measured keypoints fix the target's pose {when}: {n} step(s) before measure fewer than "
                  f"{fewest} keypoints off one line, so the filter updates its wide prior along a rotation it cannot "
                  "measure and its covariance can turn overconfident (NEES far above its band, runs that "
                  f"diverge later); keypoints placed so that {fewest} or more off one line are seen from every "
                  "view, or a start where they are, avoid it (docs/usage.md, 'Where to put the keypoints')",
                  stacklevel=2)


def warn_outages_outside(t_s: np.ndarray, mcfg: MeasurementConfig) -> None:
    """A UserWarning for each outage window that holds no step of the truth (it begins after the truth's last
    step): it removes no measurement, which a window typed for a longer truth (or in minutes) would not tell."""
    end_s = float(np.asarray(t_s)[-1]) if np.size(t_s) else 0.0
    for i, (a, b) in enumerate(mcfg.outages_s):
        if not np.any((np.asarray(t_s) >= a) & (np.asarray(t_s) < b)):
            warnings.warn(f"measurement.outages_s[{i}] [{a:g}, {b:g}) s holds no step of the truth (0 to {end_s:g} "
                          "s): it removes no measurement", stacklevel=2)


def warn_if_never_updated(offered: bool) -> None:
    """The warning of a job in which no step of any run took a measurement (its errors and NEES the prior's,
    propagated), naming why: offered, whether the truth gave any run a keypoint to measure (visible, in frame
    for pixels, outside outages, not lost). Where it did, every update failed or was refused (an innovation
    covariance not positive definite: a noise sigma far below the prior's spread, 1e-9 m against P0's 1 m), not
    a target out of view."""
    if offered:
        warnings.warn("no step of any run took a measurement although the truth offered keypoints to measure: "
                      "every update failed (its innovation covariance not positive definite: a measurement noise "
                      "sigma too small against P0?) or was gated out; the errors and NEES are the prior's, "
                      "propagated, and the runs are flagged diverged")
    else:
        warnings.warn("no step of any run had a measurement (the target never in view, or every keypoint outside "
                      "the measurement's rules): the errors and NEES are the prior's, propagated")
