"""An outage window that holds no step of the truth (typed for a longer truth, or in minutes) removed no
measurement without a word: the estimate and the campaign now warn, naming the window."""

import warnings

import pytest

from envisat_pose.filtering.montecarlo import MeasurementConfig
from envisat_pose.pipelines.campaigns.observability import warn_outages_outside


def test_a_window_after_the_truth_is_warned_of_and_one_inside_is_not():
    import numpy as np

    t_s = np.arange(61.0)
    with pytest.warns(UserWarning, match=r"outages_s\[1\] \[700, 800\) s holds no step of the truth \(0 to 60 s\)"):
        warn_outages_outside(t_s, MeasurementConfig(outages_s=((10.0, 20.0), (700.0, 800.0))))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_outages_outside(t_s, MeasurementConfig(outages_s=((10.0, 20.0), (60.0, 700.0))))


def test_the_estimate_warns_of_it(tmp_path):
    from envisat_pose.pipelines.campaigns.estimate import run_estimate
    from envisat_pose.pipelines.jobs import resolve_job

    cfg = resolve_job("estimate", "default", overrides={"measurement.outages_s": [[700.0, 800.0]]})
    with pytest.warns(UserWarning, match="holds no step of the truth"):
        run_estimate(cfg, tmp_path / "e.npz", scenario="default", duration_s=10.0)
