"""Monte Carlo statistics against synthetic Gaussian errors with known answers, and exact block merging."""

import numpy as np
import pytest
from scipy.stats import chi2, norm

from envisat_pose.analysis.stats import (
    MAHALANOBIS_3SIGMA_3D,
    P_3SIGMA,
    CampaignSums,
    SumsFolder,
    block_error_norms,
    campaign_stats,
    campaign_summary,
    chi2_mean_bounds,
    component_cov,
    component_errors,
    concat_run_summaries,
    finalize,
    merge_sums,
    reduce_runs,
    run_summary,
    state_errors,
)
from envisat_pose.attitude import mrp_error_angle_rad, mrp_shadow

P_TRUE_MRP = np.array([0.3, -0.5, 0.6])  # |p|^2 = 0.7: an error angle of 4|dp| would be 70 % too large


def _spd(rng, scales):
    """A random SPD 12x12 covariance with correlations, standard deviations `scales` (12,)."""
    A = rng.normal(size=(12, 12))
    C = A @ A.T + 12 * np.eye(12)
    d = np.sqrt(np.diag(C))
    return C / np.outer(d, d) * np.outer(scales, scales)


def _campaign(rng, R, T, P, x_true0=None, p_scale=1.0):
    """Consistent filter: x_hat = x_true + e with e ~ N(0, P), same P for every run-step."""
    x_true = np.zeros((R, T, 12))
    x_true[..., 1] = 50.0
    x_true[..., 6:9] = P_TRUE_MRP if x_true0 is None else x_true0
    x_true[..., 9:12] = [0.01, -0.02, 0.04]
    e = rng.multivariate_normal(np.zeros(12), P, size=(R, T))
    x_hat = x_true + e
    P_rt = np.broadcast_to(P * p_scale, (R, T, 12, 12))
    return x_true, x_hat, P_rt


SCALES = np.array([0.05, 0.03, 0.08, 1e-4, 2e-4, 1e-4, 2e-4, 3e-4, 1e-4, 1e-5, 2e-5, 3e-5])


def test_sample_and_filter_3sigma_rmse_and_containment_of_a_consistent_filter():
    rng = np.random.default_rng(1)
    P = _spd(rng, SCALES)
    R, T = 4000, 2
    x_true, x_hat, Pr = _campaign(rng, R, T, P)
    st = campaign_stats(x_true, x_hat, Pr, np.zeros((R, T)), np.zeros((R, T), int), np.zeros(R, bool))
    # filter 3-sigma: deterministic, position/velocity/rate straight from P; attitude through M(p_hat) of each run
    assert np.allclose(st.filter_3sigma[:, :6], 3 * SCALES[:6], rtol=1e-12)
    assert np.allclose(st.filter_3sigma[:, 9:], 3 * SCALES[9:], rtol=1e-12)
    # the attitude as a rotation vector: its covariance is (4 / (1 + p.p))^2 x the MRP one, up to a rotation
    k = 4.0 / (1.0 + P_TRUE_MRP @ P_TRUE_MRP)
    assert st.filter_3sigma_block[0, 2] == pytest.approx(3 * k * np.sqrt(np.trace(P[6:9, 6:9])), rel=1e-3)
    # the sample 3-sigma agrees with the filter's within sampling error (std of a sample std: 1 / sqrt(2R) = 1.1 %)
    assert np.allclose(st.sample_3sigma, st.filter_3sigma, rtol=0.05)
    assert np.allclose(st.sample_3sigma_block, st.filter_3sigma_block, rtol=0.05)
    # RMSE of the block norms: sqrt(trace of the block), attitude angle with the 4 / (1 + p.p) factor
    want = np.sqrt([np.trace(P[0:3, 0:3]), np.trace(P[3:6, 3:6]), k**2 * np.trace(P[6:9, 6:9]),
                    np.trace(P[9:12, 9:12])])
    assert np.allclose(st.rmse_block, want, rtol=0.04)
    # containment: 99.73 % per component and per 3-D block (binomial sd 0.0008)
    assert np.all(np.abs(st.inside_comp - P_3SIGMA) < 0.004)
    assert np.all(np.abs(st.inside_block - P_3SIGMA) < 0.004)
    assert np.allclose(st.nees_mean, 12.0, rtol=0.03)


