"""Plots: the MRP error compares estimate and truth on one set; the PNGs are written."""

import numpy as np

from envisat_pose.analysis.plots import estimate_errors, plot_estimate, plot_states
from envisat_pose.attitude import mrp_error_angle_rad


def test_mrp_error_is_small_when_the_estimate_sits_on_the_shadow_set():
    p_true = np.array([0.0, 0.0, 0.999])
    p_near = np.array([0.0, 0.0, 1.001])  # 0.23 deg away, past |p| = 1
    p_hat = -p_near / np.dot(p_near, p_near)  # the estimate reported on the short set: far away as numbers
    x_true = np.zeros((1, 1, 12))
    x_hat = np.zeros((1, 1, 12))
    x_true[0, 0, 6:9], x_hat[0, 0, 6:9] = p_true, p_hat
    err = estimate_errors(x_true, x_hat)
    assert np.linalg.norm(err[0, 0, 6:9]) < 0.003
    assert np.degrees(mrp_error_angle_rad(p_hat, p_true)) < 0.25


def test_plots_are_written(tmp_path):
    rng = np.random.default_rng(0)
    T, R = 50, 3
    t_s = np.arange(T, dtype=float)
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_hat = x_true + rng.normal(0, 0.01, x_true.shape)
    P = np.broadcast_to(np.eye(12) * 1e-4, (R, T, 12, 12))
    plot_estimate(t_s, x_true, x_hat, P, str(tmp_path / "est.png"))
    plot_states(t_s, x_true[0], str(tmp_path / "run.png"), visible=np.ones((T, 8), bool))
    for name in ("est.png", "run.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
