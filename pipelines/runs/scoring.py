"""Scoring a tracker's runs against a truth (the truth only scores: nothing here feeds back into a run).

Scores that would show a failure: nothing is scored only where it went well.

- A frame is *correct* when the attitude error is within CORRECT_ATT_DEG and the position error within
  CORRECT_POS_FRAC of the true range; the tracker *claims* an estimate on a frame whose status is one of
  status.HAS_ESTIMATE (tracking, coasting). A *false lock* is a frame claimed while not correct: its time counts
  over every frame of every run (lit or in the Earth's shadow: a claim is a claim).
- A run's *scored frames* are every frame from its first declared "tracking" to its end on which it claims an
  estimate (an excursion in the middle stays in). Frames after that on which it claims none (lost, acquiring, a
  status added later) carry no estimate: they are counted (`estimate_share`), not scored.
- Over the scored frames of all runs pooled (a run that never tracks adds none and is listed as such): RMSE per
  block, mean NEES, the share of frames whose NEES exceeds its chi-square NEES_TAIL_P quantile (NEES_DOF dof),
  the SPEC2021 per-frame score (median and 95th percentile), the range bias (mean of |rho_hat| - |rho|, m), and,
  where the caller gives a bound (the PCRLB), RMSE over it per block.
- A target whose poses are defined up to rotations nothing tells apart (pipelines/tracking/namings.py,
  `equivalent`: the CubeSat's half-turns) is scored against the truth's twin nearest each estimate (nearest_truth).
- Per run: the first declared tracking, whether it was correct (the acquisition's success), the time to the
  first correct track from the first lit frame, the false-lock time, and when the run *settled*: the time from
  which it claims an estimate and stays within SETTLED_POS_M and SETTLED_ATT_DEG on every lit frame to the end
  (the end of the last excursion; a figure of the run's end, not where statistics start).
"""

from __future__ import annotations

import functools

import numpy as np

from envisat_pose.attitude import mrp_error_angle_rad
from envisat_pose.filtering.estimator import nees
from envisat_pose.filtering.ukf import chart_error
from envisat_pose.gates import chi2_quantile
from envisat_pose.pipelines.runs.outputs import no_estimate_nan
from envisat_pose.pipelines.tracking.namings import renamed_state
from envisat_pose.state import BLOCKS, MRP, POS, error_magnitudes, error_summary
from envisat_pose.status import HAS_ESTIMATE, STATUSES, TRACKING

# a correct track (the success criterion of pose-acquisition studies): attitude within 5 deg and
# position within 2 % of the range
CORRECT_ATT_DEG = 5.0
CORRECT_POS_FRAC = 0.02
# a consistent filter's NEES is chi-square with the state's 12 dof; its tail beyond the 99.9 % quantile should
# hold 0.1 % of the frames
NEES_DOF = 12
NEES_TAIL_P = 0.999
NEES_TAIL = chi2_quantile(NEES_TAIL_P, NEES_DOF)
# SPEC2021 (Park et al., ESA/Stanford pose estimation competition 2021): per frame, position error over range plus
# attitude error in rad, each set to 0 below the ground truth's own precision (2.173 mm per m, 0.169 deg)
SPEC_POS_FLOOR = 2.173e-3
SPEC_ATT_FLOOR_DEG = 0.169
# settled: within 10 cm and 1 deg to the end of the run (the figure the project called "converged" before)
SETTLED_POS_M = 0.10
SETTLED_ATT_DEG = 1.0
# the error blocks scored, in BLOCKS order, with their units in the key
ERROR_KEYS = ("position_m", "velocity_m_s", "attitude_deg", "rate_deg_s")


def nearest_truth(x_true: np.ndarray, x_hat: np.ndarray, equivalent: np.ndarray | None) -> np.ndarray:
    """x_true (..., 12) described, frame by frame, by the twin (the identity or a rotation of `equivalent`
    (E, 3, 3) about the centre of mass: poses no image or motion tells apart) whose attitude is nearest x_hat's
    (..., 12); x_true itself where equivalent is None or empty."""
    if equivalent is None or not len(equivalent):
        return x_true
    x_true = np.broadcast_to(x_true, np.shape(x_hat))
    twins = np.stack([x_true] + [renamed_state(x_true, S, np.zeros(3)) for S in equivalent])
    angle = mrp_error_angle_rad(np.broadcast_to(x_hat[..., MRP], twins[..., MRP].shape), twins[..., MRP])
    best = np.argmin(np.nan_to_num(angle, nan=np.inf), axis=0)
    return np.take_along_axis(twins, best[None, ..., None], axis=0)[0]


