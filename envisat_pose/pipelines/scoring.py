"""Scoring a tracker's runs against a truth (the truth only scores: nothing here feeds back into a run).

A run has converged at the first lit frame from which the tracker is tracking (its filter running: the PnP poses
of the acquisition carry no velocity or rate, however close they come) and its position error stays below
POS_TOL_M and its attitude error below ATT_TOL_DEG on every lit frame to the end of the run (frames in the Earth's shadow carry no image: the
filter only predicts through them and they are not held against it); time to converge counts from the first lit
frame. Over the lit frames after convergence: RMSE per block, mean NEES (12 dof for a consistent filter), the
range bias (mean of |rho_hat| - |rho|, m).
"""

from __future__ import annotations

import numpy as np

from envisat_pose.state import BLOCKS, POS, error_magnitudes, error_summary
from envisat_pose.status import TRACKING

POS_TOL_M = 0.10
ATT_TOL_DEG = 1.0




def converged_from(t_s: np.ndarray, pos_err_m: np.ndarray, att_err_deg: np.ndarray,
                   tracking: np.ndarray | None = None) -> float | None:
    """The time (s) from which both errors (T,) stay below the tolerances to the end and the tracker is tracking
    (tracking (T,) bool; None: every frame); None if never."""
    ok = (pos_err_m < POS_TOL_M) & (att_err_deg < ATT_TOL_DEG)
    if tracking is not None:
        ok &= np.asarray(tracking, bool)
    if not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return float(t_s[0] if bad.size == 0 else t_s[bad[-1] + 1])


def score_runs(t_s: np.ndarray, x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray, status: np.ndarray,
               skipped: np.ndarray | None = None) -> dict:
    """Scores of R runs: x_true, x_hat (R, T, 12), P (R, T, 12, 12), status (R, T) (index into the tracker's
    STATUSES), skipped (T,) frames without an image (eclipse). Per run: converged, time to converge from the
    first lit frame (s); over the converged runs after convergence: RMSE per block (m, m/s, deg, deg/s), mean
    NEES, range bias (m); the error summary over the run's second half."""
    t_s = np.asarray(t_s, dtype=float)
    return score_frames(t_s, frame_errors(x_true, x_hat, P), status, skipped,
                        error_summary(t_s, x_true, x_hat, summary_after_s(t_s)))


def summary_after_s(t_s: np.ndarray) -> float:
    """Where the error summary starts: the run's second half, s."""
    return float(t_s[0] + 0.5 * (t_s[-1] - t_s[0]))


def frame_errors(x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray) -> dict[str, np.ndarray]:
    """Per frame (...): the error magnitudes (state.error_magnitudes), 'nees' and 'range_m' (|rho_hat| - |rho|, m)
    of x_true, x_hat (..., 12), P (..., 12, 12). Each frame's values depend on that frame alone, so a long run is
    scored chunk by chunk (concatenated along time) with the same numbers."""
    from envisat_pose.filtering.estimator import nees

    x_true = np.broadcast_to(x_true, np.shape(x_hat))
    out = error_magnitudes(x_true, x_hat)
    out["nees"] = nees(x_true, x_hat, P)
    out["range_m"] = np.linalg.norm(x_hat[..., POS], axis=-1) - np.linalg.norm(x_true[..., POS], axis=-1)
    return out


def score_frames(t_s: np.ndarray, errors: dict[str, np.ndarray], status: np.ndarray, skipped: np.ndarray | None,
                 summary: dict) -> dict:
    """score_runs from the per-frame errors (frame_errors, each (R, T)), status (R, T), skipped (T,) and the
    error summary over the second half (state.error_summary from summary_after_s)."""
    t_s = np.asarray(t_s, dtype=float)
    R = errors["nees"].shape[0]
    lit = ~np.asarray(skipped, bool) if skipped is not None else np.ones(len(t_s), bool)
    if not lit.any():
        lit = np.ones(len(t_s), bool)
    t_first_lit = float(t_s[np.argmax(lit)]) if lit.any() else float(t_s[0])
    err = {b: errors[b] for b in ("position_m", "velocity_m_s", "attitude_deg", "rate_deg_s")}
    e_nees, range_err = errors["nees"], errors["range_m"]
    conv_t, sq = [], {b: [] for b in err}
    nees_after, bias_after = [], []
    tracking = np.asarray(status) == TRACKING
    for r in range(R):
        tc = converged_from(t_s[lit], err["position_m"][r, lit], err["attitude_deg"][r, lit], tracking[r, lit])
        conv_t.append(tc)
        if tc is None:
            continue
        k = (t_s >= tc) & lit
        for b in err:
            sq[b].append(err[b][r, k] ** 2)
        nees_after.append(e_nees[r, k])
        bias_after.append(range_err[r, k])
    converged = [t is not None for t in conv_t]
    ttc = [None if t is None else t - t_first_lit for t in conv_t]
    done = [v for v in ttc if v is not None]
    out = {
        "runs": R, "converged": int(sum(converged)), "converged_runs": converged,
        "time_to_converge_s": ttc,
        "time_to_converge_median_s": float(np.median(done)) if done else None,
        "time_to_converge_max_s": float(np.max(done)) if done else None,
        "first_lit_s": t_first_lit,
        "rmse_after_convergence": {b: float(np.sqrt(np.mean(np.concatenate(sq[b])))) if sq[b] else None for b in err},
        "mean_nees_after_convergence": float(np.mean(np.concatenate(nees_after))) if nees_after else None,
        "range_bias_m": float(np.mean(np.concatenate(bias_after))) if bias_after else None,
        "frames_acquiring": int((np.asarray(status) == 0).sum()), "frames_lost": int((np.asarray(status) == 2).sum()),
        "errors": summary,
        "blocks": list(BLOCKS),
    }
    return out


def after_convergence_masks(t_s: np.ndarray, scores: dict, skipped: np.ndarray | None = None) -> np.ndarray:
    """(R, T) bool: the lit frames of each run from its convergence on (all False for a run that never did)."""
    t_s = np.asarray(t_s, dtype=float)
    lit = ~np.asarray(skipped, bool) if skipped is not None else np.ones(len(t_s), bool)
    first = scores["first_lit_s"]
    return np.array([np.zeros(len(t_s), bool) if d is None else (t_s >= first + d) & lit
                     for d in scores["time_to_converge_s"]])
