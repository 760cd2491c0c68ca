"""PCRLB: the Kalman covariance on linear-Gaussian models, and the 3D-corner information against closed forms."""

import numpy as np
import pytest

from envisat_pose.analysis.pcrlb import (
    STATE_FD_STEP,
    block_bounds,
    efficiency,
    fd_jacobian,
    measurement_information,
    measurement_jacobians,
    pcrlb_along_truth,
    pcrlb_recursion,
    transition_jacobians,
)
from envisat_pose.attitude import dcm_to_mrp, mrp_kinematics_matrix, mrp_to_dcm, skew
from envisat_pose.geometry import load_geometry

P0 = np.diag([1.0] * 3 + [0.01**2] * 3 + [0.044**2] * 3 + [1.7e-3**2] * 3)  # reference.md, section 6
SIGMA_M = 0.02


def kalman_covariances(P0, F, Q, Hs, Rs, update_first=True):
    """Textbook Kalman covariance recursion, Joseph form; Hs[k] (m_k, n) with m_k possibly 0."""
    n = P0.shape[0]
    out, P = [], P0.copy()
    for k in range(len(Hs)):
        if k > 0:
            P = F[k - 1] @ P @ F[k - 1].T + Q[k - 1]
        if Hs[k].shape[0] and (k > 0 or update_first):
            H, R = Hs[k], Rs[k]
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            A = np.eye(n) - K @ H
            P = A @ P @ A.T + K @ R @ K.T
        out.append(P)
    return np.array(out)


def linear_model(rng, T, n=12, q_scale=1e-14):
    """Time-varying near-identity F (dt = 1 s), tiny Q, 0 to 8 measured 3-rows per step (0 at some steps)."""
    F = np.eye(n) + 0.05 * rng.normal(size=(T - 1, n, n))
    Q = q_scale * np.broadcast_to(np.diag(np.diag(P0)), (T - 1, n, n))
    Hs, Rs = [], []
    for k in range(T):
        c = 0 if k % 7 == 3 else int(rng.integers(0, 9))
        Hs.append(rng.normal(size=(3 * c, n)))
        Rs.append(np.diag(rng.uniform(0.5, 2.0, 3 * c) * SIGMA_M**2))
    info = np.array([H.T @ np.linalg.solve(R, H) if H.shape[0] else np.zeros((n, n)) for H, R in zip(Hs, Rs)])
    return F, Q, Hs, Rs, info


def rel_err(A, B):
    """Largest |A - B| normalised by sqrt(B_ii B_jj) (relative on the diagonal, correlation scale off it)."""
    d = np.sqrt(np.diagonal(B, axis1=-2, axis2=-1))
    return np.max(np.abs(A - B) / (d[..., :, None] * d[..., None, :]))


@pytest.mark.parametrize("q_scale", [1e-14, 0.0, 1e-3])
def test_the_bound_equals_the_kalman_covariance_on_a_linear_gaussian_model(q_scale):
    rng = np.random.default_rng(10)
    T = 60
    F, Q, Hs, Rs, info = linear_model(rng, T, q_scale=q_scale)
    B = pcrlb_recursion(P0, F, Q, info)
    P = kalman_covariances(P0, F, Q, Hs, Rs)
    assert rel_err(B, P) < 1e-9
    # steps without measurement: the bound grows there (a prediction only)
    assert np.all(np.trace(B[3::7], axis1=-2, axis2=-1) > 0)
    B_no_first = pcrlb_recursion(P0, F, Q, info, info_at_first=False)
    assert rel_err(B_no_first, kalman_covariances(P0, F, Q, Hs, Rs, update_first=False)) < 1e-9
    assert np.allclose(B_no_first[0], P0, rtol=1e-14)


def test_the_recursion_batches_over_leading_axes():
    rng = np.random.default_rng(11)
    models = [linear_model(rng, 20) for _ in range(2)]
    F = np.stack([m[0] for m in models])
    info = np.stack([m[4] for m in models])
    B = pcrlb_recursion(np.stack([P0, 2 * P0]), F, np.zeros((12, 12)), info)
    for i, m in enumerate(models):
        assert rel_err(B[i], kalman_covariances((1 + i) * P0, m[0], np.zeros((19, 12, 12)), m[2], m[3])) < 1e-9


