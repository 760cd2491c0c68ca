"""filterpy's UKF (the reference, MRP hooks, the split update written on it) and our batched UKF on the same inputs:
equal to 1e-9."""

import numpy as np
import pytest

from envisat_pose.filtering.estimator import FilterConfig, run_filter
from envisat_pose.filtering.montecarlo import MeasurementConfig, inputs_from_truth
from envisat_pose.filtering.reference import make_reference_ukf, reference_predict, reference_update


@pytest.mark.parametrize("kind", ["markers3d", "pixels"])
def test_filterpy_and_batched_agree_over_100_steps(truth_600, chaser_of, kind):
    tr = truth_600
    T, R = 100, 2
    cfg = FilterConfig(gate_prob=0.0, outage_q_scale=1.0, visibility_check=False)  # as the reference
    mcfg = MeasurementConfig(kind=kind, failure_prob=0.3, outages_s=((40.0, 44.0),))
    inp = inputs_from_truth(tr, mcfg, cfg.P0, seed=11, n_runs=R, sel=slice(0, T))
    n_meas = inp.mask.sum(-1)
    assert len(np.unique(n_meas)) >= 5 and (n_meas == 0).any()  # the visible set really varies, with gaps
    c = chaser_of(tr)[:T]
    res = run_filter(inp.x0_hat, cfg.P0, tr.t_s[:T], c, inp.z, inp.mask, inp.R_c, kind, cfg)
    switches = splits = 0
    for r in range(R):
        ukf = make_reference_ukf(inp.x0_hat[r], cfg.P0, cfg.Q(1.0))
        for k in range(T):
            if k > 0:
                reference_predict(ukf, 1.0, c[k - 1])
            splits += reference_update(ukf, inp.z[r, k], inp.mask[r, k], inp.R_c, kind,
                                       split=(cfg.split_gain, cfg.split_max)) > 1
            np.testing.assert_allclose(res.x_hat[r, k], ukf.x, rtol=0, atol=1e-9, err_msg=f"run {r} step {k}")
            np.testing.assert_allclose(res.P[r, k], ukf.P, rtol=0, atol=1e-9, err_msg=f"run {r} step {k}")
        switches += int(np.sum(np.abs(np.diff(res.x_hat[r, :, 6:9], axis=0)).max(-1) > 0.5))
    assert switches >= 1  # the comparison went through MRP shadow switches
    assert splits >= R  # and through the first step's partial updates (filtering/step_update.py)
