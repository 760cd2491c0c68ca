"""`envisat adapt`'s verdict on the held-out final part (pipelines/adaptation/adapt.py): what a track run did
there (track_figures), whether the adapted weights did worse than the original ones (worse_reason) or tracked
every frame alike (unchanged_track)."""

from __future__ import annotations

import os

import numpy as np

from envisat_pose.io import open_npz
from envisat_pose.status import TRACKING

# what "worse on the held-out part" means (worse_reason): margins below which a change is noise
SHARE_MARGIN = 0.02          # tracked share may drop by at most 2 points
STAY_MARGIN_FRAMES = 3       # the pose may start to stay tracked at most 3 frames later
NIS_MARGIN = np.log(1.5)     # |ln(mean NIS / dof)| may grow by at most ln 1.5


def track_figures(run_dir: str, held_from: int) -> dict:
    """What a track run (est.npz) did on its held-out frames [held_from, T): tracked_share (of those frames),
    mean_nis_per_dof (sum NIS / sum dof over them; None without a measurement), stays_tracked_from (the first
    frame from which the status stays tracking to the end of the sequence; None when the last frame is not
    tracking), and the same over the whole sequence (tracked_share_all, frames)."""
    with open_npz(os.path.join(run_dir, "est.npz")) as est:
        status, nis, dof = est["status"][0], est["nis"][0], est["nis_dof"][0]
    T = len(status)
    tracking = status == TRACKING
    held = slice(held_from, T)
    n_dof = float(np.sum(dof[held]))
    not_tracking = np.flatnonzero(~tracking)
    stays = None if not tracking[-1] else int(not_tracking[-1] + 1 if len(not_tracking) else 0)
    return {"frames": T, "held_out_from": int(held_from), "tracked_share": float(np.mean(tracking[held])),
            "mean_nis_per_dof": float(np.sum(nis[held]) / n_dof) if n_dof else None,
            "stays_tracked_from": stays, "tracked_share_all": float(np.mean(tracking))}


def worse_reason(before: dict, after: dict) -> str | None:
    """One line saying how the adapted weights did worse on the held-out part than the original ones (beyond the
    margins SHARE_MARGIN, STAY_MARGIN_FRAMES, NIS_MARGIN), or None."""
    if after["tracked_share"] < before["tracked_share"] - SHARE_MARGIN:
        return (f"the adapted weights tracked {after['tracked_share']:.0%} of the held-out frames, the original "
                f"ones {before['tracked_share']:.0%}")
    b, a = before["stays_tracked_from"], after["stays_tracked_from"]
    if b is not None and (a is None or a > b + STAY_MARGIN_FRAMES):
        return (f"with the adapted weights the pose stays tracked from frame {a}, with the original ones from "
                f"frame {b}" if a is not None else
                f"with the adapted weights the track does not hold to the end (the original ones: from frame {b})")
    nb, na = before["mean_nis_per_dof"], after["mean_nis_per_dof"]
    if nb is not None and (na is None or abs(np.log(na)) > abs(np.log(nb)) + NIS_MARGIN):
        return (f"the held-out mean NIS per degree of freedom is {na:.2f} with the adapted weights, {nb:.2f} with "
                "the original ones" if na is not None else
                "the adapted weights gave the filter no measurement on the held-out frames")
    return None


def unchanged_track(before_dir: str, after_dir: str) -> str | None:
    """One line saying that the adapted weights tracked every frame as the original ones did (the same statuses,
    estimates and covariances within a millionth of their sigmas: floating-point rounding), or None. It happens
    where nothing they change reaches the tracker: the network not fine-tuned (params 'none'), its apparent scale
    kept, and a recalibrated covariance scale that the weights' sequence error model overrides
    (tracking/noise.sequence_cov_factor)."""
    runs = []
    for d in (before_dir, after_dir):
        with open_npz(os.path.join(d, "est.npz")) as est:
            runs.append((est["status"], est["x_hat"], est["P"]))
    (s0, x0, p0), (s1, x1, p1) = runs
    if s0.shape != s1.shape or not np.array_equal(s0, s1) or x0.shape != x1.shape:
        return None
    sigma = np.sqrt(np.abs(np.diagonal(p0, axis1=-2, axis2=-1)))
    with np.errstate(invalid="ignore"):
        same_x = np.all((np.abs(x1 - x0) <= 1e-6 * sigma) | (np.isnan(x0) & np.isnan(x1)))
        same_p = np.all((np.abs(p1 - p0) <= 1e-6 * sigma[..., :, None] * sigma[..., None, :])
                        | (np.isnan(p0) & np.isnan(p1)))
    if same_x and same_p:
        return ("the adapted weights track every frame as the original ones do (nothing they change reaches the "
                "tracker here): nothing to adopt")
    return None
