"""Relative motion and attitude on circular and strongly eccentric chaser orbits, against independent computations.

tests/datagen/test_truth_physics.py checks the truth on the default orbit (e = 0.001), where every term that grows
with the eccentricity (theta'', r', the varying LVLH rate, the Kepler solve away from E ~ M) is ~1e-3 of its
size here. The reference sheet's equations hold for any Keplerian chief (section 4; OrbitConfig accepts
0 <= e < 1 with the perigee above the Earth), so this file runs the MuJoCo truth, datagen's closed-form orbit
and the filter's RK4 model on e = 0, 0.1 and a Molniya-like e = 0.7 (through its perigee, from a true anomaly of
300 deg, where the Kepler solve starts from a negative mean anomaly) against:

- two separate inertial two-body propagations (scipy DOP853, rtol 1e-13), chaser and target, turned into LVLH
  from the chaser's own r and v (no Kepler equation, no orbit elements after t = 0);
- the target's torque-free Euler equations with quaternion kinematics (scipy), for the relative attitude.

Nothing here calls datagen.orbit, the plugin or filtering.dynamics to build a reference.
"""

import math
import os
import sys

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from orbit_elements import MU, elements_to_rv  # noqa: E402  (the tests' shared two-body reference)

from envisat_pose.attitude import mrp_error_angle_rad, mrp_shadow, mrp_to_dcm
from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.datagen.truth import simulate_truth
from envisat_pose.filtering.dynamics import propagate

J_T = np.array([[17023.3, 397.1, -2171.4], [397.1, 124825.7, 344.2], [-2171.4, 344.2, 129112.2]])

# name: (orbit overrides, duration s, rho0', m/s). The Molniya-like orbit reaches its perigee (7980 km) ~1064 s in;
# started at rest in LVLH its chaser stays 45-57 m from the target (the default drift would bring it to 19 m).
ORBITS = {
    "circular": ({"e": 0.0}, 3000.0, [0.01, -0.02, 0.005]),
    "e0.1": ({"a_m": 7500.0e3, "e": 0.1, "nu0_deg": 150.0}, 3000.0, [0.01, -0.02, 0.005]),
    "molniya": ({"a_m": 26600.0e3, "e": 0.7, "nu0_deg": 300.0}, 2400.0, [0.0, 0.0, 0.0]),
}




def two_body(t, y):
    return np.concatenate([y[3:], -MU * y[:3] / np.linalg.norm(y[:3]) ** 3])


def propagate_inertial(r0, v0, t_eval):
    sol = solve_ivp(two_body, (0, t_eval[-1]), np.concatenate([r0, v0]), method="DOP853", t_eval=t_eval,
                    rtol=1e-13, atol=1e-8)
    assert sol.success
    return sol.y[:3].T, sol.y[3:].T


def lvlh(r, v):
    """R_N_from_C (columns radial, along-track, normal), w_c in N, and the polar state (r, r', theta', theta'')
    from the inertial r and v alone: theta' = |h| / r^2, theta'' = -2 r' theta' / r (h is constant)."""
    rn = np.linalg.norm(r, axis=-1)
    x = r / rn[:, None]
    h = np.cross(r, v)
    hn = np.linalg.norm(h, axis=-1)
    z = h / hn[:, None]
    R = np.stack([x, np.cross(z, x), z], axis=-1)
    rdot = np.sum(r * v, -1) / rn
    thd = hn / rn**2
    return R, h / (rn**2)[:, None], np.stack([rn, rdot, thd, -2 * rdot * thd / rn], -1)


def euler_attitude(R_N_T0, w0_T, t_eval):
    """R_N_T(t) and w_t in T by torque-free Euler equations and quaternion kinematics (scipy, DOP853)."""
    J_inv = np.linalg.inv(J_T)

    def rhs(t, y):
        (x, yy, z, s), w = y[:4], y[4:]
        qdot = 0.5 * np.array([s * w[0] + yy * w[2] - z * w[1], s * w[1] + z * w[0] - x * w[2],
                               s * w[2] + x * w[1] - yy * w[0], -x * w[0] - yy * w[1] - z * w[2]])
        return np.concatenate([qdot, J_inv @ -np.cross(w, J_T @ w)])

    y0 = np.concatenate([Rotation.from_matrix(R_N_T0).as_quat(), w0_T])
    sol = solve_ivp(rhs, (0, t_eval[-1]), y0, method="DOP853", t_eval=t_eval, rtol=1e-13, atol=1e-15)
    return Rotation.from_quat(sol.y[:4].T).as_matrix(), sol.y[4:].T


