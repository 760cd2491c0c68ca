"""Monte Carlo consistency of the batched UKF on the MuJoCo truth of the default scenario (issue 4):
100 runs, 3D corners with sigma 0.02 m, all visible corners."""

import numpy as np
import pytest
from scipy.stats import chi2

from envisat_pose.attitude import mrp_error_angle_rad
from filtering.estimator import FilterConfig, nees, run_filter
from filtering.montecarlo import MeasurementConfig, make_run_inputs


@pytest.fixture(scope="module")
def mc_default(truth_600, chaser_of):
    tr = truth_600
    cfg = FilterConfig()
    inp = make_run_inputs(tr.x, tr.t_s, tr.visible, MeasurementConfig(sigma_m=0.02), cfg.P0, seed=2024, n_runs=100)
    res = run_filter(inp.x0_hat, cfg.P0, tr.t_s, chaser_of(tr), inp.z, inp.mask, inp.R_c, "markers3d", cfg)
    return tr, res


def test_time_averaged_nees_inside_its_95_percent_interval(mc_default):
    tr, res = mc_default
    R = res.x_hat.shape[0]
    anees = nees(tr.x[None], res.x_hat, res.P).mean(axis=0)  # (T,) average over runs
    lo, hi = chi2.ppf([0.025, 0.975], 12 * R) / R
    avg = anees.mean()
    print(f"time-averaged ANEES {avg:.2f}, 95% interval [{lo:.2f}, {hi:.2f}]")
    assert lo < avg < hi
    # the NIS agrees: innovations are as large as the filter says
    assert abs(res.nis.sum() / res.dof.sum() - 1.0) < 0.02


def test_rms_errors_after_300_s(mc_default):
    tr, res = mc_default
    late = tr.t_s >= 300.0
    pos = np.linalg.norm(res.x_hat[:, late, :3] - tr.x[None, late, :3], axis=-1)
    ang = np.degrees(mrp_error_angle_rad(res.x_hat[:, late, 6:9], tr.x[None, late, 6:9]))
    rms_pos, rms_ang = np.sqrt(np.mean(pos**2)), np.sqrt(np.mean(ang**2))
    print(f"RMS after 300 s: {100 * rms_pos:.3f} cm, {rms_ang:.4f} deg")
    assert rms_pos < 0.03 and rms_ang < 0.5
    assert not res.diverged.any()
    assert np.isfinite(res.x_hat).all() and np.isfinite(res.P).all()
    # the attitude converged from the ~10 deg of P0
    ang0 = np.degrees(mrp_error_angle_rad(res.x_hat[:, 0, 6:9], tr.x[0, 6:9]))
    assert np.sqrt(np.mean(ang0**2)) > 5 * rms_ang


def test_three_markers_case(truth_600, chaser_of):
    """The paper's 3-marker case: fewer corners, still converging (20 runs)."""
    tr = truth_600
    cfg = FilterConfig()
    inp = make_run_inputs(tr.x, tr.t_s, tr.visible, MeasurementConfig(max_markers=3), cfg.P0, seed=5, n_runs=20)
    assert inp.mask.sum(-1).max() == 3
    res = run_filter(inp.x0_hat, cfg.P0, tr.t_s, chaser_of(tr), inp.z, inp.mask, inp.R_c, "markers3d", cfg)
    late = tr.t_s >= 300.0
    pos = np.linalg.norm(res.x_hat[:, late, :3] - tr.x[None, late, :3], axis=-1)
    ang = np.degrees(mrp_error_angle_rad(res.x_hat[:, late, 6:9], tr.x[None, late, 6:9]))
    assert np.sqrt(np.mean(pos**2)) < 0.03 and np.sqrt(np.mean(ang**2)) < 0.5
    assert not res.diverged.any()
