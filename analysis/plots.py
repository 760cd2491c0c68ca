"""Plots people look at. Matplotlib with the Agg backend (no display needed); PNG files."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from envisat_pose.attitude import align_mrp, mrp_shadow
from envisat_pose.io import atomic_path  # noqa: E402
from envisat_pose.png_marks import JOB_KEY  # noqa: E402
from envisat_pose.state import MRP, N_STATE, RATE, error_magnitudes  # noqa: E402

STATE_LABELS = (
    ("rho_x [m]", "rho_y [m]", "rho_z [m]"),
    ("rho'_x [m/s]", "rho'_y [m/s]", "rho'_z [m/s]"),
    ("p_1", "p_2", "p_3"),
    ("w_r,1 [deg/s]", "w_r,2 [deg/s]", "w_r,3 [deg/s]"),
)
STATE_TITLES = ("relative position rho, in C", "relative velocity rho', in C",
                "MRP p of T relative to C", "relative angular velocity w_r, in T")


def plot_states(t_s: np.ndarray, x: np.ndarray, path: str, title: str = "", visible: np.ndarray | None = None,
                points: str = "corners", job: str | None = None) -> None:
    """A 4 x 3 grid of the 12 states over time (minutes), plus the number of visible keypoints if given: visible
    (T, K), its axis 0..K, labelled `points` (ENVISAT's "corners"; another target's "keypoints"). job: the job
    whose mark the PNG carries (png_marks), so its next run knows the file for its own."""
    rows = 5 if visible is not None else 4
    fig, axes = plt.subplots(rows, 3, figsize=(13, 2.3 * rows + 0.6), sharex=True, squeeze=False)
    t_min = t_s / 60.0
    scale = np.ones(N_STATE)
    scale[RATE] = 180.0 / np.pi
    for i in range(N_STATE):
        ax = axes[i // 3, i % 3]
        ax.plot(t_min, x[:, i] * scale[i], lw=0.9)
        ax.set_ylabel(STATE_LABELS[i // 3][i % 3])
        ax.grid(alpha=0.3)
        if i % 3 == 1:
            ax.set_title(STATE_TITLES[i // 3], fontsize=10)
    if visible is not None:
        ax = axes[4, 0]
        ax.step(t_min, visible.sum(axis=1), where="post", lw=0.9)
        ax.set_ylabel(f"visible {points} (of {visible.shape[1]})")
        ax.set_ylim(-0.5, visible.shape[1] + 0.5)
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # a count: no 7.5 keypoints
        ax.grid(alpha=0.3)
        axes[4, 1].axis("off")
        axes[4, 2].axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("t [min]")
    fig.suptitle(title or "ENVISAT relative state (truth)")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png", metadata={JOB_KEY: job} if job else None)
    plt.close(fig)


def estimate_errors(x_true: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """Errors x_hat - x_true (R, T, 12); the MRP error compares both on the truth's set (|p| <= 1 near it)."""

    err = x_hat - x_true
    p_true = mrp_shadow(x_true[..., MRP])
    err[..., MRP] = align_mrp(x_hat[..., MRP], p_true) - p_true
    return err


def _shade_no_estimate(axes, t_min: np.ndarray, none: np.ndarray) -> None:
    """The whole time axis on every plot, the frames where no run has an estimate (none (T,): acquiring, lost)
    shaded grey: a tracker's cold start reads as such, not as a figure that begins late."""
    if not len(t_min):
        return
    edges = np.flatnonzero(np.diff(np.concatenate([[0], none.astype(np.int8), [0]])))
    for i, ax in enumerate(a for a in axes if a.axison):
        ax.set_xlim(t_min[0], t_min[-1])
        for j, (a, b) in enumerate(zip(edges[::2], edges[1::2])):
            ax.axvspan(t_min[a], t_min[min(b, len(t_min) - 1)], color="0.85", lw=0, zorder=0,
                       label="no estimate" if i == j == 0 else None)


