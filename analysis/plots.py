"""Plots people look at. Matplotlib with the Agg backend (no display needed); PNG files."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from envisat_pose.io import atomic_path  # noqa: E402

STATE_LABELS = (
    ("rho_x [m]", "rho_y [m]", "rho_z [m]"),
    ("rho'_x [m/s]", "rho'_y [m/s]", "rho'_z [m/s]"),
    ("p_1", "p_2", "p_3"),
    ("w_r,1 [deg/s]", "w_r,2 [deg/s]", "w_r,3 [deg/s]"),
)
STATE_TITLES = ("relative position rho, in C", "relative velocity rho', in C",
                "MRP p of T relative to C", "relative angular velocity w_r, in T")


def plot_states(t_s: np.ndarray, x: np.ndarray, path: str, title: str = "", visible: np.ndarray | None = None) -> None:
    """A 4 x 3 grid of the 12 states over time (minutes), plus the number of visible corners if given."""
    rows = 5 if visible is not None else 4
    fig, axes = plt.subplots(rows, 3, figsize=(13, 2.3 * rows + 0.6), sharex=True, squeeze=False)
    t_min = t_s / 60.0
    scale = np.ones(12)
    scale[9:12] = 180.0 / np.pi
    for i in range(12):
        ax = axes[i // 3, i % 3]
        ax.plot(t_min, x[:, i] * scale[i], lw=0.9)
        ax.set_ylabel(STATE_LABELS[i // 3][i % 3])
        ax.grid(alpha=0.3)
        if i % 3 == 1:
            ax.set_title(STATE_TITLES[i // 3], fontsize=10)
    if visible is not None:
        ax = axes[4, 0]
        ax.step(t_min, visible.sum(axis=1), where="post", lw=0.9)
        ax.set_ylabel("visible corners")
        ax.set_ylim(-0.5, 8.5)
        ax.grid(alpha=0.3)
        axes[4, 1].axis("off")
        axes[4, 2].axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("t [min]")
    fig.suptitle(title or "ENVISAT relative state (truth)")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
