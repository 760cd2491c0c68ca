"""Shared fixtures: MuJoCo truth trajectories from the lead's simulator (datagen), never the filter's model; and
the slow lane: the tests listed in SLOW are marked `slow` (pyproject.toml), so `make test` (-m "not slow") runs
in minutes and `make test-slow` / `make test-all` (CI) run them too."""

import pytest

# The slow end-to-end tests, by node id (a parametrized test without its [...] marks every case). Measured with
# `pytest --durations` on the 2-core machine; each module keeps at least one test in the fast lane.
# tests/test_architecture.py checks that every id names a test that exists.
SLOW = (
)


def _slow(nodeid: str) -> bool:
    return nodeid in SLOW or nodeid.split("[", 1)[0] in SLOW


def pytest_collection_modifyitems(config, items):
    for item in items:
        if _slow(item.nodeid):
            item.add_marker(pytest.mark.slow)


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