def test_containment_of_an_overconfident_filter_matches_the_gaussian_closed_form():
    """P reported 4x too small (sigma halved): |e| <= 3 sigma_reported is |N| <= 1.5; a 3-D block is
    chi2(3) <= 14.16 / 4."""
    rng = np.random.default_rng(2)
    P = _spd(rng, SCALES)
    R = 6000
    x_true, x_hat, Pr = _campaign(rng, R, 1, P, p_scale=0.25)
    st = campaign_stats(x_true, x_hat, Pr, np.zeros((R, 1)), np.zeros((R, 1), int), np.zeros(R, bool))
    assert np.all(np.abs(st.inside_comp - (2 * norm.cdf(1.5) - 1)) < 0.02)
    assert np.all(np.abs(st.inside_block - chi2.cdf(MAHALANOBIS_3SIGMA_3D / 4, 3)) < 0.02)
    assert np.allclose(st.nees_mean, 48.0, rtol=0.03)
    assert np.all(st.nees_mean > st.nees_bounds[1])


def test_nees_and_nis_band_coverage_over_time_is_95_percent():
    rng = np.random.default_rng(3)
    P = _spd(rng, SCALES)
    R, T = 10, 600
    x_true, x_hat, Pr = _campaign(rng, R, T, P)
    dof = 3 * rng.integers(0, 9, size=(R, T))  # 0 to 8 corners of 3 components: the dof varies per run-step
    nis = np.where(dof > 0, rng.chisquare(np.maximum(dof, 1)), 0.0)
    st = campaign_stats(x_true, x_hat, Pr, nis, dof, np.zeros(R, bool))
    inside = (st.nees_mean >= st.nees_bounds[0]) & (st.nees_mean <= st.nees_bounds[1])
    assert abs(inside.mean() - 0.95) < 0.04
    runs = (dof > 0).sum(0)
    assert np.allclose(st.nis_bounds[:, 0], chi2.ppf(0.025, dof.sum(0)) / runs)
    inside = (st.nis_mean >= st.nis_bounds[:, 0]) & (st.nis_mean <= st.nis_bounds[:, 1])
    assert abs(inside.mean() - 0.95) < 0.04
    # runs without a measurement do not count: mean over the measured ones
    assert np.allclose(st.nis_mean, nis.sum(0) / runs)


def test_chi2_mean_bounds_closed_forms():
    assert np.allclose(chi2_mean_bounds(12, 1), [4.4037885, 23.3366640])
    lo, hi = chi2_mean_bounds(12 * 50, 50)
    assert lo < 12 < hi and hi - lo < 3  # the band of the mean narrows as sqrt(2 * 12 / R)
    assert np.isnan(chi2_mean_bounds(0, 0)).all()


def test_errors_across_the_mrp_shadow_boundary_are_small():
    p_true = np.array([0.0, 0.0, 0.999])
    p_near = np.array([0.0, 0.0, 1.001])
    p_hat = -p_near / (p_near @ p_near)  # the same nearby orientation, on the short set
    x_true, x_hat = np.zeros(12), np.zeros(12)
    x_true[6:9], x_hat[6:9] = p_true, p_hat
    ang = block_error_norms(x_true, x_hat)[2]
    assert ang == pytest.approx(mrp_error_angle_rad(p_hat, p_true), abs=1e-12)
    assert ang == pytest.approx(4 * np.arctan(0.001), rel=1e-3)
    # the rotation-vector error's norm is the error angle (to first order in dp = 0.002)
    assert np.linalg.norm(component_errors(x_true, x_hat)[6:9]) == pytest.approx(ang, rel=2e-3)
    assert np.linalg.norm(state_errors(x_true, x_hat)[6:9]) < 0.003