def frame_errors(x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray, chart: str = "additive"
                 ) -> dict[str, np.ndarray]:
    """Per frame (...): the error magnitudes (state.error_magnitudes), 'nees', 'range_error_m' (|rho_hat| - |rho|,
    m) and 'range_true_m' (|rho|, m) of x_true, x_hat (..., 12), P (..., 12, 12). chart: the sigma points' chart
    of the filter that made P (FilterConfig.sigma_chart), NEES's error is taken in it (filtering.estimator.nees).
    Each frame's values depend on that frame alone, so a long run is scored chunk by chunk (concatenated along
    time) with the same numbers."""

    x_true = np.broadcast_to(x_true, np.shape(x_hat))
    out = error_magnitudes(x_true, x_hat)
    out["nees"] = nees(x_true, x_hat, P, chart)
    true_range = np.linalg.norm(x_true[..., POS], axis=-1)
    out["range_error_m"] = np.linalg.norm(x_hat[..., POS], axis=-1) - true_range
    out["range_true_m"] = true_range
    return out


def recording_errors(chart: str):
    """analysis.recording.TrackRecorder's error_in_chart for a filter of sigma_chart `chart`: None for the additive
    chart (the recorder's own), else filtering.ukf.chart_error in that chart."""
    return None if chart == "additive" else functools.partial(chart_error, chart=chart)


def correct_frames(errors: dict[str, np.ndarray]) -> np.ndarray:
    """(...) bool: attitude error <= CORRECT_ATT_DEG and position error <= CORRECT_POS_FRAC x the true range."""
    near = errors["position_m"] <= CORRECT_POS_FRAC * errors["range_true_m"]
    return (errors["attitude_deg"] <= CORRECT_ATT_DEG) & near


def spec_score(errors: dict[str, np.ndarray]) -> np.ndarray:
    """(...) the SPEC2021 per-frame pose score: position error / range (0 below SPEC_POS_FLOOR) plus attitude
    error in rad (0 below SPEC_ATT_FLOOR_DEG)."""
    e_t = errors["position_m"] / errors["range_true_m"]
    e_t = np.where(e_t < SPEC_POS_FLOOR, 0.0, e_t)
    e_q = np.where(errors["attitude_deg"] < SPEC_ATT_FLOOR_DEG, 0.0, np.radians(errors["attitude_deg"]))
    return e_t + e_q


def claims_estimate(status: np.ndarray) -> np.ndarray:
    """(...) bool: the status claims a filter estimate (status.HAS_ESTIMATE); unknown codes claim none."""
    return np.isin(np.asarray(status), HAS_ESTIMATE)


def scored_masks(status: np.ndarray) -> np.ndarray:
    """(R, T) bool of status (R, T): the frames from each run's first declared tracking to its end on which it
    claims an estimate (all False for a run that never tracks)."""
    status = np.asarray(status)
    after_first = np.cumsum(status == TRACKING, axis=-1) > 0
    return after_first & claims_estimate(status)


def frame_period_s(t_s: np.ndarray) -> float:
    """The frame period, s (the median step; 0 for a single frame)."""
    return float(np.median(np.diff(t_s))) if len(t_s) > 1 else 0.0


def settled_from(t_s: np.ndarray, pos_err_m: np.ndarray, att_err_deg: np.ndarray,
                 claimed: np.ndarray | None = None) -> float | None:
    """The time (s) from which both errors (T,) stay within SETTLED_POS_M / SETTLED_ATT_DEG to the end and the
    tracker claims an estimate (claimed (T,) bool; None: every frame); None if never."""
    ok = (pos_err_m < SETTLED_POS_M) & (att_err_deg < SETTLED_ATT_DEG)
    if claimed is not None:
        ok &= np.asarray(claimed, bool)
    if not ok.size or not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return float(t_s[0] if bad.size == 0 else t_s[bad[-1] + 1])


def _first(t_s: np.ndarray, mask: np.ndarray) -> float | None:
    return float(t_s[np.argmax(mask)]) if mask.any() else None