def test_fd_jacobians_of_a_linear_model_and_the_whole_chain_against_kalman():
    rng = np.random.default_rng(12)
    T = 30
    A = np.eye(12) + 0.05 * rng.normal(size=(T - 1, 12, 12))
    Hm = rng.normal(size=(8, 3, 12))
    x_true = rng.normal(size=(T, 12))
    fx = lambda X: np.einsum("kij,ksj->ksi", A, X)  # noqa: E731  row k: step k -> k+1
    hx = lambda X: np.einsum("cmj,ksj->kscm", Hm, X)  # noqa: E731
    F = transition_jacobians(fx, x_true, STATE_FD_STEP, align=None)
    assert np.allclose(F, A, rtol=0, atol=1e-8)
    H = measurement_jacobians(hx, x_true)
    assert H.shape == (T, 8, 3, 12) and np.allclose(H, Hm, rtol=0, atol=1e-8)
    measured = rng.random((T, 8)) < 0.5
    measured[5] = False
    Q = 1e-12 * np.eye(12)
    B = pcrlb_along_truth(fx, hx, x_true, measured, SIGMA_M**2 * np.eye(3), P0, Q, align=None)
    Hs = [Hm[measured[k]].reshape(-1, 12) for k in range(T)]
    Rs = [SIGMA_M**2 * np.eye(H.shape[0]) for H in Hs]
    assert rel_err(B, kalman_covariances(P0, A, np.broadcast_to(Q, (T - 1, 12, 12)), Hs, Rs)) < 1e-6


def corners_hx(X):
    """The paper's 3D-corner model z_i = rho + Gamma(p)^T v_i, written with the core. (..., 12) -> (..., 8, 3)."""
    v = load_geometry().corners_T_m
    return X[..., None, 0:3] + v @ mrp_to_dcm(X[..., 6:9])  # (Gamma^T v)_j = sum_i Gamma_ij v_i


def state_at(p):
    x = np.zeros(12)
    x[0:3] = [0.3, 50.0, -0.2]
    x[3:6] = [1e-3, 0.0, 2e-4]
    x[6:9] = p
    x[9:12] = [0.004, -0.007, 0.035]
    return x


def analytic_corner_jacobian(x):
    """d z_i / dx: identity in rho, -Gamma^T [v_i x] B(p)^-1 in p (Gamma' = -[w x] Gamma, p' = B(p) w), 0 else."""
    v = load_geometry().corners_T_m
    G = mrp_to_dcm(x[6:9])
    B_inv = np.linalg.inv(mrp_kinematics_matrix(x[6:9]))
    H = np.zeros((8, 3, 12))
    H[:, :, 0:3] = np.eye(3)
    H[:, :, 6:9] = -G.T @ skew(v) @ B_inv
    return H


@pytest.mark.parametrize("p", [[0.0, 0.0, 0.0], [0.2, -0.4, 0.5], [0.55, 0.5, -0.6]])
def test_corner_jacobian_and_information_match_the_analytic_derivative(p):
    x = state_at(np.array(p))
    H = measurement_jacobians(corners_hx, x[None])[0]
    H_ref = analytic_corner_jacobian(x)
    assert np.max(np.abs(H - H_ref)) < 1e-8 * np.max(np.abs(H_ref))
    R = SIGMA_M**2 * np.eye(3)
    info = measurement_information(H[None], np.ones((1, 8), bool), R)[0]
    info_ref = sum(Hi.T @ Hi for Hi in H_ref) / SIGMA_M**2
    assert np.max(np.abs(info - info_ref)) < 1e-8 * np.max(np.abs(info_ref))
    assert np.allclose(info[0:3, 0:3], 8 / SIGMA_M**2 * np.eye(3), rtol=1e-9)
    # corners about the centre of mass: no position-attitude coupling with all eight
    assert np.max(np.abs(info[0:3, 6:9])) < 1e-6 * info[0, 0]


def one_step(x, measured, P0_):
    """F = I, Q = 0, no update at t_0, the corners `measured` at t_1: the bound at t_1."""
    x_true = np.stack([x, x])
    H = measurement_jacobians(corners_hx, x_true)
    info = measurement_information(H, np.stack([np.zeros(8, bool), measured]), SIGMA_M**2 * np.eye(3))
    return pcrlb_recursion(P0_, np.eye(12)[None], np.zeros((12, 12)), info, info_at_first=False)[1]


