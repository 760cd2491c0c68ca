"""Scoring a tracker's runs: convergence needs the filter running (a close PnP pose while acquiring is not a
converged track), the figures after it equal a direct computation on the same frames."""

import numpy as np

from envisat_pose.pipelines.scoring import TRACKING, converged_from, score_runs
from envisat_pose.pipelines.tracker import STATUSES


def test_tracking_index_is_the_trackers():
    assert STATUSES[TRACKING] == "tracking"


def test_convergence_waits_for_the_filter():
    t = np.arange(10.0)
    pos, att = np.full(10, 0.01), np.full(10, 0.1)
    tracking = np.arange(10) >= 4
    assert converged_from(t, pos, att) == 0.0
    assert converged_from(t, pos, att, tracking) == 4.0
    pos[6] = 0.2
    assert converged_from(t, pos, att, tracking) == 7.0
    pos[9] = 0.2
    assert converged_from(t, pos, att, tracking) is None


def test_scores_after_convergence_equal_a_direct_computation():
    rng = np.random.default_rng(0)
    T = 50
    t = np.arange(T, dtype=float)
    x_true = np.zeros((1, T, 12))
    x_true[..., 1] = 50.0  # 50 m along V-bar
    x_true[..., 9:] = 0.01
    x_hat = x_true + rng.normal(0, 1e-3, (1, T, 12))
    x_hat[0, :10, 0] += 1.0  # far off while acquiring
    x_hat[0, 10:12, 9:] += 0.05  # rate off on the first frames the PnP pose is close: still acquiring
    P = np.broadcast_to(np.eye(12) * 1e-6, (1, T, 12, 12)).copy()
    status = np.where(np.arange(T) < 12, 0, 1)[None]
    s = score_runs(t, x_true, x_hat, P, status)
    assert s["time_to_converge_s"] == [12.0]
    e = x_hat[0, 12:] - x_true[0, 12:]
    assert np.isclose(s["rmse_after_convergence"]["position_m"], np.sqrt(np.mean(np.sum(e[:, :3] ** 2, -1))))
    assert np.isclose(s["mean_nees_after_convergence"], np.mean(np.sum(e**2, -1) / 1e-6), rtol=1e-6)
    rng_err = np.linalg.norm(x_hat[0, 12:, :3], axis=-1) - 50.0
    assert np.isclose(s["range_bias_m"], rng_err.mean())
