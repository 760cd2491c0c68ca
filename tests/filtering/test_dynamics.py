"""The filter's RK4 model against independent computations: inertial two-body propagation and target Euler
equations (scipy, DOP853), and the MuJoCo truth simulator (another implementation of the same physics)."""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from envisat_pose.attitude import dcm_to_mrp, mrp_error_angle_rad, mrp_shadow
from envisat_pose.filtering.dynamics import (
    MAX_TURN_PER_RK4_STEP_RAD,
    load_inertia_T_kg_m2,
    propagate,
    rk4_step_s,
    rotation_rate,
    translation_rate,
)

MU = 3.986004418e14
SHEET_J = np.array([[17023.3, 397.1, -2171.4], [397.1, 124825.7, 344.2], [-2171.4, 344.2, 129112.2]])


def test_inertia_comes_from_the_mjcf_and_matches_the_sheet():
    J = load_inertia_T_kg_m2()
    np.testing.assert_array_equal(J, SHEET_J)
    np.testing.assert_allclose(np.linalg.eigvalsh(J), [16979.7, 124801.2, 129180.3], atol=0.1)


def _two_body(t, s):
    r = s[:3]
    return np.concatenate([s[3:], -MU * r / np.linalg.norm(r) ** 3])


def _inertial_reference(duration_s, period_s=134.74):
    """Chaser and target propagated separately in an inertial frame; attitude by Euler's equations (the target
    spinning at 2 pi / period_s about the reference sheet's axis)."""
    a, e, nu = 7142.0e3, 0.001, math.radians(30.0)
    p = a * (1 - e**2)
    r0 = p / (1 + e * math.cos(nu))
    rdot0 = math.sqrt(MU / p) * e * math.sin(nu)
    thdot0 = math.sqrt(MU * p) / r0**2
    r_c = np.array([r0, 0.0, 0.0])
    v_c = np.array([rdot0, r0 * thdot0, 0.0])  # theta0 = 0: C axes = N axes at t = 0
    rho0, rhodot0 = np.array([3.0, 50.0, -2.0]), np.array([0.01, -0.02, 0.005])
    w_c = np.array([0.0, 0.0, thdot0])
    r_t, v_t = r_c + rho0, v_c + rhodot0 + np.cross(w_c, rho0)
    t_eval = np.arange(0.0, duration_s + 0.5, 1.0)
    kw = dict(method="DOP853", rtol=1e-13, atol=1e-10, t_eval=t_eval)
    sc = solve_ivp(_two_body, (0, duration_s), np.concatenate([r_c, v_c]), **kw).y.T
    st = solve_ivp(_two_body, (0, duration_s), np.concatenate([r_t, v_t]), **kw).y.T
    # target attitude: q_N_T (scipy x,y,z,w) and w_t in T
    J = SHEET_J
    p0 = np.array([0.3, -0.5, 0.2])
    G0 = Rotation.from_mrp(p0).as_matrix().T  # any orientation; Gamma0 = R_T_from_C with C = N at t = 0
    w_t0 = 2 * math.pi / period_s * np.array([0.12, -0.2, 1.0]) / np.linalg.norm([0.12, -0.2, 1.0])

    def euler(t, s):
        q, w = s[:4], s[4:]
        wq = np.array([w[0], w[1], w[2], 0.0])
        qdot = 0.5 * np.array([  # q * (w, 0), scalar last
            q[3] * wq[0] + q[1] * wq[2] - q[2] * wq[1],
            q[3] * wq[1] + q[2] * wq[0] - q[0] * wq[2],
            q[3] * wq[2] + q[0] * wq[1] - q[1] * wq[0],
            -q[0] * wq[0] - q[1] * wq[1] - q[2] * wq[2],
        ])
        return np.concatenate([qdot, np.linalg.solve(J, -np.cross(w, J @ w))])

    q0 = Rotation.from_matrix(G0.T).as_quat()  # R_N_T
    sa = solve_ivp(euler, (0, duration_s), np.concatenate([q0, w_t0]), **kw).y.T
    out = []
    for k in range(len(t_eval)):
        rc, vc = sc[k, :3], sc[k, 3:]
        r = np.linalg.norm(rc)
        th = math.atan2(rc[1], rc[0])
        e_r = rc / r
        e_z = np.array([0.0, 0.0, 1.0])
        R_N_C = np.stack([e_r, np.cross(e_z, e_r), e_z], axis=1)
        rdot = vc @ e_r
        thdot = (vc @ R_N_C[:, 1]) / r
        rho = R_N_C.T @ (st[k, :3] - rc)
        wc = np.array([0.0, 0.0, thdot])
        rhodot = R_N_C.T @ (st[k, 3:] - vc) - np.cross(wc, rho)
        R_N_T = Rotation.from_quat(sa[k, :4]).as_matrix()
        G = R_N_T.T @ R_N_C
        w_r = sa[k, 4:] - G @ wc
        x = np.concatenate([rho, rhodot, dcm_to_mrp(G), w_r])
        out.append((x, np.array([r, rdot, th, thdot])))
    return t_eval, np.array([o[0] for o in out]), np.array([o[1] for o in out])


