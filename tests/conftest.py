"""Shared fixtures: MuJoCo truth trajectories from the lead's simulator (datagen), never the filter's model."""

import pytest


@pytest.fixture(scope="session")
def truth_600():
    """The default scenario (50 m V-bar hold, 134.74 s tumble), 600 s at 1 s, simulated by MuJoCo."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate

    return simulate(scenario_config("default", duration_s=600.0, seed=0))


@pytest.fixture(scope="session")
def truth_1800():
    """The default scenario over its full 1800 s (MuJoCo), another random initial attitude."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate

    return simulate(scenario_config("default", duration_s=1800.0, seed=1))


@pytest.fixture(scope="session")
def chaser_of():
    """A function: truth trajectory -> (T, 4) chaser polar state."""
    from envisat_pose.filtering.estimator import chaser_states

    return lambda tr: chaser_states(tr.chaser_r_m, tr.chaser_rdot_m_s, tr.chaser_theta_rad, tr.chaser_thetadot_rad_s)
