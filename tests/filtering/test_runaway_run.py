"""A batch shares its RK4 sub-step (the fastest run's): one run whose rate estimate ran away must not stall the
others in millions of sub-steps (seen: `envisat estimate` with p0_sigma = [100, 1, 1, 0.1], 20 runs: one run's
|w| reached 5e5 rad/s at step 154, the sub-step 3e-7 s, and the job never finished; with the bound on
the sub-steps it finishes in 30 s, 16 of 20 runs flagged diverged)."""

import math

import numpy as np
import pytest

from envisat_pose.filtering import fast
from envisat_pose.filtering.estimator import FilterConfig, Measurement, filter_step, init_state, make_setup

N_ORBIT = 1.046018e-3
CHASER = np.array([7142e3, 0.0, 0.0, N_ORBIT])


def _state(cfg, runaway: bool):
    """Two runs of the default hold (target 50 m ahead, 2.67 deg/s); run 1's rate diverged when runaway."""
    x = np.zeros((2, 12))
    x[:, 1] = 50.0
    x[:, 9:12] = 2 * np.pi / 134.74 * np.array([0.12, -0.20, 1.0]) / np.linalg.norm([0.12, -0.20, 1.0])
    P = np.broadcast_to(np.diag(np.repeat(np.square([1e-3, 1e-5, 1e-4, 1e-6]), 3)), (2, 12, 12)).copy()
    if runaway:
        x[1, 9:12] = [3e5, -2e5, 1e5]
        P[1, 9:12, 9:12] = 1e10 * np.eye(3)
    return init_state(x, P, 0.0, CHASER, cfg)


def _spied_steps(monkeypatch):
    steps = []
    real = fast.predict_fused

    def spy(mean, cov, c0, dt_s, Q, setup, max_step_s=1.0):
        steps.append((dt_s, max_step_s))
        if math.ceil(dt_s / max_step_s - 1e-9) > 10_000:  # the stall itself: never run it
            return mean, cov
        return real(mean, cov, c0, dt_s, Q, setup, max_step_s)

    monkeypatch.setattr(fast, "predict_fused", spy)
    return steps


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the runaway run overflows, as it is built to
def test_one_runaway_run_does_not_stall_the_batch_in_sub_steps(monkeypatch):
    cfg = FilterConfig()
    setup = make_setup(cfg, "markers3d")
    steps = _spied_steps(monkeypatch)
    meas = Measurement(1.0, CHASER, np.zeros((2, 8, 3)), np.zeros((2, 8), dtype=bool), 4e-4 * np.eye(3))
    healthy = filter_step(_state(cfg, runaway=False), meas, setup)
    assert steps[-1] == (1.0, 1.0)  # a healthy batch keeps its sub-step (the default's figures unchanged)
    state = filter_step(_state(cfg, runaway=True), meas, setup)
    dt_s, step_s = steps[-1]
    assert math.ceil(dt_s / step_s - 1e-9) <= 100
    # the healthy run of the batch is predicted as it is alone, to the RK4 error of a finer sub-step
    assert np.isfinite(state.mean[0]).all() and np.isfinite(state.cov[0]).all()
    np.testing.assert_allclose(state.mean[0], healthy.mean[0], rtol=0, atol=1e-9)
    sd = np.sqrt(np.diag(healthy.cov[0]))
    assert np.abs((state.cov[0] - healthy.cov[0]) / np.outer(sd, sd)).max() < 1e-6


def test_the_sub_step_bound_keeps_a_configured_shorter_step():
    from envisat_pose.filtering.dynamics import sigma_step_s

    mean, cov = np.zeros((1, 12)), np.zeros((1, 12, 12))
    mean[0, 9] = 1e6  # a runaway rate: the bound on the sub-steps holds
    assert sigma_step_s(1.0, mean, cov, 12.0, dt_s=10.0) == 0.1
    assert sigma_step_s(0.01, mean, cov, 12.0, dt_s=10.0) == 0.01  # the config's max_rk4_step_s still holds
    mean[0, 9] = 0.05  # ENVISAT's tumble: untouched
    assert sigma_step_s(1.0, mean, cov, 12.0, dt_s=20.0) == sigma_step_s(1.0, mean, cov, 12.0)
