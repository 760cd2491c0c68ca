"""The batched UKF's core against closed forms: a linear-Gaussian model must give the Kalman filter exactly,
covariance repair keeps a broken covariance usable, and the shadow-set hooks keep the orientation."""

import numpy as np

from envisat_pose.attitude import mrp_error_angle_rad, mrp_shadow, mrp_to_dcm
from envisat_pose.filtering.ukf import (
    align_mrp,
    merwe_weights,
    repair_cov,
    shadow_switch,
    sigma_points,
    state_mean,
    state_residual,
    ut_predict,
    ut_update,
)


def _kf_predict(x, P, F, Q):
    return F @ x, F @ P @ F.T + Q


def _kf_update(x, P, z, H, R):
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    return x + K @ (z - H @ x), (np.eye(len(x)) - K @ H) @ P @ (np.eye(len(x)) - K @ H).T + K @ R @ K.T


def test_linear_gaussian_equals_closed_form_kalman_filter():
    """Constant-velocity 2D target, 4 runs at once, position measured with a varying mask, 50 steps."""
    rng = np.random.default_rng(7)
    n, dt = 4, 1.0
    F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    Q = np.diag([1e-3, 2e-3, 1e-4, 3e-4])
    H = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [1, 1, 0, 0.0]])
    Rm = np.diag([0.04, 0.09, 0.05])
    R = 4
    for alpha, beta, kappa in ((1.0, 2.0, 0.0), (0.5, 2.0, 1.0)):
        w = merwe_weights(n, alpha, beta, kappa)
        x_b = rng.standard_normal((R, n))
        P_b = np.broadcast_to(np.diag([1.0, 2.0, 0.5, 0.3]), (R, n, n)).copy()
        x_k, P_k = x_b.copy(), P_b.copy()
        for k in range(50):
            x_b, P_b = ut_predict(x_b, P_b, lambda s: s @ F.T, Q, w)
            z = rng.standard_normal((R, 3)) * 3
            mask = rng.random((R, 3)) < 0.7
            x_b, P_b, nis, *_ = ut_update(x_b, P_b, z, mask, np.broadcast_to(Rm, (R, 3, 3)), lambda s: s @ H.T, w)
            for r in range(R):
                x_k[r], P_k[r] = _kf_predict(x_k[r], P_k[r], F, Q)
                if mask[r].any():
                    Hm, Rr = H[mask[r]], Rm[np.ix_(mask[r], mask[r])]
                    S = Hm @ P_k[r] @ Hm.T + Rr
                    y = z[r, mask[r]] - Hm @ x_k[r]
                    np.testing.assert_allclose(nis[r], y @ np.linalg.solve(S, y), rtol=1e-9)
                    x_k[r], P_k[r] = _kf_update(x_k[r], P_k[r], z[r, mask[r]], Hm, Rr)
                else:
                    assert nis[r] == 0.0
            np.testing.assert_allclose(x_b, x_k, rtol=0, atol=1e-9)
            np.testing.assert_allclose(P_b, P_k, rtol=0, atol=1e-9)


def test_repair_makes_a_broken_covariance_positive_definite():
    A = np.diag([1.0, 1e-3, -1e-4, 2.0])
    A[0, 1] = A[1, 0] = 0.3
    good = np.eye(4)
    fixed, bad = repair_cov(np.stack([A, good]))
    assert bad.tolist() == [True, False]
    np.linalg.cholesky(fixed)  # no exception
    np.testing.assert_array_equal(fixed[1], good)
    # sigma points from a non-PD covariance do not raise and stay finite
    sig = sigma_points(np.zeros(4), A, merwe_weights(4))
    assert np.isfinite(sig).all()


