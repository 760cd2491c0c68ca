"""Covariance calibration: an honest covariance gives a mean e^T C^-1 e of 2; a scaled one is found out."""

import numpy as np

from envisat_pose.perception.calibrate import calibration_by_group, fit_cov_scale, nees_px


def _samples(rng, n):
    A = rng.normal(size=(n, 2, 2))
    cov = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(2)
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, 2)))
    return err, cov


def test_honest_covariance_has_mean_two():
    err, cov = _samples(np.random.default_rng(0), 20000)
    assert abs(np.mean(nees_px(err, cov)) - 2.0) < 0.06


def test_fit_scale_recovers_a_misscaled_covariance():
    err, cov = _samples(np.random.default_rng(1), 20000)
    s = fit_cov_scale(err, cov / 3.0)  # the network claims 3x too little variance
    assert abs(s - 3.0) < 0.15
    assert abs(np.mean(nees_px(err, s * cov / 3.0)) - 2.0) < 1e-9


def test_groups():
    err, cov = _samples(np.random.default_rng(2), 4000)
    group = np.where(np.arange(4000) < 2000, "clean", "noisy")
    cov = np.where((group == "noisy")[:, None, None], cov / 4.0, cov)
    out = calibration_by_group(err, cov, group)
    assert out["clean"]["count"] == 2000 and abs(out["clean"]["mean_nees"] - 2) < 0.2
    assert abs(out["noisy"]["mean_nees"] - 8) < 0.8


def test_floor_brings_the_mean_to_two_and_is_zero_when_covered():
    from envisat_pose.perception.calibrate import fit_floor, nees_px

    rng = np.random.default_rng(4)
    sig = rng.uniform(0.05, 0.3, 4000)
    err = rng.normal(0, 1, (4000, 2)) * np.sqrt(sig[:, None] ** 2 + 0.04)  # each claims sig^2, misses 0.04 px^2
    cov = sig[:, None, None] ** 2 * np.eye(2)
    f = fit_floor(err, cov)
    assert abs(f - 0.04) < 0.004
    assert abs(np.mean(nees_px(err, cov + f * np.eye(2))) - 2.0) < 1e-6
    assert fit_floor(err, cov * 100.0) == 0.0
