"""The closed loop's use of the steppable filter: a prediction made first (predict_to, for the detector's region of
interest) and handed to filter_step as its prior gives exactly the step that predicts on its own, for several
measurement hypotheses sharing that one prediction; per-corner covariances that change every frame (the
detector's) are taken as given."""

import numpy as np

from envisat_pose.filtering.estimator import FilterConfig, Measurement, filter_step, init_state, make_setup, predict_to
from envisat_pose.filtering.measurements import measure


def test_prior_from_predict_to_equals_the_step_that_predicts(truth_600, chaser_of):
    tr = truth_600
    ch = chaser_of(tr)
    cfg = FilterConfig(adaptive_r=True)
    setup = make_setup(cfg, "pixels")
    rng = np.random.default_rng(4)
    x0 = tr.x[0] + rng.standard_normal((2, 12)) @ np.linalg.cholesky(cfg.P0).T
    state = init_state(x0, cfg.P0, tr.t_s[0], ch[0], cfg)
    for k in range(1, 30):
        z = measure(tr.x[k], "pixels") + rng.normal(0.0, 1.5, (8, 2))
        mask = np.broadcast_to(tr.visible[k] & tr.in_frame[k], (2, 8))
        # a different covariance per corner and frame, as the detector gives
        R_c = np.einsum("cij,c->cij", np.broadcast_to(np.eye(2), (8, 2, 2)), rng.uniform(1.0, 4.0, 8))
        meas = Measurement(tr.t_s[k], ch[k], np.broadcast_to(z, (2, 8, 2)), mask, R_c)
        prior = predict_to(state, tr.t_s[k], setup)
        assert prior[0].shape == (2, 12) and prior[1].shape == (2, 12, 12)
        alt = filter_step(state, Measurement(tr.t_s[k], ch[k], np.broadcast_to(z[::-1], (2, 8, 2)), mask, R_c),
                          setup, prior=prior)  # a second hypothesis on the same prior leaves it untouched
        with_prior = filter_step(state, meas, setup, prior=prior)
        plain = filter_step(state, meas, setup)
        np.testing.assert_array_equal(with_prior.mean, plain.mean)
        np.testing.assert_array_equal(with_prior.cov, plain.cov)
        np.testing.assert_array_equal(with_prior.nis, plain.nis)
        np.testing.assert_array_equal(with_prior.r_scale, plain.r_scale)
        assert alt.t_s == plain.t_s
        state = plain
    err = np.abs(state.mean[:, 0:3] - tr.x[29, 0:3])
    assert np.all(err < 0.5)  # pixels of the visible corners pull the position in from P0's 1 m
