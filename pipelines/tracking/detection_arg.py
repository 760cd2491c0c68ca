"""A detector's answer as the Tracker takes it: one FrameDetection of the tracker's K keypoints, checked at the
boundary. A detector of another keypoint count (ENVISAT's 8 corners for a 12-keypoint target, another target's
network), arrays of the wrong shape or a keypoint given as found with a covariance that is not positive definite
is refused in one line naming the field, what it holds and what was expected; before, such answers failed deep in
the cold start (an IndexError), in the filter (a LinAlgError) or were never used (corners (K, 3): acquiring
forever, silently). A keypoint not found is NaN or not visible, as FrameDetection says."""

from __future__ import annotations

import numpy as np

from envisat_pose.config import InputError


class DetectionRefused(InputError):
    """A detector's answer the Tracker refuses (detection_arg); the frame is not taken (Tracker.step)."""


def detection_arg(fd, K: int):
    """fd, what `detector.detect` returned for a tracker of K keypoints, when it is a FrameDetection (or holds its
    fields: read by name, perception.detect not imported here, where it would pull in torch) whose
    corners_px are (K, 2), cov_px (K, 2, 2), visible (K,) and whose every keypoint visible with finite values
    has a symmetric positive-definite covariance; InputError naming the field otherwise."""
    if not all(hasattr(fd, f) for f in ("corners_px", "cov_px", "visible", "alt_probability")):
        raise DetectionRefused(f"detector.detect returned {type(fd).__name__}; expected a perception.detect."
                               f"FrameDetection of the tracker's {K} keypoints (FrameDetection.missing(crop, {K}) where "
                               "nothing is found)")
    z = np.asarray(fd.corners_px)
    if z.shape != (K, 2):
        more = " (ENVISAT's 8 corners: its corner detector, not the target's keypoint detector?)" \
            if z.shape == (8, 2) else ""
        raise DetectionRefused(f"detection corners_px: shape {z.shape}; expected ({K}, 2), the tracker's {K} keypoints "
                               f"in the target's order{more}")
    cov = np.asarray(fd.cov_px)
    if cov.shape != (K, 2, 2):
        raise DetectionRefused(f"detection cov_px: shape {cov.shape}; expected ({K}, 2, 2), px^2")
    visible = np.asarray(fd.visible)
    if visible.shape != (K,):
        raise DetectionRefused(f"detection visible: shape {visible.shape}; expected ({K},) bool")
    try:
        z, cov, visible = z.astype(float), cov.astype(float), visible.astype(bool)
    except (TypeError, ValueError) as err:
        raise DetectionRefused(f"detection: corners_px, cov_px and visible must be numbers ({err})") from None
    used = visible & np.isfinite(z).all(-1) & np.isfinite(cov).all((-1, -2))
    a, b, c = cov[:, 0, 0], 0.5 * (cov[:, 0, 1] + cov[:, 1, 0]), cov[:, 1, 1]
    bad = np.flatnonzero(used & ~((a > 0) & (c > 0) & (a * c - b * b > 0)))
    if bad.size:
        k = int(bad[0])
        raise DetectionRefused(f"detection cov_px[{k}]: {cov[k].tolist()} for a keypoint given as found; expected a "
                               f"symmetric positive-definite covariance, px^2 ({bad.size} keypoint(s) so; a keypoint not "
                               "found: visible False or NaN)")
    return fd