def cfg_of(name, dt_s):
    orbit, duration, rhodot0 = ORBITS[name]
    return scenario_config(duration_s=duration, dt_s=dt_s, seed=3, orbit=orbit,
                           relative={"rho0_C_m": [3.0, 50.0, -2.0], "rhodot0_C_m_s": rhodot0})


def reference(cfg, t_s):
    """The independent relative state (rho, rho', Gamma, w_r) and the chaser's polar state along t_s."""
    o = cfg.orbit
    r_c0, v_c0 = elements_to_rv(o.a_m, o.e, o.i_deg, o.raan_deg, o.argp_deg, o.nu0_deg)
    r_c, v_c = propagate_inertial(r_c0, v_c0, t_s)
    R, w_c_N, polar = lvlh(r_c, v_c)
    rho0, rhodot0 = np.array(cfg.relative.rho0_C_m), np.array(cfg.relative.rhodot0_C_m_s)
    r_t, v_t = propagate_inertial(r_c[0] + R[0] @ rho0, v_c[0] + R[0] @ rhodot0 + np.cross(w_c_N[0], R[0] @ rho0),
                                  t_s)
    d = r_t - r_c
    rho = np.einsum("nji,nj->ni", R, d)
    rhodot = np.einsum("nji,nj->ni", R, v_t - v_c - np.cross(w_c_N, d))
    return dict(R_N_C=R, polar=polar, rho=rho, rhodot=rhodot, r_c=r_c)


@pytest.fixture(scope="module", params=list(ORBITS))
def case(request):
    cfg = cfg_of(request.param, 10.0)
    traj = simulate_truth(cfg)
    ref = reference(cfg, traj.t_s)
    R_N_T, w_t_T = euler_attitude(ref["R_N_C"][0] @ mrp_to_dcm(traj.x[0, 6:9]).T, cfg.target.w0_T_rad_s, traj.t_s)
    ref["Gamma"] = np.swapaxes(R_N_T, 1, 2) @ ref["R_N_C"]
    ref["w_r"] = w_t_T - ref["Gamma"][:, :, 2] * ref["polar"][:, 2:3]  # w_c = theta' z_C
    return request.param, cfg, traj, ref


def test_the_orbits_are_what_they_claim(case):
    """The eccentric cases do reach large theta'' and r': otherwise they would test nothing beyond e = 0.001."""
    name, cfg, _, ref = case
    rdot = ref["polar"][:, 1]
    if name == "circular":
        assert np.abs(rdot).max() < 1e-6
    else:
        assert np.abs(rdot).max() > 500.0  # m/s
    if name == "molniya":
        assert rdot.min() < -1000.0 and rdot.max() > 1000.0  # through the perigee


def test_truth_chaser_orbit_is_the_two_body_orbit(case):
    """The truth's chaser_* arrays (datagen's closed-form Kepler) against the integrated chaser. Measured at worst
    (Molniya): r 8e-6 m, r' 3.5e-8 m/s, theta' 3e-12 of itself, the reference's own floor (DOP853 at rtol 1e-13 on
    a 26600 km orbit). Bounds: r 1e-4 m, r' 2e-7 m/s, theta' 1e-10 relative, theta's advance 1e-10 rad."""
    _, _, traj, ref = case
    r, rdot, thd, _ = ref["polar"].T
    np.testing.assert_allclose(traj.chaser_r_m, r, rtol=0, atol=1e-4)
    np.testing.assert_allclose(traj.chaser_rdot_m_s, rdot, rtol=0, atol=2e-7)
    np.testing.assert_allclose(traj.chaser_thetadot_rad_s, thd, rtol=1e-10, atol=0)
    x0 = ref["r_c"][0] / r[0]
    angle = np.arctan2(np.linalg.norm(np.cross(x0, ref["r_c"]), axis=-1), ref["r_c"] @ x0)  # < pi over these spans
    turned = np.unwrap(traj.chaser_theta_rad - traj.chaser_theta_rad[0])
    assert np.ptp(angle) < math.pi
    np.testing.assert_allclose(turned, angle, rtol=0, atol=1e-10)


