"""A campaign of one run: it has no sample spread (the sample 3-sigma is NaN), so its figure draws the filter's
3-sigma alone, as its recording does, with no NumPy warning (`envisat montecarlo --runs 1` once printed
"warning: All-NaN slice encountered")."""

import warnings

from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign


def test_one_run_writes_its_figures_without_a_warning(tmp_path):
    cfg = MonteCarloConfig(scenario="default", runs=1, duration_s=40.0, settle_s=20.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        summary = run_campaign(cfg, tmp_path / "one")
    assert summary["n_runs"] == 1
    assert (tmp_path / "one" / "envelopes.png").stat().st_size > 0
