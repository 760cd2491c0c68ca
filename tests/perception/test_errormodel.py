"""The detector's error model: the autocorrelation and inflation estimators against synthetic sequences of known
correlation, the bias figures against a known scaling, and the model's round trip through the weights' metadata
to `load_detector(...).error_model`."""

import json

import numpy as np
import pytest
import torch

from envisat_pose.perception import errormodel as em
from envisat_pose.perception.detect import load_detector
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import WeightsError, save_weights, with_metadata


def ar1(rng, rho, shape, n):
    """n steps of a stationary AR(1) of unit variance, independent over `shape`: (n, *shape)."""
    x = np.empty((n, *shape))
    x[0] = rng.standard_normal(shape)
    for t in range(1, n):
        x[t] = rho * x[t - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal(shape)
    return x


def sequence(err, sigma=1.0):
    t = len(err)
    return {"err_px": err, "sigma_px": np.full_like(err, sigma), "scale": np.full(t, np.nan),
            "radial_px": np.full((t, 8), np.nan), "dt_s": 2.0}


def test_ar1_rho_and_inflation_recovered_with_gaps():
    rng = np.random.default_rng(0)
    rho = 0.6
    seqs = []
    for _ in range(6):
        e = 1.7 * ar1(rng, rho, (8, 2), 400) + 0.3  # a constant bias: removed before the correlation
        e[rng.random((400, 8)) < 0.2] = np.nan  # corners missed at random
        seqs.append(sequence(e, sigma=1.7))
    model, record = em.measure_error_model(seqs, cov_scale=1.0, max_lag=6)
    assert abs(model.rho_lag1 - rho) < 0.03
    assert abs(model.ar1_phi - rho) < 0.05 and model.ar1_share > 0.9
    assert abs(model.inflation - (1 + rho) / (1 - rho)) < 0.3  # 4.0
    assert abs(record["pure_ar1"]["inflation"] - (1 + rho) / (1 - rho)) < 0.3
    assert abs(model.corr_time_s - (-2.0 / np.log(rho))) < 0.4
    r = np.array(record["autocorr_normalized"])
    assert np.all(np.abs(r[1:5] - rho ** np.arange(1, 5)) < 0.04)
    assert abs(record["bias_px_by_corner"]["C"][1] - 0.3) < 0.1


def test_white_plus_ar1_share_and_inflation_recovered():
    rng = np.random.default_rng(3)
    a, phi = 0.5, 0.85  # rho_k = a phi^k: r_1 = 0.425 alone would say (1.425 / 0.575) = 2.5; tau = 1 + 2 a phi / (1 - phi)
    tau = 1 + 2 * a * phi / (1 - phi)  # 6.67
    seqs = []
    for _ in range(8):
        e = np.sqrt(a) * ar1(rng, phi, (8, 2), 600) + np.sqrt(1 - a) * rng.standard_normal((600, 8, 2))
        e[rng.random((600, 8)) < 0.3] = np.nan
        seqs.append(sequence(e))
    model, record = em.measure_error_model(seqs, cov_scale=1.0, max_lag=8)
    assert abs(model.rho_lag1 - a * phi) < 0.03
    assert abs(model.ar1_share - a) < 0.08 and abs(model.ar1_phi - phi) < 0.04
    assert abs(model.inflation - tau) < 0.15 * tau
    assert record["pure_ar1"]["inflation"] < 0.5 * tau  # what AR(1) from lag 1 alone would miss


def test_white_errors_need_no_inflation():
    rng = np.random.default_rng(1)
    seqs = [sequence(rng.standard_normal((500, 8, 2))) for _ in range(3)]
    model, _ = em.measure_error_model(seqs, cov_scale=1.0)
    assert abs(model.rho_lag1) < 0.03
    assert abs(model.inflation - 1.0) < 0.1


def test_another_targets_keypoints_are_named_and_their_count_checked():
    """Five keypoints of another target: measured under their names (ENVISAT's eight corners are only the
    default), the correlation as for the corners; err_px of another count is refused naming both."""
    rng = np.random.default_rng(4)
    names = ("nose", "tail", "fin", "pod", "dish")
    seqs = [{**sequence(ar1(rng, 0.5, (5, 2), 400)), "radial_px": np.full((400, 5), np.nan)} for _ in range(3)]
    model, record = em.measure_error_model(seqs, cov_scale=1.0, max_lag=6, names=names)
    assert abs(model.rho_lag1 - 0.5) < 0.05
    assert list(record["bias_px_by_corner"]) == list(names) and list(record["autocorr_lag1_by_corner"]) == list(names)
    with pytest.raises(ValueError, match=r"8 keypoints .* got shapes \[\(5, 2\)\]"):
        em.measure_error_model(seqs, cov_scale=1.0)  # ENVISAT's 8 corners by default


def test_apparent_scale_and_radial_error_of_a_scaled_box():
    rng = np.random.default_rng(2)
    true = rng.uniform(100, 300, (5, 8, 2))
    right = np.ones((5, 8), bool)
    c = true.mean(axis=1, keepdims=True)
    pred = c + 1.01 * (true - c) + np.array([3.0, -2.0])  # 1 % larger, shifted: the scale ignores the shift
    s = em.apparent_scale(pred, true, right, np.zeros((5, 8), bool))
    np.testing.assert_allclose(s, 1.01, atol=1e-12)
    r = em.radial_errors(pred - np.array([3.0, -2.0]), true, right)  # unshifted: purely radial errors
    expect = 0.01 * np.linalg.norm(true - c, axis=-1)  # outward by 1 % of each corner's distance
    np.testing.assert_allclose(r, expect, atol=1e-9)
    wrong = np.zeros((5, 8), bool)
    wrong[1, 3] = True
    few = right.copy()
    few[2, 2:] = False
    s = em.apparent_scale(pred, true, few, wrong)
    assert np.isnan(s[1]) and np.isnan(s[2]) and np.isfinite(s[0])


def test_error_model_round_trips_through_the_weights(tmp_path):
    torch.manual_seed(0)  # this test's untrained model
    w, out = tmp_path / "w.safetensors", tmp_path / "e.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    assert load_detector(str(w)).error_model == em.ErrorModel()
    assert load_detector(str(w)).error_model.inflation == 1.0 and load_detector(str(w)).error_model.rho_lag1 == 0.0
    model = em.ErrorModel(cov_scale=0.8, rho_lag1=0.5, inflation=3.0, corr_time_s=1.44, bias_scale=1.002,
                          bias_radial_px=0.25, n_frames=300, source="test")
    with_metadata(str(w), str(out), {"error_model": model.to_json()})
    assert load_detector(str(out)).error_model == model
    assert json.loads(model.to_json())["inflation"] == 3.0
    bad = tmp_path / "bad.safetensors"
    with_metadata(str(w), str(bad), {"error_model": json.dumps({"rho_lag1": 1.5})})
    with pytest.raises(WeightsError, match="error_model"):
        load_detector(str(bad))
    with_metadata(str(w), str(bad), {"error_model": json.dumps({"bias_scale_sd": -1e-4})})
    with pytest.raises(WeightsError, match="bias_scale_sd"):
        load_detector(str(bad))


def test_the_scale_spread_is_that_of_the_sequences_means():
    """Three sequences whose per-frame scales average 1.000, 1.001 and 1.002 (NaN frames skipped): their sample
    standard deviation 0.001 times sqrt(1 + 1/3); a sequence with too few frames does not count."""
    rng = np.random.default_rng(5)
    seqs = []
    for m in (1.000, 1.001, 1.002):
        x = m + rng.normal(0.0, 1e-4, 40)
        x -= x.mean() - m  # each sequence's mean exactly m
        seqs.append(np.r_[x, np.nan, np.nan])
    sd, means = em.scale_spread(seqs + [np.array([1.5, np.nan])])
    np.testing.assert_allclose(means, [1.000, 1.001, 1.002], atol=1e-12)
    assert sd == pytest.approx(0.001 * np.sqrt(4.0 / 3.0), rel=1e-9)
    assert em.scale_spread(seqs[:1]) == (0.0, means[:1])


@pytest.mark.parametrize("a, phi, lam", [(1.0, 0.8, 0.9), (0.5, 0.93, 0.7), (0.3, 0.5, 0.0)])
def test_memory_inflation_matches_a_simulated_exponential_average(a, phi, lam):
    """tau(lambda) against the variance of an exponentially weighted average of simulated white + AR(1) errors,
    over the variance of the same average of white errors of the same variance (Monte Carlo, independent)."""
    rng = np.random.default_rng(3)
    n, m = 400, 4000  # steps, independent series
    slow = ar1(rng, phi, (m,), n)
    err = np.sqrt(a) * slow + np.sqrt(1 - a) * rng.standard_normal((n, m))
    white = rng.standard_normal((n, m))
    w = (1 - lam) * lam ** np.arange(n)[::-1]  # the newest frame last
    ratio = np.var(w @ err) / np.var(w @ white)
    assert abs(ratio - em.memory_inflation(a, phi, lam)) < 0.08 * em.memory_inflation(a, phi, lam)
    assert em.memory_inflation(a, phi, 0.0) == 1.0
    assert em.memory_inflation(a, phi, 1.0) == pytest.approx(em.model_inflation(a, phi))


def test_phi_at_another_frame_interval():
    assert em.phi_at(0.9, -2.0 / np.log(0.9), 2.0) == pytest.approx(0.9)
    assert em.phi_at(0.9, -2.0 / np.log(0.9), 4.0) == pytest.approx(0.81)
    assert em.phi_at(0.9, 0.0, 1.0) == 0.0


def turning_views(rate_rad_s, n, dt_s=1.0):
    """R_cam_from_target (n, 3, 3) of a view turning at rate_rad_s about a fixed tilted axis."""
    from scipy.spatial.transform import Rotation

    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    base = Rotation.from_euler("xyz", [0.4, -1.1, 2.0])
    return np.stack([(Rotation.from_rotvec(axis * rate_rad_s * dt_s * t) * base).as_matrix() for t in range(n)])


def test_rotation_angles_of_a_constant_turn():
    R = turning_views(np.radians(3.0), 30)
    np.testing.assert_allclose(np.degrees(em.rotation_angles(R, 1)), 3.0, atol=1e-9)
    np.testing.assert_allclose(np.degrees(em.rotation_angles(R, 7)), 21.0, atol=1e-9)


def test_correlation_in_the_views_rotation_recovered_across_tumble_rates():
    """Errors whose slow part decays with the angle the view turned (share a, angle theta_c), on sequences turning
    at 1.5, 2.7 and 5 deg/s: the angle fit finds one (a, theta_c) for all; the time fit (one correlation time)
    cannot, and phi_at_rotation gives each rate's per-frame coefficient."""
    rng = np.random.default_rng(5)
    a, theta_c = 0.4, np.radians(15.0)
    seqs = []
    for rate_deg in (1.5, 2.7, 5.0):
        phi = np.exp(-np.radians(rate_deg) / theta_c)
        for _ in range(3):
            e = np.sqrt(a) * ar1(rng, phi, (8, 2), 500) + np.sqrt(1 - a) * rng.standard_normal((500, 8, 2))
            e[rng.random((500, 8)) < 0.2] = np.nan
            s = sequence(e)
            s["dt_s"] = 1.0
            s["R_cam_from_target"] = turning_views(np.radians(rate_deg), 500)
            seqs.append(s)
    model, record = em.measure_error_model(seqs, cov_scale=1.0, max_lag=10)
    assert abs(model.angle_share - a) < 0.06
    assert abs(np.degrees(model.corr_angle_rad) - 15.0) < 2.0
    np.testing.assert_allclose(record["autocorr_by_angle"]["view_rate_deg_s"], [1.5] * 3 + [2.7] * 3 + [5.0] * 3,
                               atol=1e-6)
    assert em.phi_at_rotation(model.corr_angle_rad, np.radians(5.0), 1.0) < \
        em.phi_at_rotation(model.corr_angle_rad, np.radians(1.5), 1.0)
    assert em.phi_at_rotation(theta_c, np.radians(5.0), 2.0) == pytest.approx(np.exp(-np.radians(10.0) / theta_c))
    assert em.phi_at_rotation(0.0, 1.0, 1.0) == 0.0
    # without the views the model carries no angle fit
    plain = [{k: v for k, v in s.items() if k != "R_cam_from_target"} for s in seqs]
    model2, record2 = em.measure_error_model(plain, cov_scale=1.0, max_lag=10)
    assert model2.corr_angle_rad == 0.0 and record2["autocorr_by_angle"] is None