def test_rk4_model_matches_inertial_two_body_and_euler_equations():
    t, x_ref, c_ref = _inertial_reference(1200.0)
    x = x_ref[0].copy()
    max_pos, max_ang = 0.0, 0.0
    for k in range(1, len(t)):
        x = propagate(x, c_ref[k - 1], 1.0)
        x[6:9] = mrp_shadow(x[6:9])
        max_pos = max(max_pos, np.abs(x[:3] - x_ref[k, :3]).max())
        max_ang = max(max_ang, float(mrp_error_angle_rad(x[6:9], x_ref[k, 6:9])))
    assert max_pos < 1e-6, max_pos                       # m, over 1200 s at 50 m
    assert np.degrees(max_ang) < 1e-4, np.degrees(max_ang)  # the sheet: RK4 at 1 s within 2e-5 deg per orbit
    np.testing.assert_allclose(x[9:], x_ref[-1, 9:], atol=1e-9)
    np.testing.assert_allclose(x[3:6], x_ref[-1, 3:6], atol=1e-8)


def test_a_fast_tumble_is_propagated_in_sub_steps_short_enough_for_it():
    """An 8 s tumble (0.79 rad/s) in the filter's 1 s steps: the step bound (dynamics.rk4_step_s, at most 0.2 rad a
    sub-step) keeps the attitude within 5e-3 deg of scipy's Euler equations over 120 s; RK4 over whole 1 s steps
    is off by more than a hundred times that (what made the filter over-confident on such a tumble)."""
    t, x_ref, c_ref = _inertial_reference(120.0, period_s=8.0)
    w = float(np.linalg.norm(x_ref[0, 9:]))
    assert rk4_step_s(1.0, w) == pytest.approx(MAX_TURN_PER_RK4_STEP_RAD / w) and rk4_step_s(1.0, 0.05) == 1.0
    errors = {}
    for name, step in (("bounded", rk4_step_s(1.0, w)), ("whole", 1.0)):
        x, worst = x_ref[0].copy(), 0.0
        for k in range(1, len(t)):
            x = propagate(x, c_ref[k - 1], 1.0, max_step_s=step)
            x[6:9] = mrp_shadow(x[6:9])
            worst = max(worst, float(mrp_error_angle_rad(x[6:9], x_ref[k, 6:9])))
        errors[name] = np.degrees(worst)
    assert errors["bounded"] < 5e-3 and errors["whole"] > 100 * errors["bounded"], errors  # 0.0018, 0.68 deg here


def test_rk4_model_follows_the_mujoco_truth(truth_600, chaser_of):
    tr = truth_600
    c = chaser_of(tr)
    x = tr.x[0].copy()
    for k in range(1, len(tr.t_s)):
        x = propagate(x, c[k - 1], 1.0)
        x[6:9] = mrp_shadow(x[6:9])
    assert np.abs(x[:6] - tr.x[-1, :6]).max() < 1e-6
    assert np.degrees(mrp_error_angle_rad(x[6:9], tr.x[-1, 6:9])) < 1e-4
    assert np.abs(x[9:] - tr.x[-1, 9:]).max() < 1e-9


def test_blocks_are_decoupled_and_batched():
    rng = np.random.default_rng(0)
    c = np.array([7.14e6, 7.0, 0.3, 1.046e-3])
    x = np.concatenate([[1.0, 50.0, -2.0, 0.01, 0.0, 0.02], [0.2, -0.4, 0.1, 0.01, -0.02, 0.04]])
    xb = x + 0.1 * rng.standard_normal((3, 5, 12))
    out = propagate(xb, c, 1.0)
    for i in range(3):
        for j in range(5):
            np.testing.assert_allclose(out[i, j], propagate(xb[i, j], c, 1.0), rtol=0, atol=1e-12)
    # translation does not see attitude, and the other way round
    x2 = x.copy()
    x2[6:] += 0.3
    np.testing.assert_array_equal(translation_rate(x[:6], c), translation_rate(x2[:6], c))
    x3 = x.copy()
    x3[:6] += 5.0
    np.testing.assert_array_equal(rotation_rate(x[6:], c, SHEET_J), rotation_rate(x3[6:], c, SHEET_J))


