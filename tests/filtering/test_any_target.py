"""The UKF over any target's K keypoints: ENVISAT's numbers unchanged, the upper stage's (K = 12) consistent.

make_setup(target=...) carries the target's keypoints (K, 3), inertia and visibility rule; the estimate pipeline
takes them from the truth's target file.
"""

import numpy as np
import pytest

from envisat_pose.analysis.stats import chi2_mean_bounds
from envisat_pose.filtering.estimator import (
    FilterConfig,
    Measurement,
    chaser_states,
    filter_step,
    init_state,
    make_setup,
    nees,
    run_filter,
)
from envisat_pose.filtering.measurements import chaser_T_m_from_state
from envisat_pose.filtering.montecarlo import MeasurementConfig, inputs_from_truth
from envisat_pose.filtering.ukf import sigma_points
from envisat_pose.geometry import load_camera
from envisat_pose.target import default_target, load_target

UPPER_STAGE = "models/upper_stage.xml"
NEES_BAND_P = (0.005, 0.995)  # two-sided 99 %


def _truth(target_file=None, duration_s=300.0, dt_s=2.0, seed=7):
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    extra = {} if target_file is None else {"target": {"file": target_file}}
    return simulate_truth(scenario_config("default", duration_s=duration_s, dt_s=dt_s, seed=seed, **extra))


@pytest.fixture(scope="module")
def envisat_truth():
    return _truth(duration_s=60.0, dt_s=1.0, seed=3)


@pytest.fixture(scope="module")
def upper_truth():
    return _truth(UPPER_STAGE)


def _filter(truth, kind, cfg, runs, seed, **kw):
    mcfg = MeasurementConfig(kind=kind, sigma_m=0.02, sigma_px=1.0)
    inp = inputs_from_truth(truth, mcfg, cfg.P0, seed=seed, n_runs=runs)
    chaser = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad,
                           truth.chaser_thetadot_rad_s)
    return inp, run_filter(inp.x0_hat, cfg.P0, truth.t_s, chaser, inp.z, inp.mask, inp.R_c, kind, cfg, **kw)


# ---------------------------------------------------------------- (a) ENVISAT unchanged

@pytest.mark.parametrize("kind, kernel", [("markers3d", "fast"), ("pixels", "fast"), ("markers3d", "reference")])
def test_envisat_with_its_target_is_the_default_filter_exactly(envisat_truth, kind, kernel):
    """target=None and target=default_target(): the same setup numbers and the same filter outputs, bit for bit."""
    cfg = FilterConfig(kernel=kernel)
    a = make_setup(cfg, kind)
    b = make_setup(cfg, kind, target=default_target())
    np.testing.assert_array_equal(a.keypoints_T_m, b.keypoints_T_m)
    np.testing.assert_array_equal(a.J_T, b.J_T)
    assert a.visibility is None and b.visibility is None  # ENVISAT keeps the box face test
    runs = 4 if kernel == "reference" else 8
    _, ra = _filter(envisat_truth, kind, cfg, runs, seed=11)
    _, rb = _filter(envisat_truth, kind, cfg, runs, seed=11, target=default_target())
    for name in ("x_hat", "P", "n_meas", "nis", "dof", "rejected", "diverged", "repaired", "r_scale", "dropped"):
        np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name), err_msg=name)


def test_the_estimate_pipeline_keeps_envisats_default_model(envisat_truth):
    from envisat_pose.pipelines.campaigns.estimate import truth_target

    assert truth_target(envisat_truth.config, "the truth") is None


# ---------------------------------------------------------------- (b) the upper stage, K = 12

