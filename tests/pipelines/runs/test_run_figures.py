"""What `envisat run`'s errors.png draws: frames without an estimate (acquiring, lost) are gaps, never the
placeholder state the run's rows keep there (zeros and a huge covariance, for est.npz's contract)."""

import numpy as np

from envisat_pose.pipelines.runs.rows import RunRows
from envisat_pose.pipelines.runs.run_files import plot_inputs
from envisat_pose.status import STATUSES


def _write_run(run_dir, T, acquiring_until, sigma):
    rows = RunRows(str(run_dir), T, chunk=7)
    for k in range(T):
        i = rows.row(k)
        tracking = k >= acquiring_until
        rows.buf["x_hat"][i] = np.full(12, 0.5) if tracking else 0.0
        rows.buf["P"][i] = np.eye(12) * (sigma**2 if tracking else 1e8)
        rows.buf["status"][i] = STATUSES.index("tracking" if tracking else "acquiring")
    rows.close()


def test_the_figure_skips_frames_without_an_estimate_and_averages_p_over_runs_that_have_one(tmp_path):
    T = 20
    _write_run(tmp_path / "run-0000", T, acquiring_until=5, sigma=1.0)
    _write_run(tmp_path / "run-0001", T, acquiring_until=10, sigma=3.0)
    t_s = np.arange(T, dtype=float)
    t, x_true, x_hat, P = plot_inputs(t_s, np.zeros((T, 12)), [str(tmp_path / "run-0000"), str(tmp_path / "run-0001")])
    assert np.array_equal(t, t_s) and x_true.shape == (2, T, 12)
    assert np.isnan(x_hat[0, :5]).all() and np.isnan(x_hat[1, :10]).all()
    assert np.allclose(x_hat[0, 5:], 0.5) and np.allclose(x_hat[1, 10:], 0.5)
    var = np.diagonal(P[0], axis1=-2, axis2=-1)
    assert np.isnan(var[:5]).all()                   # no run has an estimate: no covariance drawn
    assert np.allclose(var[5:10], 1.0)               # run 0 alone
    assert np.allclose(var[10:], (1.0 + 9.0) / 2)    # both runs: their mean
    assert np.isfinite(var[5:]).all() and np.nanmax(var) < 1e3  # the placeholder's 1e8 nowhere
