"""What the tracker's outputs say they are (`envisat run` and `envisat track`): est.npz holds each row's status
(envisat_pose.status) and NaN where the row holds no estimate (acquiring, lost: the run's own files keep the
tracker's placeholders there, which only the truth's scoring reads); est.npz, det.npz and summary.json carry the
status legend; the printed summary says plainly when nothing was tracked."""

from __future__ import annotations

import numpy as np

from envisat_pose.status import STATUSES, TRACKING, has_estimate


def no_estimate_nan(a: np.ndarray, status: np.ndarray) -> np.ndarray:
    """a (T, ...) (or (R, T, ...)) with NaN on the rows whose status (T,) (or (R, T)) holds no estimate."""
    a = np.array(a, dtype=float)
    a[~has_estimate(status)] = np.nan
    return a


def status_counts(status: np.ndarray) -> dict[str, int]:
    """Frames per status name."""
    status = np.asarray(status)
    return {s: int((status == i).sum()) for i, s in enumerate(STATUSES)}


def status_line(frames: int, counts: dict[str, int], first_tracking_s: float | None, final: str,
                mean_nis: float | None, refusal: str | None = None) -> str:
    """The printed summary of a run's statuses; says plainly when nothing was tracked, and why its last cold start
    was refused where one was (refusal: the Tracker's last_refusal)."""
    rest = ", ".join(f"{counts[s]} {s}" for s in STATUSES if s != "tracking" and counts.get(s))
    if not counts.get("tracking"):
        return (f"{frames} frames: nothing tracked ({rest}): the tracker never claimed tracking, so est.npz "
                + ("holds estimates only in its coasting rows" if counts.get("coasting") else
                   "holds no estimate (x_hat NaN, status per row)") + refused_clause(refusal))
    nis = "no filter update with measurements" if mean_nis is None else f"mean NIS per dof {mean_nis:.2f}"
    return (f"{frames} frames: {counts['tracking']} tracking" + (f", {rest}" if rest else "")
            + f"; first tracking at t = {seconds(first_tracking_s)} s; final status {final}; {nis}")


def seconds(t_s: float) -> str:
    """A frame time to the ms, whole however large (times since an epoch: :g printed 1.7e+09)."""
    return f"{t_s:.3f}".rstrip("0").rstrip(".")


def refused_clause(refusal: str | None) -> str:
    """"; its last cold start was refused: ..." for a tracker that refused one (Tracker.last_refusal), else ""."""
    return f"; its last cold start was refused: {refusal}" if refusal else ""


def first_tracking_s(t_s: np.ndarray, status: np.ndarray) -> float | None:
    """The first frame time with status tracking, s; None if never."""
    k = np.flatnonzero(np.asarray(status) == TRACKING)
    return float(t_s[k[0]]) if k.size else None


def mean_nis_per_dof(nis: np.ndarray, nis_dof: np.ndarray) -> float | None:
    """The NIS summed over every filter update divided by their degrees of freedom (~1 when the filter's
    innovations match its covariance; a truth-free consistency check); None without an update with measurements."""
    dof = int(np.sum(nis_dof))
    return float(np.sum(nis) / dof) if dof else None


def status_summary(t_s: np.ndarray, col: dict) -> dict:
    """What one run's statuses say, without a truth: frames by status, whether and when it first tracked, its
    final status and its mean NIS per dof. col: the run's status, nis and nis_dof per frame (T,)."""
    status = col["status"]
    counts = status_counts(status)
    return {"frames_by_status": counts, "tracked": counts["tracking"] > 0,
            "first_tracking_s": first_tracking_s(t_s, status), "final_status": STATUSES[int(status[-1])],
            "mean_nis_per_dof": mean_nis_per_dof(col["nis"], col["nis_dof"])}
