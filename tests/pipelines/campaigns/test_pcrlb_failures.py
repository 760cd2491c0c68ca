"""A campaign's PCRLB counts its random keypoint failures: the expected information of each keypoint is its
probability of being measured times its information (the bound had every keypoint of the visible set, so a
consistent filter with failure_prob 0.6 read RMSE/PCRLB 1.5-1.7 on the default scenario, and with max_markers 3
the bound of always the first three lay above the RMSE: attitude 0.66)."""

import json

import numpy as np

from envisat_pose.filtering.measurements import limit_markers, measured_probability, random_failures
from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign


def test_the_measured_probability_is_that_of_random_failures_then_the_first_max_markers():
    rng = np.random.default_rng(3)
    mask = rng.random((6, 8)) < 0.7
    for failure_prob, max_markers in ((0.4, 3), (0.6, None), (0.3, 1), (0.0, 3)):
        drawn = np.mean([limit_markers(random_failures(mask, failure_prob, rng), max_markers) for _ in range(4000)], 0)
        assert np.abs(drawn - measured_probability(mask, failure_prob, max_markers)).max() < 0.03
    assert np.array_equal(measured_probability(mask, 0.0, 3), limit_markers(mask, 3))


def test_half_the_keypoints_failing_bounds_like_twice_the_noise_variance(tmp_path):
    """3D markers with a constant noise: keeping each with probability 1/2 halves every step's expected
    information, as sigma x sqrt(2) does; the two campaigns' bounds agree."""
    def bound(name, **measurement):
        run_campaign(MonteCarloConfig(runs=2, duration_s=40.0, seed=0, measurement=measurement), tmp_path / name)
        with np.load(tmp_path / name / "campaign.npz") as z:
            pcrlb = z["pcrlb_block"]
        return pcrlb, json.loads((tmp_path / name / "summary.json").read_text())["pcrlb_rms"]

    failing, failing_rms = bound("failing", sigma_m=0.02, failure_prob=0.5)
    noisier, noisier_rms = bound("noisier", sigma_m=0.02 * np.sqrt(2.0))
    np.testing.assert_allclose(failing, noisier, rtol=1e-6)
    assert failing_rms == noisier_rms or all(np.isclose(failing_rms[b], noisier_rms[b]) for b in failing_rms)
