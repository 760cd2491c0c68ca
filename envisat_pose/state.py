"""The 12-state relative pose: its layout, block names and units, the initial-estimate draw and error summaries.

One home for the state's layout (docs/reference.md, section 3), used by every stage, pipeline and bench:

    x = (rho_C_m (3), rhodot_C_m_s (3), p_mrp (3) of T relative to C, w_r_T_rad_s (3))

Slices: POS, VEL, MRP, RATE; BLOCK_SLICES in that order with BLOCKS (names) and BLOCK_UNITS (the units the
statistics report a block in: the attitude block as a rotation angle); block_sums folds a per-component
vector into the four blocks. nees_window_diverged is the divergence monitor on a run's NEES; nees_window_judged
says whether a run is long enough for it to judge.
"""

from __future__ import annotations

import numpy as np

from envisat_pose.attitude import mrp_error_angle_rad

N_STATE = 12
POS = slice(0, 3)  # rho, target relative to chaser, in C, m
VEL = slice(3, 6)  # rho', in C, m/s
MRP = slice(6, 9)  # p, MRP of T relative to C (shadow set |p| <= 1)
RATE = slice(9, 12)  # w_r, angular velocity of T relative to C, in T, rad/s
BLOCKS = ("position", "velocity", "attitude", "angular_velocity")
BLOCK_UNITS = ("m", "m/s", "rad", "rad/s")
BLOCK_SLICES = (POS, VEL, MRP, RATE)
ATTITUDE = BLOCKS.index("attitude")  # the attitude block's place among the four


def block_sums(v: np.ndarray) -> np.ndarray:
    """Per-component values (..., 12) (variances, squared errors) summed within each block -> (..., 4)."""
    v = np.asarray(v)
    return np.stack([v[..., s].sum(-1) for s in BLOCK_SLICES], axis=-1)


def nees_window_judged(n_steps: int, settle_steps: int) -> bool:
    """Whether nees_window_diverged can judge a run of n_steps: it holds a step at or after settle_steps (0-based),
    where the divergence monitors are armed. A run that ends before cannot be judged, and its False from
    nees_window_diverged means "not judged", never "not diverged": the callers count such runs apart. Apart, not
    refused: a short campaign or estimate (a smoke run, a look at the first seconds) still gives its errors, NEES
    and bound; only its divergence count is unknown, and its line says so (docs/design.md, "Divergence")."""
    return int(n_steps) > int(settle_steps)


def unjudged_why(n_steps: int, settle_steps: int, window: int) -> str:
    """Why runs of n_steps are not judged (nees_window_judged False) at settle_steps and window (FilterConfig's
    divergence_settle_steps, divergence_window), in words for a summary line."""
    return (f"their {n_steps} steps end before step {settle_steps}, where the divergence monitors are armed: "
            f"filter.divergence_settle_steps = {settle_steps}, divergence_window = {window}; a longer run or a lower "
            "divergence_settle_steps judges them")


def nees_window_diverged(nees_rt: np.ndarray, window: int, settle_steps: int, factor: float) -> np.ndarray:
    """The NEES divergence monitor on precomputed NEES (R, T): a mean over `window` steps above factor x 12
    (the state's dimension) in a window ending at or after step settle_steps, or a non-finite NEES there.
    A run too short for a whole window from step max(settle_steps - window + 1, 0) (then settle_steps < window - 1
    and T < window) is judged on the one window it holds, shortened to the run: the mean of those steps against
    the same factor x 12, when its last step is at or after settle_steps. A run with no step at or after
    settle_steps is not judged (False; nees_window_judged tells it apart). Returns (R,) bool. Errors are
    correlated in time, so this is a factor on the mean, not a chi-square bound."""
    nees_rt = np.asarray(nees_rt, dtype=float)
    e = nees_rt[:, max(settle_steps - window + 1, 0):]
    if e.shape[1] < window:  # a short run: its one window, shortened (docs/design.md, "Divergence")
        if not nees_window_judged(nees_rt.shape[1], settle_steps):
            return np.zeros(e.shape[0], dtype=bool)
        finite = np.isfinite(e).all(axis=1)
        return ~finite | (np.where(finite[:, None], e, 0.0).sum(axis=1) > factor * N_STATE * e.shape[1])
    c = np.cumsum(np.concatenate([np.zeros((e.shape[0], 1)), e], axis=1), axis=1)
    with np.errstate(invalid="ignore"):  # inf - inf past an infinite NEES: that run is flagged below anyway
        window_sums = c[:, window:] - c[:, :-window]
    return (window_sums > factor * N_STATE * window).any(axis=1) | ~np.isfinite(e).all(axis=1)


def draw_initial_estimate(x0_true: np.ndarray, P0: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A warm start for filter studies: x0_true (12,) plus one draw from N(0, P0) (12, 12), as every campaign
    draws it (x0 + chol(P0) @ standard normal(12)). The tracker never uses it: it starts from images."""
    return np.asarray(x0_true, dtype=float) + np.linalg.cholesky(P0) @ rng.standard_normal(N_STATE)


def error_magnitudes(x_true: np.ndarray, x_hat: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample error magnitudes (..., 12) -> dict of (...): position_m, velocity_m_s (norms in C),
    attitude_deg (rotation angle between the two MRPs), rate_deg_s (norm in T)."""
    x_true = np.asarray(x_true, dtype=float)
    x_hat = np.asarray(x_hat, dtype=float)
    return {
        "position_m": np.linalg.norm(x_hat[..., POS] - x_true[..., POS], axis=-1),
        "velocity_m_s": np.linalg.norm(x_hat[..., VEL] - x_true[..., VEL], axis=-1),
        "attitude_deg": np.degrees(mrp_error_angle_rad(x_hat[..., MRP], x_true[..., MRP])),
        "rate_deg_s": np.degrees(np.linalg.norm(x_hat[..., RATE] - x_true[..., RATE], axis=-1)),
    }


def error_summary(t_s: np.ndarray, x_true: np.ndarray, x_hat: np.ndarray, after_s: float) -> dict:
    """Errors of R runs (R, T, 12) (x_true may broadcast) from after_s on: per block the RMS over runs and
    times after, the largest after, and the RMS over runs at the last time. Units in the keys (m, m/s, deg,
    deg/s). When no sample lies after after_s the whole run counts. Samples without an estimate (x_hat NaN: a
    tracker acquiring or lost) are left out; a figure none holds is None."""
    t_s = np.asarray(t_s, dtype=float)
    late = t_s >= after_s
    if not late.any():
        late = np.ones_like(t_s, dtype=bool)
    out: dict = {"after_s": float(t_s[late][0])}
    for name, e in error_magnitudes(x_true, x_hat).items():
        e = np.atleast_2d(e)
        after, last = e[:, late][np.isfinite(e[:, late])], e[:, -1][np.isfinite(e[:, -1])]
        out[name] = {"rms_after": float(np.sqrt(np.mean(after ** 2))) if after.size else None,
                     "max_after": float(np.max(after)) if after.size else None,
                     "final": float(np.sqrt(np.mean(last ** 2))) if last.size else None}
    return out
