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
                mean_nis: float | None) -> str:
    """The printed summary of a run's statuses; says plainly when nothing was tracked."""
    rest = ", ".join(f"{counts[s]} {s}" for s in STATUSES if s != "tracking" and counts.get(s))
    if not counts.get("tracking"):
        return (f"{frames} frames: nothing tracked ({rest}): the tracker never got past acquisition, so est.npz "
                "holds no estimate (x_hat NaN, status per row)")
    nis = "no filter update with measurements" if mean_nis is None else f"mean NIS per dof {mean_nis:.2f}"
    return (f"{frames} frames: {counts['tracking']} tracking" + (f", {rest}" if rest else "")
            + f"; first tracking at t = {first_tracking_s:g} s; final status {final}; {nis}")


def first_tracking_s(t_s: np.ndarray, status: np.ndarray) -> float | None:
    """The first frame time with status tracking, s; None if never."""
    k = np.flatnonzero(np.asarray(status) == TRACKING)
    return float(t_s[k[0]]) if k.size else None