def run_record(t_s: np.ndarray, errors: dict[str, np.ndarray], status: np.ndarray, lit: np.ndarray) -> dict:
    """One run's figures from its per-frame errors (frame_errors, each (T,)), status (T,) and lit (T,) bool (frames
    with an image): times in s, those 'to' something counted from the first lit frame; None where it never
    happened."""
    claimed = claims_estimate(status)
    tracking = np.asarray(status) == TRACKING
    correct = correct_frames(errors)
    false_lock = claimed & ~correct
    first_lit = _first(t_s, lit)
    t0 = first_lit if first_lit is not None else float(t_s[0])
    first_track = _first(t_s, tracking)
    first_correct = _first(t_s, tracking & correct)
    k_first = int(np.argmax(tracking)) if tracking.any() else None
    after = np.cumsum(tracking) > 0
    settled = settled_from(t_s[lit], errors["position_m"][lit], errors["attitude_deg"][lit], claimed[lit]) \
        if lit.any() else None
    return {
        "first_lit_s": first_lit,
        "tracked": bool(tracking.any()),
        "first_tracking_s": first_track,
        "first_track_correct": None if k_first is None else bool(correct[k_first]),
        "time_to_first_track_s": None if first_track is None else first_track - t0,
        "time_to_first_correct_track_s": None if first_correct is None else first_correct - t0,
        "false_lock_frames": int(false_lock.sum()),
        "false_lock_s": float(false_lock.sum() * frame_period_s(t_s)),
        "first_false_lock_s": _first(t_s, false_lock),
        "frames_after_first_track": int(after.sum()),
        "frames_scored": int((after & claimed).sum()),
        "settled": settled is not None,
        "time_to_settle_s": None if settled is None else settled - t0,
    }


def _stats(values: list[float | None]) -> dict:
    done = [v for v in values if v is not None]
    return {"median": float(np.median(done)) if done else None, "max": float(np.max(done)) if done else None,
            "runs_without": len(values) - len(done)}


def pooled_figures(errors: dict[str, np.ndarray], mask: np.ndarray, bound: np.ndarray | None = None) -> dict:
    """The statistics over the frames in mask (R, T) of errors (frame_errors, each (R, T)), pooled over runs:
    frames, RMSE per block (BLOCKS; units of ERROR_KEYS), mean NEES, the share beyond NEES_TAIL, the SPEC2021
    score's median and 95th percentile, the range bias (m), the largest attitude and position errors; with bound
    (R, T, 4): the PCRLB per block in m, m/s, rad, rad/s, also RMSE / bound per block (sqrt of the mean squared
    error over the mean squared bound on the same frames). None where no frame is scored."""
    n = int(mask.sum())
    none = n == 0
    nees = errors["nees"][mask]
    spec = spec_score(errors)[mask]
    out = {
        "frames": n,
        "rmse": {b: None if none else float(np.sqrt(np.mean(errors[k][mask] ** 2)))
                 for b, k in zip(BLOCKS, ERROR_KEYS)},
        "mean_nees": None if none else float(np.mean(nees)),
        "nees_tail_share": None if none else float(np.mean(nees > NEES_TAIL)),
        "spec_score_median": None if none else float(np.median(spec)),
        "spec_score_p95": None if none else float(np.percentile(spec, 95)),
        "range_bias_m": None if none else float(np.mean(errors["range_error_m"][mask])),
        "max_position_m": None if none else float(np.max(errors["position_m"][mask])),
        "max_attitude_deg": None if none else float(np.max(errors["attitude_deg"][mask])),
    }
    if bound is not None:
        to_bound_units = (1.0, 1.0, np.pi / 180.0, np.pi / 180.0)  # deg -> rad for the bound's units
        out["rmse_over_pcrlb"] = {
            b: None if none else float(np.sqrt(np.mean((errors[k][mask] * u) ** 2) / np.mean(bound[..., i][mask] ** 2)))
            for i, (b, k, u) in enumerate(zip(BLOCKS, ERROR_KEYS, to_bound_units))}
    return out