def test_upper_stage_nees_is_consistent_over_50_runs(upper_truth):
    """markers3d at 0.02 m, 0.5 Hz, 50 runs (seed 0) of a 300 s upper-stage truth (seed 7): the mean NEES over the
    second half inside the two-sided 99 % chi-square band of 12 dof x 50 runs; position RMSE < 0.1 m; runs use
    more than 8 keypoints at a step (K = 12)."""
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, estimate

    assert upper_truth.corners_C_m.shape[1] == 12
    R = 50
    cfg = EstimateConfig(measurement=MeasurementConfig(kind="markers3d", sigma_m=0.02, rate_hz=0.5), runs=R, seed=0)
    a = estimate(upper_truth, cfg)
    T = len(a["t_s"])
    late = slice(T // 2, None)
    anees = nees(a["x_true"][:, late], a["x_hat"][:, late], a["P"][:, late]).mean()
    lo, hi = chi2_mean_bounds(12 * R, R, NEES_BAND_P)
    assert lo <= anees <= hi, (anees, lo, hi)
    err_m = a["x_hat"][:, late, :3] - a["x_true"][:, late, :3]
    rmse_m = float(np.sqrt(np.mean(np.sum(err_m**2, axis=-1))))
    assert np.isfinite(rmse_m) and rmse_m < 0.1, rmse_m
    assert not a["diverged"].any()
    assert a["n_meas"].max() > 8


def test_upper_stage_fast_kernel_matches_the_numpy_filter(upper_truth):
    """The fused kernels over K = 12 keypoints (and the table's visibility check before them) are the numpy
    filter's update to round-off."""
    target = load_target(UPPER_STAGE)
    res = {}
    for kernel in ("fast", "reference"):
        _, res[kernel] = _filter(upper_truth, "pixels", FilterConfig(kernel=kernel), 3, seed=4, target=target)
    np.testing.assert_allclose(res["fast"].x_hat, res["reference"].x_hat, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(res["fast"].n_meas, res["reference"].n_meas)
    np.testing.assert_array_equal(res["fast"].dropped, res["reference"].dropped)


def test_visibility_check_uses_the_targets_table_and_counts_dropped_keypoints(upper_truth):
    """A setup of the upper stage looks visibility up in its table from c_T = -Gamma rho; every keypoint measured
    while the table says hidden at the prior mean and at each of its sigma points is dropped (FilterState.dropped),
    by both kernels alike."""
    target = load_target(UPPER_STAGE)
    table = target.visibility_table()
    x = upper_truth.x[::10]
    for kernel in ("fast", "reference"):
        setup = make_setup(FilterConfig(kernel=kernel), "markers3d", target=target)
        assert setup.visibility is not None and setup.num_keypoints == 12
        np.testing.assert_array_equal(setup.predicted_visible(x), table.lookup(chaser_T_m_from_state(x)))
        P = np.broadcast_to(setup.cfg.P0 * 1e-4, (len(x), 12, 12))
        spread = sigma_points(x, P, setup.weights)  # (R, 25, 12), the mean first
        hidden = ~table.lookup(chaser_T_m_from_state(spread)).any(axis=-2)
        np.testing.assert_array_equal(setup.visible_by_prior(x, P), ~hidden)
        assert hidden.any(axis=1).all()  # some keypoint is hidden at every sample: the check has work
        R = len(x)
        state = init_state(x, P[0], 0.0, np.array([7.142e6, 0.0, 0.0, 1e-3]), setup.cfg)
        z = setup.hx(x)
        meas = Measurement(0.0, state.chaser, z, np.ones((R, 12), bool), np.broadcast_to(0.02**2 * np.eye(3), (R, 12, 3, 3)))
        out = filter_step(state, meas, setup)
        np.testing.assert_array_equal(out.dropped, hidden.sum(-1), err_msg=kernel)
        np.testing.assert_array_equal(out.n_meas + out.rejected, 12 - hidden.sum(-1), err_msg=kernel)


def test_inputs_from_truth_take_all_k_keypoints_and_max_markers_up_to_k(upper_truth):
    from envisat_pose.config import ConfigError

    P0 = FilterConfig().P0
    inp = inputs_from_truth(upper_truth, MeasurementConfig(), P0, seed=1, n_runs=2)
    assert inp.z.shape[2:] == (12, 3) and inp.mask.shape[2] == 12
    np.testing.assert_array_equal(inp.mask[0], upper_truth.visible)  # default: every visible keypoint
    three = inputs_from_truth(upper_truth, MeasurementConfig(max_markers=3), P0, seed=1, n_runs=2)
    assert three.mask.sum(-1).max() == 3
    twelve = inputs_from_truth(upper_truth, MeasurementConfig(max_markers=12), P0, seed=1, n_runs=2)
    np.testing.assert_array_equal(twelve.mask, inp.mask)
    with pytest.raises(ConfigError, match="max_markers"):
        inputs_from_truth(upper_truth, MeasurementConfig(max_markers=13), P0, seed=1, n_runs=1)


@pytest.mark.parametrize("scenario", ["default", "paper-all-0.02", "paper-all-0.2", "paper-3markers-0.02"])
def test_the_paper_cases_measure_a_targets_keypoints_not_envisats_eight(upper_truth, scenario):
    """The seed paper's "all visible markers" cases (and the default scenario) set no max_markers: every visible
    keypoint of the target, up to its K = 12 (more than 8 at some steps of this truth); the sparse case keeps 3."""
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig

    mcfg = EstimateConfig(scenario=scenario).measurement
    inp = inputs_from_truth(upper_truth, mcfg, FilterConfig().P0, seed=1, n_runs=1)
    if scenario == "paper-3markers-0.02":
        assert mcfg.max_markers == 3 and inp.mask.sum(-1).max() == 3
    else:
        assert mcfg.max_markers is None
        np.testing.assert_array_equal(inp.mask[0], upper_truth.visible)
        assert upper_truth.visible.sum(-1).max() > 8


# ---------------------------------------------------------------- (c) the measurement model, independently

def _passive_dcm_from_mrp(p):
    """R_T_from_C of the MRP p = e tan(phi / 4): cos(phi) I + (1 - cos(phi)) e e^T - sin(phi) [e x]."""
    norm = np.linalg.norm(p)
    phi = 4.0 * np.arctan(norm)
    e = p / norm
    ex = np.array([[0.0, -e[2], e[1]], [e[2], 0.0, -e[0]], [-e[1], e[0], 0.0]])
    return np.cos(phi) * np.eye(3) + (1.0 - np.cos(phi)) * np.outer(e, e) - np.sin(phi) * ex


@pytest.mark.parametrize("target_file", [UPPER_STAGE, "models/cubesat_3u.xml"])
def test_measurement_model_of_a_shipped_target_against_an_independent_computation(target_file):
    """hx of markers3d: rho + R^T v_i over the target's K keypoints (R from the MRP's Euler axis and angle);
    pixels: the pinhole of those points in the camera frame."""
    target = load_target(target_file)
    v_T = target.keypoints_T_m
    rng = np.random.default_rng(5)
    cam = load_camera()
    for _ in range(5):
        x = np.zeros(12)
        x[0:3] = [0.3, 30.0, -0.4] + rng.normal(0, 0.5, 3)
        x[6:9] = rng.normal(0, 0.3, 3)
        R = _passive_dcm_from_mrp(x[6:9])
        want_C = x[0:3] + v_T @ R  # rows: (R^T v_i)^T = v_i^T R
        for kind in ("markers3d", "pixels"):
            setup = make_setup(FilterConfig(), kind, target=target)
            got = setup.hx(x)
            assert got.shape == (target.num_keypoints, 3 if kind == "markers3d" else 2)
            if kind == "markers3d":
                np.testing.assert_allclose(got, want_C, rtol=0, atol=1e-12)
            else:
                p_K = (want_C - cam.pos_C_m) @ cam.R_K_from_C.T
                uv = cam.f_px * p_K[:, :2] / p_K[:, 2:] + np.array([cam.cu_px, cam.cv_px])
                np.testing.assert_allclose(got, uv, rtol=0, atol=1e-8)


def test_the_kernels_table_lookup_is_the_tables():
    """filtering/fast.py's O(1) lookup from the prior mean equals VisibilityTable.lookup from c_T = -Gamma rho
    (numpy's Gamma and grid) on 5,000 random states at 2-150 reaches (seed 11): the same cells, rows and ranges
    (a cell boundary met at the last bit could flip one; none is)."""
    from envisat_pose.filtering.fast import table_visible

    target = load_target(UPPER_STAGE)
    table = target.visibility_table()
    rng = np.random.default_rng(11)
    x = np.zeros((5000, 12))
    d = rng.standard_normal((5000, 3))
    x[:, :3] = d / np.linalg.norm(d, axis=1, keepdims=True) * np.exp(rng.uniform(np.log(2), np.log(150), (5000, 1)))
    x[:, :3] *= target.reach_m
    x[:, 6:9] = rng.uniform(-1, 1, (5000, 3))
    got = table_visible(x, table)
    np.testing.assert_array_equal(got, table.lookup(chaser_T_m_from_state(x)))
    assert got.shape == (5000, target.num_keypoints) and 0 < got.mean() < 1
    np.testing.assert_array_equal(table_visible(x.reshape(50, 100, 12), table), got.reshape(50, 100, -1))
