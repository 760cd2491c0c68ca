"""The seed paper's Monte Carlo figures and the campaign's other plots, from plain arrays. Matplotlib Agg, PNG,
written atomically.

Inputs are in the statistics' units of `analysis.stats` (m, m/s, rad as a rotation vector / angle, rad/s); the
figures show m, mm/s, deg and deg/s. Colours (module constants, the tests look for them): every run's error in
grey, the filter's 3-sigma from P red dashed, the 3-sigma of the sample errors green, RMSE blue, the PCRLB black.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from envisat_pose.io import atomic_path  # noqa: E402
from envisat_pose.state import BLOCK_SLICES, BLOCKS  # noqa: E402

GREY_RUNS = "#8c8c8c"
RED_FILTER = "#e00000"
GREEN_SAMPLE = "#00a000"
BLUE_RMSE = "#1f5fd0"
BLACK_BOUND = "#000000"
BAND_FILL = "#f2c200"  # chi-square 95 % band

BLOCK_TITLES = tuple(b.replace("_", " ") for b in BLOCKS)
BLOCK_DISPLAY = (("m", 1.0), ("mm/s", 1e3), ("deg", 180.0 / np.pi), ("deg/s", 180.0 / np.pi))
COMPONENT_NAMES = ("rho_x", "rho_y", "rho_z", "rho'_x", "rho'_y", "rho'_z", "dtheta_1", "dtheta_2", "dtheta_3",
                   "w_r1", "w_r2", "w_r3")
COMPONENT_SCALE = np.concatenate([np.full(s.stop - s.start, scale) for s, (_, scale) in zip(BLOCK_SLICES, BLOCK_DISPLAY)])


def _stride(T: int, max_points: int) -> int:
    """Every how many steps to draw so that a line has at most max_points points."""
    return max(1, -(-T // max_points))


def _save(fig, path: str, dpi: int = 100) -> None:
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)


def _runs(ax, t: np.ndarray, y: np.ndarray) -> None:
    """Every run of y (R, T') as one grey LineCollection (fast for hundreds of runs)."""
    segs = np.stack([np.broadcast_to(t, y.shape), y], axis=-1)
    ax.add_collection(LineCollection(list(segs), colors=GREY_RUNS, linewidths=0.6, zorder=1))


def plot_error_envelopes(t_s: np.ndarray, err: np.ndarray | None, filter_3sigma: np.ndarray,
                         sample_3sigma: np.ndarray | None, path: str, title: str = "", max_runs: int = 200,
                         max_points: int = 2000) -> None:
    """The paper's figure: per component (4 blocks x 3), the error of every Monte Carlo run (grey), +- the
    filter's 3-sigma from P (red dashed) and +- the 3-sigma of the sample errors (green).

    t_s (T,) s. err (R, T, 12) component errors (`stats.component_errors`; attitude as a rotation vector, rad)
    or None; a campaign may pass a subset of its runs; the first max_runs are drawn. filter_3sigma,
    sample_3sigma (T, 12) (`stats.CampaignStats`). Lines are thinned to at most max_points per run.
    """
    k = slice(None, None, _stride(len(t_s), max_points))
    t_min = np.asarray(t_s)[k] / 60.0
    fig, axes = plt.subplots(4, 3, figsize=(13, 11), sharex=True)
    for i in range(12):
        ax = axes[i // 3, i % 3]
        s = COMPONENT_SCALE[i]
        if err is not None:
            _runs(ax, t_min, err[:max_runs, k, i] * s)
        f3 = filter_3sigma[k, i] * s
        ax.plot(t_min, f3, color=RED_FILTER, ls="--", lw=1.3, zorder=3, label="filter 3 sigma (P)")
        ax.plot(t_min, -f3, color=RED_FILTER, ls="--", lw=1.3, zorder=3)
        lim = np.nanmax(np.abs(f3[len(f3) // 10:])) * 1.6 if len(f3) else 0.0
        if sample_3sigma is not None:
            m3 = sample_3sigma[k, i] * s
            ax.plot(t_min, m3, color=GREEN_SAMPLE, lw=1.3, zorder=2, label="sample 3 sigma")
            ax.plot(t_min, -m3, color=GREEN_SAMPLE, lw=1.3, zorder=2)
            lim = max(lim, np.nanmax(np.abs(m3[len(m3) // 10:])) * 1.6)
        if np.isfinite(lim) and lim > 0:
            ax.set_ylim(-lim, lim)
        ax.set_xlim(t_min[0], t_min[-1] if t_min[-1] > t_min[0] else t_min[0] + 1.0)
        ax.set_ylabel(f"{COMPONENT_NAMES[i]} [{BLOCK_DISPLAY[i // 3][0]}]")
        if i % 3 == 1:
            ax.set_title(f"{BLOCK_TITLES[i // 3]} error", fontsize=10)
    for ax in axes[-1]:
        ax.set_xlabel("t [min]")
    n = 0 if err is None else min(err.shape[0], max_runs)
    fig.suptitle(title or f"Estimation errors, {n} Monte Carlo runs (grey)", x=0.02, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.legend(*axes[0, 0].get_legend_handles_labels(), fontsize=8, loc="upper right", ncol=2)  # above the panels
    _save(fig, path)



def _finish_time_grid(fig, axes, title: str, path: str) -> None:
    """Legend on the first panel, time labels on the bottom row, the title; then write the PNG."""
    axes[0, 0].legend(fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("t [min]")
    fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)

def plot_block_norms(t_s: np.ndarray, norms: np.ndarray | None, rmse_block: np.ndarray, filter_3sigma_block: np.ndarray,
                     path: str, title: str = "", max_runs: int = 200, max_points: int = 2000) -> None:
    """Per block, |error| of every run (grey; attitude: the error angle), the RMSE over runs (blue) and the
    filter's 3-sigma of the block (red dashed), on log axes.

    norms (R, T, 4) (`stats.block_error_norms`) or None; rmse_block, filter_3sigma_block (T, 4).
    """
    k = slice(None, None, _stride(len(t_s), max_points))
    t_min = np.asarray(t_s)[k] / 60.0
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), sharex=True)
    for b in range(4):
        ax = axes[b // 2, b % 2]
        unit, s = BLOCK_DISPLAY[b]
        if norms is not None:
            _runs(ax, t_min, np.maximum(norms[:max_runs, k, b] * s, 1e-12))
        ax.plot(t_min, rmse_block[k, b] * s, color=BLUE_RMSE, lw=1.4, zorder=3, label="RMSE")
        ax.plot(t_min, filter_3sigma_block[k, b] * s, color=RED_FILTER, ls="--", lw=1.3, zorder=3,
                label="filter 3 sigma")
        ax.set_yscale("log")
        ax.autoscale_view()
        ax.set_ylabel(f"|{BLOCK_TITLES[b]} error| [{unit}]")
        ax.grid(alpha=0.3, which="both", color="#c8d4e6")
    _finish_time_grid(fig, axes, title or "Error norms per block", path)


def plot_nees_nis(t_s: np.ndarray, nees_mean: np.ndarray, nees_bounds: np.ndarray, nis_mean: np.ndarray | None,
                  nis_bounds: np.ndarray | None, path: str, title: str = "", max_points: int = 4000) -> None:
    """Mean NEES (12 dof) and mean NIS over the runs with their chi-square 95 % bands (shaded), log y.

    nees_mean (T,), nees_bounds (2,) or (T, 2); nis_mean (T,) (NaN where no run measured), nis_bounds (T, 2).
    """
    k = slice(None, None, _stride(len(t_s), max_points))
    t_min = np.asarray(t_s)[k] / 60.0
    rows = 2 if nis_mean is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(11, 3.4 * rows + 0.5), sharex=True, squeeze=False)
    series = [("mean NEES (12 dof)", nees_mean, np.broadcast_to(nees_bounds, (len(t_s), 2)))]
    if nis_mean is not None:
        series.append(("mean NIS", nis_mean, np.asarray(nis_bounds)))
    for ax, (label, y, bnd) in zip(axes[:, 0], series):
        bnd = bnd[k]
        ax.fill_between(t_min, bnd[:, 0], bnd[:, 1], color=BAND_FILL, alpha=0.45, lw=0, label="95 % chi-square band")
        ax.plot(t_min, y[k], color=BLUE_RMSE, lw=0.9, label=label)
        ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both", color="#c8d4e6")
        ax.legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel("t [min]")
    fig.suptitle(title or "Filter consistency")
    fig.tight_layout()
    _save(fig, path)


def plot_rmse_vs_bound(t_s: np.ndarray, rmse_block: np.ndarray, bound_block: np.ndarray | None, path: str,
                       title: str = "", filter_3sigma_block: np.ndarray | None = None, max_points: int = 4000) -> None:
    """Per block, the Monte Carlo RMSE (blue) against the PCRLB (black dashed), log y; optionally the filter's own
    3-sigma / 3 (red dotted: what the filter believes its RMSE is).

    rmse_block, bound_block, filter_3sigma_block (T, 4) in the statistics' units (`pcrlb.block_bounds`).
    """
    k = slice(None, None, _stride(len(t_s), max_points))
    t_min = np.asarray(t_s)[k] / 60.0
    fig, axes = plt.subplots(2, 2, figsize=(12, 7.5), sharex=True)
    for b in range(4):
        ax = axes[b // 2, b % 2]
        unit, s = BLOCK_DISPLAY[b]
        ax.plot(t_min, rmse_block[k, b] * s, color=BLUE_RMSE, lw=1.4, label="Monte Carlo RMSE")
        if bound_block is not None:
            ax.plot(t_min, bound_block[k, b] * s, color=BLACK_BOUND, ls="--", lw=1.4, label="PCRLB")
        if filter_3sigma_block is not None:
            ax.plot(t_min, filter_3sigma_block[k, b] / 3.0 * s, color=RED_FILTER, ls=":", lw=1.2,
                    label="filter sigma (P)")
        ax.set_yscale("log")
        ax.set_ylabel(f"{BLOCK_TITLES[b]} RMSE [{unit}]")
        ax.grid(alpha=0.3, which="both", color="#c8d4e6")
    _finish_time_grid(fig, axes, title or "RMSE against the posterior Cramér-Rao lower bound", path)


def plot_rate_sweep(rate_hz: np.ndarray, rmse_block: np.ndarray, path: str, bound_block: np.ndarray | None = None,
                    diverged_share: np.ndarray | None = None, title: str = "") -> None:
    """The rate sweep: per block, the settled RMSE (blue dots) against the filter rate (log-log), the PCRLB at each
    rate (black dashed) and the share of diverged runs (red, its own axis).

    rate_hz (K,) Hz; rmse_block, bound_block (K, 4) statistics' units (NaN: no converged run); diverged_share (K,).
    """
    order = np.argsort(rate_hz)
    r = np.asarray(rate_hz, dtype=float)[order]
    fig, axes = plt.subplots(1, 5 if diverged_share is not None else 4, figsize=(18, 3.8), squeeze=False)
    for b in range(4):
        ax = axes[0, b]
        unit, s = BLOCK_DISPLAY[b]
        ax.plot(r, rmse_block[order, b] * s, color=BLUE_RMSE, marker="o", lw=1.2, label="RMSE")
        if bound_block is not None:
            ax.plot(r, bound_block[order, b] * s, color=BLACK_BOUND, ls="--", marker="x", lw=1.2, label="PCRLB")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("filter rate [Hz]")
        ax.set_ylabel(f"{BLOCK_TITLES[b]} RMSE [{unit}]")
        ax.grid(alpha=0.3, which="both", color="#c8d4e6")
    axes[0, 0].legend(fontsize=8)
    if diverged_share is not None:
        ax = axes[0, 4]
        ax.plot(r, 100 * np.asarray(diverged_share)[order], color=RED_FILTER, marker="s", lw=1.2)
        ax.set_xscale("log")
        ax.set_ylim(-5, 105)
        ax.set_xlabel("filter rate [Hz]")
        ax.set_ylabel("diverged runs [%]")
        ax.grid(alpha=0.3, which="both", color="#c8d4e6")
    fig.suptitle(title or "Filter rate sweep")
    fig.tight_layout()
    _save(fig, path)