def test_shadow_hooks_keep_the_orientation():
    rng = np.random.default_rng(3)
    p = rng.standard_normal((200, 3))
    p *= (0.9 + 0.2 * rng.random((200, 1))) / np.linalg.norm(p, axis=1, keepdims=True)  # around |p| = 1
    ref = p + 1e-3 * rng.standard_normal((200, 3))
    ps = -p / np.sum(p * p, axis=1, keepdims=True)
    for q in (align_mrp(p, ref), align_mrp(ps, ref)):
        np.testing.assert_allclose(q, p, atol=1e-12)       # both sets end on the reference's set
    assert np.max(mrp_error_angle_rad(ps, p)) < 1e-7          # the shadow is the same orientation
    # sigma points straddling |p| = 1: the mean is the orientation in the middle, on |p| <= 1
    p_mid = np.array([0.0, 0.0, 1.0])
    sig = np.zeros((5, 12))
    for i, d in enumerate([0.0, 0.05, -0.05, 0.08, -0.08]):
        sig[i, 6:9] = p_mid * (1 + d)
    sig[1:, 6:9] = np.where(np.linalg.norm(sig[1:, 6:9], axis=1, keepdims=True) > 1, mrp_shadow(sig[1:, 6:9]),
                            sig[1:, 6:9])
    W = np.full(5, 0.25)
    W[0] = 0.0
    m = state_mean(sig, W)
    assert np.linalg.norm(m[6:9]) <= 1.0
    assert np.degrees(mrp_error_angle_rad(m[6:9], p_mid)) < 0.05  # a plain average would be ~180 deg off
    r = state_residual(sig, m[None])
    assert np.abs(r[:, 6:9]).max() < 0.1


def test_shadow_switch_maps_the_covariance_to_first_order():
    """Sample the posterior on one set, map the samples to the shadow set: their covariance is S P S^T."""
    rng = np.random.default_rng(5)
    mean = np.zeros(12)
    mean[6:9] = [0.7, -0.6, 0.5]  # |p| > 1
    A = rng.standard_normal((12, 12))
    P = 1e-8 * (A @ A.T + np.eye(12))
    m2, P2 = shadow_switch(mean, P)
    assert np.linalg.norm(m2[6:9]) < 1.0
    np.testing.assert_allclose(mrp_to_dcm(m2[6:9]), mrp_to_dcm(mean[6:9]), atol=1e-12)
    samples = rng.multivariate_normal(mean, P, size=200000)
    samples[:, 6:9] = mrp_shadow(samples[:, 6:9])
    emp = np.cov(samples.T)
    np.testing.assert_allclose(emp, P2, atol=3e-2 * np.abs(P2).max())
    np.testing.assert_array_equal(P2[:6, :6], P[:6, :6])


def test_the_gate_keeps_a_corner_just_inside_its_bound_and_drops_one_just_outside():
    """Three corners of 2 components with a correlated block S_cc each (and cross terms between corners, which
    the per-corner test ignores): innovations scaled so that y^T S_cc^-1 y is 0.99, 1.01 and 0.5 times the 2-dof
    chi-square bound at 1 - 1e-5 (computed here by Cholesky, not by the gate's solve); the second corner is
    dropped, a corner not measured stays out, NaN fails."""
    from scipy.stats import chi2

    from envisat_pose.filtering.ukf import gate_corners

    thr = chi2.ppf(1 - 1e-5, 2)
    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 6))
    S = A @ A.T + 6 * np.eye(6)
    y = np.empty(6)
    for c, share in enumerate((0.99, 1.01, 0.5)):
        Scc = S[2 * c:2 * c + 2, 2 * c:2 * c + 2]
        u = rng.normal(size=2)
        v = np.linalg.cholesky(Scc) @ u  # v^T Scc^-1 v = u.u
        y[2 * c:2 * c + 2] = v * np.sqrt(share * thr / (u @ u))
    mask = np.ones(6, bool)
    assert gate_corners(y, S, mask, 2, thr).tolist() == [True, True, False, False, True, True]
    mask[4:] = False
    assert gate_corners(y, S, mask, 2, thr).tolist() == [True, True, False, False, False, False]
    y[0] = np.nan
    assert gate_corners(y, S, np.ones(6, bool), 2, thr)[:2].tolist() == [False, False]