def plot_estimate(t_s: np.ndarray, x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray, path: str,
                  title: str = "", job: str | None = None) -> None:
    """The seed paper's figures: per-state error of run 0, the filter's +-3 sigma (from P, mean over runs)
    and the +-3 sigma of the Monte Carlo sample errors, plus the attitude error angle of every run.

    t_s (T,), x_true / x_hat (R, T, 12), P (R, T, 12, 12). Velocities in mm/s, angular rates in deg/s. job: the
    job whose mark the PNG carries (png_marks), so its next run knows the file for its own.
    """

    err = estimate_errors(x_true, x_hat)
    magnitudes = error_magnitudes(x_true, x_hat)
    sig_filter = np.sqrt(np.mean(np.diagonal(P, axis1=-2, axis2=-1), axis=0))  # (T, 12)
    sig_mc = err.std(axis=0) if err.shape[0] > 1 else None
    scale = np.array([100.0] * 3 + [1000.0] * 3 + [1.0] * 3 + [180.0 / np.pi] * 3)
    units = ["cm"] * 3 + ["mm/s"] * 3 + [""] * 3 + ["deg/s"] * 3
    names = ["rho_x", "rho_y", "rho_z", "rho'_x", "rho'_y", "rho'_z", "p_1", "p_2", "p_3", "w_r1", "w_r2", "w_r3"]
    fig, axes = plt.subplots(5, 3, figsize=(13, 13), sharex=True)
    t_min = t_s / 60.0
    for i in range(N_STATE):
        ax = axes[i // 3, i % 3]
        ax.plot(t_min, err[0, :, i] * scale[i], lw=0.8, color="C0", label="error, run 0")
        ax.plot(t_min, 3 * sig_filter[:, i] * scale[i], lw=0.9, color="C3", label="filter 3 sigma (P)")
        ax.plot(t_min, -3 * sig_filter[:, i] * scale[i], lw=0.9, color="C3")
        if sig_mc is not None:
            ax.plot(t_min, 3 * sig_mc[:, i] * scale[i], lw=0.9, ls="--", color="k", label="Monte Carlo 3 sigma")
            ax.plot(t_min, -3 * sig_mc[:, i] * scale[i], lw=0.9, ls="--", color="k")
        sig = sig_filter[len(t_s) // 10:, i]
        sig = sig[np.isfinite(sig)]  # frames without an estimate are NaN: gaps, not the axes' scale
        lim = 3 * np.percentile(sig, 95) * scale[i] * 2.0 if sig.size else np.nan
        if np.isfinite(lim) and lim > 0:
            ax.set_ylim(-lim, lim)
        ax.set_ylabel(f"{names[i]} [{units[i]}]" if units[i] else names[i])
        ax.grid(alpha=0.3)
    ang_deg = magnitudes["attitude_deg"]  # (R, T)
    ax = axes[4, 0]
    ax.semilogy(t_min, np.maximum(ang_deg.T, 1e-6), lw=0.5, alpha=0.5)
    ax.set_ylabel("attitude error [deg]")
    ax.grid(alpha=0.3, which="both")
    ax = axes[4, 1]
    pos_cm = 100 * magnitudes["position_m"]
    ax.semilogy(t_min, np.maximum(pos_cm.T, 1e-6), lw=0.5, alpha=0.5)
    ax.set_ylabel("position error [cm]")
    ax.grid(alpha=0.3, which="both")
    axes[4, 2].axis("off")
    _shade_no_estimate(list(axes.flat), t_min, ~np.isfinite(x_hat).all(-1).any(0))
    # the legend in the free panel, where it hides no data
    axes[4, 2].legend(*axes[0, 0].get_legend_handles_labels(), fontsize=9, loc="center")
    for ax in axes[-1]:
        ax.set_xlabel("t [min]")
    fig.suptitle(title or f"UKF estimation errors, {x_hat.shape[0]} runs")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100, format="png", metadata={JOB_KEY: job} if job else None)
    plt.close(fig)