def test_truth_relative_translation_against_two_inertial_propagations(case):
    """MuJoCo's rho and rho' against the difference of the two propagations in LVLH. Measured at worst (Molniya)
    1.1e-6 m and 2.5e-9 m/s, the floor of differencing two separate 7000-27000 km integrations at rtol 1e-13;
    bounds 5e-6 m and 2e-8 m/s. A wrong chief position or LVLH rate costs centimetres to metres here."""
    name, _, traj, ref = case
    assert np.abs(traj.x[:, 0:3] - ref["rho"]).max() < 5e-6, name
    assert np.abs(traj.x[:, 3:6] - ref["rhodot"]).max() < 2e-8, name
    assert np.ptp(ref["rho"], axis=0).max() > 1.0  # the motion is real


def test_truth_relative_attitude_against_euler_equations(case):
    """MuJoCo's MRP and w_r against the Euler-equation target seen from the integrated LVLH frame: the LVLH
    rate and its derivative (theta'', up to ~1e-6 rad/s^2 at the Molniya perigee) enter only through the frame.
    Measured at worst 1.1e-10 deg and 1.5e-14 rad/s (MuJoCo's RK4 at 0.05 s); bounds 1e-8 deg and 1e-12 rad/s."""
    name, _, traj, ref = case
    err = np.degrees(mrp_error_angle_rad(traj.x[:, 6:9], np.array([_dcm_to_mrp(G) for G in ref["Gamma"]])))
    assert err.max() < 1e-8, (name, err.max())
    assert np.abs(traj.x[:, 9:12] - ref["w_r"]).max() < 1e-12, name


def _dcm_to_mrp(G):
    """MRP of Gamma = R_T_from_C through scipy: Gamma^T is the active rotation taking T axes into C."""
    return mrp_shadow(Rotation.from_matrix(G.T).as_mrp())


@pytest.mark.parametrize("name", list(ORBITS))
def test_filter_rk4_model_against_the_independent_reference(name):
    """The filter's RK4 at 1 s (filtering.dynamics.propagate), fed at every step with the chaser's polar state
    from the integrated chaser orbit, against the two propagations and the Euler equations. Measured at worst:
    1.2e-6 m and 2.6e-9 m/s (the reference's floor, unchanged at 0.5 s steps), 1.1e-5 deg and 2.5e-9 rad/s (RK4's
    truncation over 3000 s at 2.7 deg/s: 16x smaller at 0.5 s steps). Bounds: 5e-6 m, 2e-8 m/s, 3e-5 deg (the
    sheet: 2e-5 deg per orbit), 8e-9 rad/s."""
    cfg = cfg_of(name, 1.0)
    t = np.arange(0.0, ORBITS[name][1] + 0.5, 1.0)
    ref = reference(cfg, t)
    p0 = np.array([0.3, -0.5, 0.2])
    R_N_T, w_t_T = euler_attitude(ref["R_N_C"][0] @ mrp_to_dcm(p0).T, cfg.target.w0_T_rad_s, t)
    Gamma = np.swapaxes(R_N_T, 1, 2) @ ref["R_N_C"]
    w_r = w_t_T - Gamma[:, :, 2] * ref["polar"][:, 2:3]
    theta = np.zeros(len(t))  # the filter's model does not read theta
    c = np.stack([ref["polar"][:, 0], ref["polar"][:, 1], theta, ref["polar"][:, 2]], -1)
    x = np.concatenate([ref["rho"][0], ref["rhodot"][0], p0, w_r[0]])
    worst = np.zeros(4)
    for k in range(1, len(t)):
        x = propagate(x, c[k - 1], 1.0, J_T=J_T)
        x[6:9] = mrp_shadow(x[6:9])
        worst = np.maximum(worst, [np.abs(x[0:3] - ref["rho"][k]).max(), np.abs(x[3:6] - ref["rhodot"][k]).max(),
                                   np.degrees(mrp_error_angle_rad(x[6:9], _dcm_to_mrp(Gamma[k]))),
                                   np.abs(x[9:12] - w_r[k]).max()])
    print(name, "worst |rho|, |rho'|, attitude deg, |w_r|:", worst)
    assert worst[0] < 5e-6 and worst[1] < 2e-8, worst
    assert worst[2] < 3e-5 and worst[3] < 8e-9, worst