def test_one_step_position_bound_is_sigma_over_sqrt_8():
    x = state_at(np.array([0.2, -0.4, 0.5]))
    B = one_step(x, np.ones(8, bool), P0)
    assert np.allclose(np.diag(B)[0:3], 1.0 / (1.0 / P0[0, 0] + 8 / SIGMA_M**2), rtol=1e-9)
    flat = P0.copy()
    flat[0:3, 0:3] *= 1e10  # no prior on the position: the average of 8 corners
    B = one_step(x, np.ones(8, bool), flat)
    assert np.allclose(np.sqrt(np.diag(B)[0:3]), SIGMA_M / np.sqrt(8), rtol=1e-9)
    assert block_bounds(B, x)[0] == pytest.approx(np.sqrt(3) * SIGMA_M / np.sqrt(8), rel=1e-9)
    # the attitude block: P0^-1 + M^T (sum [v x]^T [v x]) M / sigma^2, M = B(p)^-1 (independent closed form)
    v = load_geometry().corners_T_m
    M = np.linalg.inv(mrp_kinematics_matrix(x[6:9]))
    J_att = np.linalg.inv(P0[6:9, 6:9]) + M.T @ sum(skew(vi).T @ skew(vi) for vi in v) @ M / SIGMA_M**2
    assert rel_err(B[6:9, 6:9], np.linalg.inv(J_att)) < 1e-8
    # velocity and rate: unobserved in one step, the prior stays
    assert np.allclose(np.diag(B)[3:6], np.diag(P0)[3:6], rtol=1e-9)


def test_one_face_couples_position_and_attitude_like_a_dense_inverse():
    x = state_at(np.array([0.1, 0.3, -0.2]))
    face = load_geometry().corners_T_m[:, 0] > 0  # A, B, C, D: the +x face only
    B = one_step(x, face, P0)
    H = analytic_corner_jacobian(x)[face].reshape(-1, 12)
    B_dense = np.linalg.inv(np.linalg.inv(P0) + H.T @ H / SIGMA_M**2)
    assert rel_err(B, B_dense) < 1e-8
    assert np.all(np.diag(B)[0:3] > 1.0 / (1.0 / P0[0, 0] + 4 / SIGMA_M**2) * (1 + 1e-6))


def rotate_about_z(X, angle_rad=np.radians(10.0)):
    """Toy dynamics: T turns by angle_rad about C's z per step, the other states stay; MRP on |p| <= 1."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])  # R_C_from_T picks up a turn about z_C
    Y = np.array(X, copy=True)
    Y[..., 6:9] = dcm_to_mrp(np.swapaxes(Rz @ np.swapaxes(mrp_to_dcm(X[..., 6:9]), -1, -2), -1, -2))
    return Y


def test_transition_jacobian_across_the_shadow_switch_is_continuous():
    """The step lands at 180 deg (|p| = 1), where stencil points fall on either set: aligned to the truth's
    set, F stays O(1) and equals F a hair before the switch."""
    p0 = np.array([0.0, 0.0, np.tan(np.radians(170.0) / 4)])
    xs = [state_at(p0 * (1 + d)) for d in (0.0, -1e-5)]
    F = [transition_jacobians(lambda X: rotate_about_z(X[0])[None], np.stack([x, rotate_about_z(x)]))[0]
         for x in xs]
    assert np.max(np.abs(F[0])) < 10
    assert np.allclose(F[0], F[1], atol=1e-3)
    unaligned = transition_jacobians(lambda X: rotate_about_z(X[0])[None], np.stack([xs[0], rotate_about_z(xs[0])]),
                                     align=None)[0]
    assert np.max(np.abs(unaligned)) > 1e3  # what the alignment prevents


def test_attitude_bound_uses_the_mrp_angle_scale_and_efficiency_is_a_ratio():
    B = np.diag([1e-4] * 3 + [1e-6] * 3 + [1e-6] * 3 + [1e-8] * 3)
    x = state_at(np.array([0.6, 0.0, 0.0]))
    b = block_bounds(B, x)
    assert b[2] == pytest.approx(4 / 1.36 * np.sqrt(3e-6), rel=1e-12)
    assert b[0] == pytest.approx(np.sqrt(3e-4), rel=1e-12)
    t_s = np.arange(10.0)
    bound = np.tile(b, (10, 1))
    rmse = bound * np.array([1.0, 1.1, 2.0, 1.0])
    rmse[:3] *= 100  # before convergence: left out by settle_s
    assert np.allclose(efficiency(rmse, bound, t_s, settle_s=3.0), [1.0, 1.1, 2.0, 1.0])


def test_fd_jacobian_shapes_and_accuracy_on_a_nonlinear_function():
    rng = np.random.default_rng(13)
    x = rng.normal(size=(4, 5, 3))
    f = lambda X: np.stack([np.sin(X[..., 0]) * X[..., 1], np.exp(X[..., 2])], axis=-1)  # noqa: E731
    J = fd_jacobian(f, x, 1e-5)
    assert J.shape == (4, 5, 2, 3)
    ref = np.zeros((4, 5, 2, 3))
    ref[..., 0, 0] = np.cos(x[..., 0]) * x[..., 1]
    ref[..., 0, 1] = np.sin(x[..., 0])
    ref[..., 1, 2] = np.exp(x[..., 2])
    assert np.allclose(J, ref, rtol=1e-8, atol=1e-9)
