"""The estimate's and the campaign's recordings carry the NEES with its 95 % band (metrics/nees/{value,band}, as a
tracker's run does) and a plot of it: before, `envisat estimate --rrd` and `envisat montecarlo --rrd` (a CubeSat,
4 runs over 60 s: mean NEES 10.37 in the summary and in nees_nis.png) held errors and 3-sigma bands only, no NEES.
The NEES is rebuilt here from the arrays (e^T P^-1 e, one step at a time) and the band from scipy."""

import os
import sys

import numpy as np
from scipy.stats import chi2

from envisat_pose.analysis import recording
from envisat_pose.analysis.recording import read_recording
from envisat_pose.contracts import Estimates

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from test_recording_blueprint import time_series_views  # noqa: E402


def estimates_without_attitude_error(R=3, T=7, seed=4) -> Estimates:
    """R runs whose attitude (MRP) is exact, so every chart's error is the plain difference x_hat - x_true."""
    rng = np.random.default_rng(seed)
    t_s = np.arange(T) * 2.0
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_true[..., 6:9] = 0.1 * np.sin(t_s[:, None] / 10 + np.arange(3))
    x_hat = x_true + 0.01 * rng.standard_normal((R, T, 12))
    x_hat[..., 6:9] = x_true[..., 6:9]
    A = rng.standard_normal((R, T, 12, 12))
    P = A @ np.swapaxes(A, -1, -2) * 1e-4 + 1e-6 * np.eye(12)
    return Estimates(t_s=t_s, x_true=x_true, x_hat=x_hat, P=P, n_meas=np.full((R, T), 8), nis=np.ones((R, T)),
                     nis_dof=np.full((R, T), 24), diverged=np.zeros(R, bool), config_json="{}")


def plain_nees(x_true, x_hat, P) -> np.ndarray:
    """e^T P^-1 e of every (run, step), e the plain difference."""
    out = np.empty(x_hat.shape[:-1])
    for idx in np.ndindex(*out.shape):
        e = x_hat[idx] - x_true[idx]
        out[idx] = e @ np.linalg.inv(P[idx]) @ e
    return out


def logged_nees(path):
    static, temporal = read_recording(str(path))
    value, band = temporal["/metrics/nees/value"], temporal["/metrics/nees/band"]
    assert value["frame"] == band["frame"]
    seconds = [d.total_seconds() for d in value["sim_time"]]
    return (static, seconds, np.array([v[0] for v in value["Scalars:scalars"]]),
            np.array(band["Scalars:scalars"], dtype=float))


def test_the_estimates_recording_plots_the_runs_mean_nees_and_its_band(tmp_path):
    est = estimates_without_attitude_error()
    R, T = est.x_hat.shape[:2]
    path = tmp_path / "est.rrd"
    recording.write_estimates_recording(str(path), est)
    static, seconds, value, band = logged_nees(path)
    np.testing.assert_allclose(seconds, est.t_s)
    np.testing.assert_allclose(value, plain_nees(est.x_true, est.x_hat, est.P).mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(band, np.tile(chi2.ppf([0.025, 0.975], 12 * R) / R, (T, 1)), rtol=1e-9)
    assert static["/metrics/nees/value"]["SeriesLines:names"] == [f"mean NEES over {R} runs"]
    assert static["/metrics/nees/band"]["SeriesLines:names"] == ["2.5 %", "97.5 %"]
    assert any("NEES" in name for name in time_series_views(path))  # shown at load, not only stored
    # the filter's own chart: the caller's NEES is what is drawn
    given = np.arange(R * T, dtype=float).reshape(R, T)
    recording.write_estimates_recording(str(path), est, nees_rt=given)
    np.testing.assert_allclose(logged_nees(path)[2], given.mean(axis=0))


def test_the_campaign_recording_plots_the_campaigns_nees_or_run_0s(tmp_path):
    est = estimates_without_attitude_error(R=2)
    T = len(est.t_s)
    args = (est.t_s, est.x_true[0], est.x_hat[0], est.P[0], est.x_hat - est.x_true, np.ones((T, 12)), None)
    path = tmp_path / "mc.rrd"
    nees_mean, bounds = np.linspace(9.0, 13.0, T), np.array([11.1, 12.9])
    recording.write_campaign_recording(str(path), *args, nees_mean=nees_mean, nees_bounds=bounds, runs=40)
    static, seconds, value, band = logged_nees(path)
    np.testing.assert_allclose(seconds, est.t_s)
    np.testing.assert_allclose(value, nees_mean)
    np.testing.assert_allclose(band, np.tile(bounds, (T, 1)))
    assert static["/metrics/nees/value"]["SeriesLines:names"] == ["mean NEES over 40 runs"]
    # without the campaign's: run 0's own NEES and the band of a single 12-dof chi-square
    recording.write_campaign_recording(str(path), *args)
    static, _, value, band = logged_nees(path)
    np.testing.assert_allclose(value, plain_nees(est.x_true[0], est.x_hat[0], est.P[0]), rtol=1e-9)
    np.testing.assert_allclose(band, np.tile(chi2.ppf([0.025, 0.975], 12), (T, 1)), rtol=1e-9)
    assert static["/metrics/nees/value"]["SeriesLines:names"] == ["NEES"]
