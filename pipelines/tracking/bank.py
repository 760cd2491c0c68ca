"""The tracker's bank of hypotheses: one run of the batched filter per open hypothesis (the half-turn twins of a
cold start), their log weights, the naming each takes, and their pruning.

Each frame every hypothesis takes the naming (the detector's or its renaming by one of the target's symmetries:
namings.py, the box's half-turns for ENVISAT) nearest its predicted keypoints and its log weight gains -cost/2 (cost ~ -2 log likelihood: the NIS, the gate's
bound per rejected or dropped corner and dof x log of the adaptive R scale, so a hypothesis that explains its
misfit by a larger R pays for it) plus the appearance log-likelihood of the naming it took, counted as one look
per `appearance_frames` frames, and what the image shows of the solar array's end (perception/arraycue.py: the
twins by a half-turn about y or z put it at the other end of the body).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from envisat_pose.attitude import mrp_to_dcm
from envisat_pose.filtering.estimator import FilterState
from envisat_pose.gates import chi2_bound
from envisat_pose.pipelines.tracking.namings import Namings, box_namings
from envisat_pose.state import MRP


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


def probabilities(log_w: np.ndarray) -> np.ndarray:
    """(H,) normalized probabilities of log weights (H,)."""
    if not log_w.size:
        return log_w
    w = np.exp(log_w - np.max(log_w))
    return w / w.sum()


def choose_namings(zd: np.ndarray, cd: np.ndarray, p_alt: float, uv_pred: np.ndarray, clip: float,
                   appearance_frames: float, namings: Namings | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per hypothesis, the naming (of namings, None: ENVISAT's box_namings: the detector's, or its renaming by
    one of the target's symmetries, or their equivalents: Namings.relabel_*) nearest its predicted keypoints: zd
    (K, 2), cd (K, 2, 2) the detector's
    naming, p_alt its half-turn probability, uv_pred (H, K, 2) each hypothesis' predicted keypoints. Returns z
    (H, K, 2), cov (H, K, 2, 2) (identity where not measured), namings (H,) (indices of namings) and the
    appearance log-likelihoods (H,) of the namings taken (Namings.log_likelihood, over appearance_frames)."""
    nm = namings or box_namings()
    H = uv_pred.shape[0]
    options = [nm.relabeled(zd, cd, r) for r in range(nm.relabel_count)]  # each naming and its equivalents
    dist = np.stack([np.nanmean(np.linalg.norm(z[None] - uv_pred, axis=-1), axis=-1) for z, _ in options], axis=-1)
    chosen = np.argmin(np.where(np.isfinite(dist), dist, np.inf), axis=-1).reshape(H)  # (H,); 0 when none seen
    z = np.stack([options[r][0] for r in chosen])
    cov = np.stack([options[r][1] for r in chosen])
    cov = np.where(np.isfinite(z).all(-1)[..., None, None], cov, np.eye(2))
    named = nm.relabel_class[chosen]
    appearance = np.array([nm.log_likelihood(p_alt, int(n), clip) for n in named]) / appearance_frames
    return z, cov, named, appearance


def update_cost(new: FilterState, gate_bound: float) -> np.ndarray:
    """(H,) ~ -2 log likelihood of each hypothesis' update: NIS, the gate's bound per rejected or dropped corner,
    and dof x log of the adaptive R scale."""
    return new.nis + gate_bound * (new.rejected + new.dropped) + new.dof * np.log(new.r_scale)


def bounded_frame_evidence(log_l: np.ndarray, seen: np.ndarray, max_log: float) -> np.ndarray:
    """(H,) one frame's log-likelihoods log_l (H,) of the hypotheses that saw it (seen), each at most max_log nats
    below the frame's best (a frame the model does not hold, a keypoint misnamed as its twin, bounds the ratio it
    gives; BankConfig.frame_max_log), 0 where not seen; max_log 0: unbounded."""
    log_l = np.where(seen, log_l, 0.0)
    if max_log <= 0.0 or not np.any(seen):
        return log_l
    best = np.max(log_l[seen])
    return np.where(seen, np.maximum(log_l, best - max_log), 0.0)


def frame_discriminates(nis: np.ndarray, dof: np.ndarray, prob: float) -> bool:
    """Whether one frame's innovations can tell the hypotheses apart: False when every hypothesis that used
    corners (dof > 0) finds them beyond the chi-square bound at tail probability prob for its dof. Such a frame
    contradicts them all (a detector error the model does not hold: a corner on the boom's edge, a wrong naming
    of one corner), and the differences between their NIS are then the error's, not evidence for one twin
    (three such frames, NIS 29-51 on 12 dof for both, once gave the wrong twin 3.4 nats; docs/history.md)."""

    nis, dof = np.asarray(nis, float), np.asarray(dof)
    ok = dof > 0
    if not ok.any():
        return True
    return bool(np.any(nis[ok] <= chi2_bound(prob, dof[ok])))


def same_array_end(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(H,) bool: each hypothesis of x (H, 12) puts the solar array (T's -x end) at the same end of the body as
    the state ref (12,): its long axis points the same way in C (the x half-turn keeps it, y and z reverse it)."""

    x_axis_C = mrp_to_dcm(np.asarray(x)[:, MRP])[:, 0, :]  # Gamma = T_from_C: its first row is T's x in C
    return x_axis_C @ mrp_to_dcm(np.asarray(ref)[MRP])[0] > 0.0


def array_log_likelihood(cue: int, x: np.ndarray, ref: np.ndarray, per_frame: float) -> np.ndarray:
    """(H,) log-likelihoods of the hypotheses x (H, 12) from one frame's array cue, read under the pose ref (12,)
    (+1: the array where ref puts it, -1: at the other end, 0: no reading): per_frame nats to every hypothesis
    that puts it where the image shows it, 0 to the others."""
    same = same_array_end(x, ref)
    if cue == 0:
        return np.zeros(len(same))
    return np.where(same == (cue > 0), float(per_frame), 0.0)