def test_rotation_vector_covariance_is_the_error_angle_law_at_any_mrp():
    rng = np.random.default_rng(4)
    for p in (np.zeros(3), P_TRUE_MRP, mrp_shadow(np.array([0.1, 0.2, 0.97]))):
        dp = 1e-5 * rng.normal(size=(200, 3))
        x_true, x_hat = np.zeros((200, 12)), np.zeros((200, 12))
        x_true[:, 6:9], x_hat[:, 6:9] = p, p + dp
        ang = mrp_error_angle_rad(x_hat[:, 6:9], x_true[:, 6:9])
        assert np.allclose(np.linalg.norm(component_errors(x_true, x_hat)[:, 6:9], axis=-1), ang, rtol=1e-4)
        C = component_cov(np.broadcast_to(np.eye(12), (200, 12, 12)), x_hat)[:, 6:9, 6:9]
        pp_hat = np.einsum("ri,ri->r", x_hat[:, 6:9], x_hat[:, 6:9])
        want = (4 / (1 + pp_hat))[:, None, None] ** 2 * np.eye(3)  # M M^T, as B B^T = ((1 + p.p) / 4)^2 I
        assert np.allclose(C, want, rtol=0, atol=1e-12)


def _blocks(rng, R, T, cuts):
    P = _spd(rng, SCALES)
    x_true, x_hat, Pr = _campaign(rng, R, T, P)
    Pr = Pr * rng.uniform(0.5, 2.0, size=(R, T, 1, 1))
    dof = 3 * rng.integers(0, 9, size=(R, T))
    nis = np.where(dof > 0, rng.chisquare(np.maximum(dof, 1)), 0.0)
    div = rng.random(R) < 0.2
    edges = [0, *cuts, R]
    parts = [reduce_runs(x_true[a:b], x_hat[a:b], Pr[a:b], nis[a:b], dof[a:b], div[a:b], run_start=a)
             for a, b in zip(edges[:-1], edges[1:])]
    whole = reduce_runs(x_true, x_hat, Pr, nis, dof, div)
    return parts, whole


def _same_bits(a: CampaignSums, b: CampaignSums):
    assert (a.run_start, a.run_stop, a.n_runs, a.n_diverged) == (b.run_start, b.run_stop, b.n_runs, b.n_diverged)
    for k in CampaignSums.ARRAYS:
        assert np.array_equal(getattr(a, k), getattr(b, k)), k


def test_merging_blocks_in_any_order_gives_the_same_bits_and_equals_the_whole():
    rng = np.random.default_rng(5)
    parts, whole = _blocks(rng, 37, 40, [5, 6, 19, 30])
    ref = merge_sums(parts)
    for _ in range(6):
        order = rng.permutation(len(parts))
        _same_bits(merge_sums([parts[i] for i in order]), ref)
        folder = SumsFolder()
        for i in order:
            folder.add(parts[i])
        _same_bits(folder.result(), ref)
    for k in ("inside_comp", "inside_block", "nis_dof", "nis_runs"):
        assert np.array_equal(getattr(ref, k), getattr(whole, k))
    for k in ("sq_norm", "err", "sq_err", "filt_var", "nees", "nis"):
        assert np.allclose(getattr(ref, k), getattr(whole, k), rtol=1e-12, atol=0), k
    assert ref.n_diverged == whole.n_diverged and ref.n_runs == 37
    st_m, st_w = finalize(ref), finalize(whole)
    assert np.allclose(st_m.sample_3sigma, st_w.sample_3sigma, rtol=1e-9)
    _same_bits(CampaignSums.from_arrays(ref.to_arrays()), ref)


def test_a_block_counted_twice_or_missing_is_refused():
    rng = np.random.default_rng(6)
    parts, _ = _blocks(rng, 12, 5, [4, 8])
    with pytest.raises(ValueError):
        merge_sums([parts[0], parts[1], parts[1], parts[2]])
    with pytest.raises(ValueError):
        merge_sums([parts[0], parts[2]])
    folder = SumsFolder()
    folder.add(parts[2])
    folder.add(parts[0])
    assert folder.runs_folded == 4
    with pytest.raises(ValueError):
        folder.result()
    with pytest.raises(ValueError):
        folder.add(parts[0])
    folder.add(parts[1])
    assert folder.result().n_runs == 12