def score_runs(t_s: np.ndarray, x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray, status: np.ndarray,
               skipped: np.ndarray | None = None, bound: np.ndarray | None = None, chart: str = "additive") -> dict:
    """Scores of R runs: x_true (T, 12) or (R, T, 12), x_hat (R, T, 12), P (R, T, 12, 12), status (R, T) (codes of
    envisat_pose.status), skipped (T,) or (R, T) frames without an image (eclipse), bound (R, T, 4) a PCRLB per
    block (optional), chart: P's (frame_errors). See score_frames."""
    t_s = np.asarray(t_s, dtype=float)
    claimed = no_estimate_nan(x_hat, np.asarray(status))  # what est.npz holds
    return score_frames(t_s, frame_errors(x_true, x_hat, P, chart), status, skipped,
                        error_summary(t_s, x_true, claimed, summary_after_s(t_s)), bound)


def summary_after_s(t_s: np.ndarray) -> float:
    """Where the error summary starts: the run's second half, s."""
    return float(t_s[0] + 0.5 * (t_s[-1] - t_s[0]))


def score_frames(t_s: np.ndarray, errors: dict[str, np.ndarray], status: np.ndarray, skipped: np.ndarray | None,
                 summary: dict, bound: np.ndarray | None = None) -> dict:
    """score_runs from the per-frame errors (frame_errors, each (R, T)), status (R, T), skipped (T,) or (R, T),
    the error summary over the second half (state.error_summary from summary_after_s) and an optional bound.

    Keys: runs; per_run (run_record of each, with its own 'scored': pooled_figures over its frames alone, so that
    a figure that holds pooled but not on every run shows); runs_tracked, runs_never_tracking (their indices),
    first_track_correct (count of runs whose first declared tracking was correct); false_lock_s (summed over runs), false_lock_runs;
    time_to_first_correct_track_s and time_to_settle_s ({median, max, runs_without}); scored (pooled_figures over
    scored_masks); frames_by_status (counts per status name; 'code N' for a code this package does not know);
    settled, settled_runs (the old 'converged', renamed: see the module's docstring); errors (the summary)."""
    t_s = np.asarray(t_s, dtype=float)
    status = np.asarray(status)
    R, T = status.shape
    lit = np.ones((R, T), bool) if skipped is None else np.broadcast_to(~np.asarray(skipped, bool), (R, T))
    masks = scored_masks(status)
    runs = [run_record(t_s, {k: v[r] for k, v in errors.items()}, status[r], lit[r])
            | {"scored": pooled_figures({k: v[r:r + 1] for k, v in errors.items()}, masks[r:r + 1],
                                        None if bound is None else bound[r:r + 1])}
            for r in range(R)]
    codes, counts = np.unique(status, return_counts=True)
    by_status = {s: 0 for s in STATUSES} | {(STATUSES[c] if 0 <= c < len(STATUSES) else f"code {c}"): int(n)
                                            for c, n in zip(codes.tolist(), counts.tolist())}
    return {
        "runs": R,
        "per_run": runs,
        "runs_tracked": sum(r["tracked"] for r in runs),
        "runs_never_tracking": [i for i, r in enumerate(runs) if not r["tracked"]],
        "first_track_correct": sum(bool(r["first_track_correct"]) for r in runs),
        "false_lock_s": float(sum(r["false_lock_s"] for r in runs)),
        "false_lock_runs": sum(r["false_lock_frames"] > 0 for r in runs),
        "time_to_first_correct_track_s": _stats([r["time_to_first_correct_track_s"] for r in runs]),
        "time_to_settle_s": _stats([r["time_to_settle_s"] for r in runs]),
        "settled": sum(r["settled"] for r in runs),
        "settled_runs": [r["settled"] for r in runs],
        "scored": pooled_figures(errors, masks, bound),
        "thresholds": {"correct_attitude_deg": CORRECT_ATT_DEG, "correct_position_of_range": CORRECT_POS_FRAC,
                       "nees_dof": NEES_DOF, "nees_tail_p": NEES_TAIL_P, "nees_tail": NEES_TAIL,
                       "spec_position_floor": SPEC_POS_FLOOR, "spec_attitude_floor_deg": SPEC_ATT_FLOOR_DEG,
                       "settled_position_m": SETTLED_POS_M, "settled_attitude_deg": SETTLED_ATT_DEG},
        "frames_by_status": by_status,
        "errors": summary,
        "blocks": list(BLOCKS),
    }