def test_long_steps_use_substeps_and_pass_through_a_full_turn(truth_600, chaser_of):
    """A 100 s step (0.01 Hz) turns the target by ~270 deg: sub-steps of 1 s and set switches in between keep
    it equal to 100 steps of 1 s."""
    tr = truth_600
    c = chaser_of(tr)
    x_long = propagate(tr.x[0], c[0], 100.0, max_step_s=1.0)
    x = tr.x[0].copy()
    for k in range(100):
        x = propagate(x, c[k], 1.0)
        x[6:9] = mrp_shadow(x[6:9])
    assert np.isfinite(x_long).all()
    assert np.abs(x_long[:6] - x[:6]).max() < 1e-5  # the chaser is re-read every 1 s in the loop, not in x_long
    assert np.degrees(mrp_error_angle_rad(x_long[6:9], x[6:9])) < 1e-6
    assert np.degrees(mrp_error_angle_rad(x_long[6:9], tr.x[100, 6:9])) < 1e-4


def _point_mass_torque_T(R_T_m, J, mu=MU):
    """Exact gravity torque about the CoM, in T, on six point masses that have J's second moments (two on each
    principal axis, at +-d), at R_T from the Earth's centre: sum s_i x F_i. Independent of the 1/R^5 formula."""
    I, V = np.linalg.eigh(J)
    second = 0.5 * I.sum() - I  # sum m d^2 along each principal axis gives J
    m = 1000.0
    tau = np.zeros(3)
    for k in range(3):
        d = math.sqrt(second[k] / m)
        for sign in (1.0, -1.0):
            s = sign * d * V[:, k]
            tau += np.cross(s, -mu * 0.5 * m * (R_T_m + s) / np.linalg.norm(R_T_m + s) ** 3)
    return tau


def test_gravity_gradient_torque_equals_the_point_mass_sum():
    from envisat_pose.filtering.dynamics import gravity_gradient_torque_T

    rng = np.random.default_rng(4)
    c = np.array([7.14e6, 7.0, 0.3, 1.046e-3])
    for _ in range(5):
        p = rng.uniform(-0.6, 0.6, 3)
        rho = rng.uniform(-60.0, 60.0, 3)
        Gamma = Rotation.from_mrp(p).as_matrix().T  # R_T_from_C
        R_T = Gamma @ (np.array([c[0], 0.0, 0.0]) + rho)
        ref = _point_mass_torque_T(R_T, SHEET_J)
        tau = gravity_gradient_torque_T(rho, p, c, SHEET_J)
        assert np.linalg.norm(ref) > 1e-3  # N m: a real torque, not zero = zero
        np.testing.assert_allclose(tau, ref, rtol=0, atol=1e-7 * np.linalg.norm(ref))
    # batched over runs x sigma points, chaser broadcast
    ps, rhos = rng.uniform(-0.5, 0.5, (2, 4, 3)), rng.uniform(-50, 50, (2, 4, 3))
    out = gravity_gradient_torque_T(rhos, ps, c, SHEET_J)
    assert out.shape == (2, 4, 3)
    np.testing.assert_allclose(out[1, 2], gravity_gradient_torque_T(rhos[1, 2], ps[1, 2], c, SHEET_J), rtol=1e-14)


def test_gravity_gradient_model_follows_the_mujoco_truth_with_the_torque(chaser_of):
    """The MuJoCo plugin's torque (truth) and the filter's model: 600 s of RK4 at 1 s agree; torque-free does not."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    tr = simulate_truth(scenario_config("gravity-gradient", duration_s=600.0, seed=5))
    c = chaser_of(tr)
    err = {}
    for gg in (False, True):
        x = tr.x[0].copy()
        for k in range(1, len(tr.t_s)):
            x = propagate(x, c[k - 1], 1.0, gravity_gradient=gg)
            x[6:9] = mrp_shadow(x[6:9])
        err[gg] = (np.abs(x[9:] - tr.x[-1, 9:]).max(), np.degrees(mrp_error_angle_rad(x[6:9], tr.x[-1, 6:9])))
        assert np.abs(x[:6] - tr.x[-1, :6]).max() < 1e-6
    print("w_r error, attitude error (deg) without / with the torque:", err)
    assert err[True][0] < 1e-9 and err[True][1] < 1e-4
    assert err[False][0] > 1e-6  # the torque matters at this accuracy


def test_propagate_without_the_torque_is_unchanged_and_with_it_one_coupled_step():
    c = np.array([7.14e6, 7.0, 0.3, 1.046e-3])
    x = np.concatenate([[1.0, 50.0, -2.0, 0.01, 0.0, 0.02], [0.2, -0.4, 0.1, 0.01, -0.02, 0.04]])
    np.testing.assert_array_equal(propagate(x, c, 1.0), propagate(x, c, 1.0, gravity_gradient=False))
    # with the torque, moving rho changes the rotation (the blocks couple)
    x2 = x.copy()
    x2[0] += 30.0
    a, b = propagate(x, c, 1.0, gravity_gradient=True), propagate(x2, c, 1.0, gravity_gradient=True)
    assert np.abs(a[9:] - b[9:]).max() > 0