def test_run_summary_of_a_biased_run_and_a_consistent_one():
    rng = np.random.default_rng(7)
    T = 500
    t_s = np.arange(T, dtype=float)
    P = np.diag(SCALES**2)
    x_true, x_hat, Pr = _campaign(rng, 2, T, P)
    x_hat[1] = x_true[1]
    x_hat[1, :, 0] += 0.5  # run 1: a constant 0.5 m bias in rho_x, 10 sigma
    x_hat[1, :100, 3] += 1.0  # and a 1 m/s error before the settle time only
    dof = np.full((2, T), 24)
    dof[:, ::2] = 0
    nis = np.where(dof > 0, 24.0, 0.0)
    nis[1] = np.where(dof[1] > 0, 48.0, 0.0)
    rs = run_summary(t_s, x_true, x_hat, Pr, nis, dof, np.array([False, True]), settle_s=100.0)
    assert rs.rms_block[1, 0] == pytest.approx(0.5, rel=1e-12)
    assert rs.rms_block[1, 1] == 0.0 and rs.max_block[1, 1] == 0.0  # the early error is outside the window
    assert rs.final_block[1, 0] == pytest.approx(0.5, rel=1e-12)
    assert rs.inside_share[1, 0] == 0.0 and rs.inside_share[1, 3] == 1.0
    assert abs(rs.inside_share[0, 0] - P_3SIGMA) < 0.01
    assert rs.nis_per_dof[0] == pytest.approx(1.0) and rs.nis_per_dof[1] == pytest.approx(2.0)
    assert rs.rms_block[0, 0] == pytest.approx(np.linalg.norm(SCALES[:3]), rel=0.1)
    both = concat_run_summaries([rs, rs])
    assert both.rms_block.shape == (4, 4) and both.diverged.tolist() == [False, True, False, True]


def test_campaign_summary_counts_run_steps_after_the_settle_time():
    rng = np.random.default_rng(8)
    T, R = 300, 50
    t_s = np.arange(T, dtype=float)
    P = np.diag(SCALES**2)
    x_true, x_hat, Pr = _campaign(rng, R, T, P)
    x_hat[:, :100, 0:3] += 10.0  # far outside before t = 100 s
    s = reduce_runs(x_true, x_hat, Pr, np.zeros((R, T)), np.zeros((R, T), int), np.zeros(R, bool))
    early = campaign_summary(s, t_s, 0.0)
    late = campaign_summary(s, t_s, 100.0)
    assert early["inside_3sigma_share"]["position"] < 0.7
    assert abs(late["inside_3sigma_share"]["position"] - P_3SIGMA) < 0.003
    assert late["rmse"]["position"] == pytest.approx(np.linalg.norm(SCALES[:3]), rel=0.02)
    lo, hi = late["nees_bounds"]
    assert lo < late["nees_mean"] < hi
    # the band with one sample a run: chi2(12 R) / R's 2.5 and 97.5 % points (scipy), wider than the steps' band
    from scipy.stats import chi2

    run_lo, run_hi = late["nees_run_bounds"]
    assert run_lo == pytest.approx(chi2.ppf(0.025, 12 * R) / R, rel=1e-9)
    assert run_hi == pytest.approx(chi2.ppf(0.975, 12 * R) / R, rel=1e-9)
    assert run_lo < lo < hi < run_hi


@pytest.mark.parametrize("p_norm", [0.1, 0.8, 0.99])
def test_attitude_errors_are_the_rotation_vector_in_T_not_only_its_length(p_norm):
    """A small rotation e (in T, rad) of the estimated frame: Gamma_hat = exp(-[e x]) Gamma_true (Gamma takes C's
    components to T's), built with scipy's rotation vectors at |p| far from 0, where B(p) is far from a multiple
    of the identity: component_errors' attitude block is e itself, direction included (within the small
    angle's second order)."""
    from scipy.spatial.transform import Rotation

    from envisat_pose.attitude import dcm_to_mrp, mrp_to_dcm

    rng = np.random.default_rng(11)
    for _ in range(5):
        p = rng.normal(size=3)
        p *= p_norm / np.linalg.norm(p)
        e = rng.normal(size=3) * 1e-5
        x_true = np.zeros(12)
        x_true[6:9] = p
        x_hat = x_true.copy()
        x_hat[6:9] = dcm_to_mrp(Rotation.from_rotvec(-e).as_matrix() @ mrp_to_dcm(p))
        got = component_errors(x_true, x_hat)[6:9]
        assert np.allclose(got, e, rtol=0.0, atol=1e-3 * np.linalg.norm(e)), (got, e)
