"""A campaign's initial errors drawn wider (or narrower) than the P0 the filter is told: init_error_scale."""

import numpy as np
import pytest

from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.filtering.montecarlo import MeasurementConfig, make_run_inputs

P0 = FilterConfig().P0
X0 = np.array([0.0, 50.0, 0.0, 0.0, 0.0, 0.0, 0.1, -0.2, 0.05, 0.0, 0.04, 0.0])


def _x0_hat(n_runs, **kw):
    z_true = np.zeros((1, 8, 3))  # one step: the draws of the initial errors come first in each run's stream
    return make_run_inputs(X0, np.zeros(1), z_true, np.ones((1, 8), bool), MeasurementConfig(), P0, seed=7,
                           n_runs=n_runs, **kw).x0_hat


def test_the_initial_errors_spread_by_the_scale_and_the_filter_keeps_p0():
    """Each component's sample sigma over 4000 runs against S x sqrt(P0_ii) (its sampling sd ~1.1 %: within 5 %),
    and the same standard normals scaled: run r's error at S = 3 is 3 x its error at S = 1."""
    one, three = _x0_hat(4000) - X0, _x0_hat(4000, init_error_scale=3.0) - X0
    np.testing.assert_allclose(three.std(axis=0) / (3.0 * np.sqrt(np.diag(P0))), 1.0, atol=0.05)
    np.testing.assert_allclose(three, 3.0 * one, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(_x0_hat(50, init_error_scale=1.0), _x0_hat(50))  # the default: the draws of before


@pytest.mark.parametrize("scale", [0.0, -1.0, float("nan"), 1e3])
def test_a_scale_out_of_range_is_refused_naming_the_field(scale):
    from envisat_pose.config import ConfigError
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig

    with pytest.raises(ConfigError, match="init_error_scale"):
        EstimateConfig(init_error_scale=scale)
