"""The screw chart of the sigma points (FilterConfig.sigma_chart = "screw", filtering.screw_chart).

Two markers on a line that misses the centre of mass leave one pose direction unmeasured: the turn about that
line, a screw motion of the body (its centre of mass moves, the markers do not). The rotation chart composes the
attitude but adds the position and velocity in C, so that turn is a curve in its coordinates, and every update,
relinearized at a new mean, reads the curve as information (ENVISAT not tumbling, markers A and B, 20 runs,
1200 s: mean NEES 2642, the additive chart 24118). The screw chart takes the position and velocity errors as a
twist in the body: the turn about any body line, with the body's motion relative to C kept, is a straight line.
"""

import numpy as np

from envisat_pose.attitude import mrp_compose, mrp_to_dcm
from envisat_pose.filtering.screw_chart import rotvec_from_chart_mrp, screw_local, screw_retract, screw_transport
from envisat_pose.filtering.ukf import chart_local, chart_retract
from envisat_pose.state import MRP, POS, RATE, VEL
from envisat_pose.target import load_target


def _states(rng, n=200):
    return np.concatenate([rng.normal(size=(n, 3)) * 20.0, rng.normal(size=(n, 3)) * 0.01,
                           rng.uniform(-0.6, 0.6, size=(n, 3)), rng.normal(size=(n, 3)) * 0.05], axis=-1)


def test_screw_chart_inverts_and_is_the_additive_chart_to_first_order():
    """screw_local(screw_retract(m, D), m) = D to 1e-12 for error rotations up to 180 deg (past it the local chart
    takes the smaller turn), and d screw_retract / dD = I at D = 0."""
    rng = np.random.default_rng(1)
    m = _states(rng, 50)
    D = rng.normal(size=(50, 25, 12)) * np.r_[[1.0] * 3, [0.01] * 3, [0.3] * 3, [3e-3] * 3]
    angle = np.linalg.norm(rotvec_from_chart_mrp(np.broadcast_to(m[:, None, MRP], D[..., MRP].shape), D[..., MRP]),
                           axis=-1)
    assert angle.max() > 2.0 and (angle < np.pi).mean() > 0.9
    back = screw_local(screw_retract(m, D), m)
    np.testing.assert_allclose(back[angle < np.pi], D[angle < np.pi], atol=1e-12)
    eps = 1e-7
    np.testing.assert_allclose((screw_retract(m, eps * D) - m[:, None]) / eps, D, atol=1e-5)


def _turned_about_line(x, c1_T_m, c2_T_m, angle_rad):
    """x with the body turned by angle_rad about the body line through c1 and c2 (T, m), the points on it staying
    where they are in C and moving as they did, the body's motion relative to C kept (w_r's components turned):
    an independent construction from the state's definitions (rho + Gamma^T r_T is a body point in C, its velocity
    in C rho' + (Gamma^T w_r) x Gamma^T r_T)."""
    u = (c2_T_m - c1_T_m) / np.linalg.norm(c2_T_m - c1_T_m)
    a = np.tan(angle_rad / 4.0) * u
    G = mrp_to_dcm(x[MRP])
    X = x.copy()
    X[MRP] = mrp_compose(a, x[MRP])
    X[RATE] = mrp_to_dcm(a) @ x[RATE]
    X[POS] = x[POS] + G.T @ c1_T_m - mrp_to_dcm(X[MRP]).T @ c1_T_m
    X[VEL] = x[VEL] + np.cross(G.T @ x[RATE], X[POS] - x[POS])
    return X


def _keypoints_C(x, r_T_m):
    """Body points r_T_m (K, 3) of state x in C: positions and velocities, (K, 3) each."""
    G = mrp_to_dcm(x[MRP])
    r_C = r_T_m @ G  # rows G^T r
    return x[POS] + r_C, x[VEL] + np.cross(G.T @ x[RATE], r_C)


def test_a_turn_about_the_line_of_two_keypoints_is_straight_and_keeps_them():
    """ENVISAT turned about the line through keypoints A and B (which misses its centre of mass by metres): in the
    screw chart the turns by 0.05 to 2.6 rad are one direction times the angle, and the chart's straight line
    through the first moves A and B (positions and velocities) by round-off at every point up to 150 deg; the
    rotation chart's line through the same first turn moves them by decimetres to metres (0.3 m at 25 deg, 12 m
    at 150 deg)."""
    target = load_target()
    r_AB = target.keypoints_T_m[:2]
    rng = np.random.default_rng(2)
    x = _states(rng, 1)[0]
    D = {}
    for angle in (0.05, 0.5, 1.5, 2.6):
        D[angle] = screw_local(_turned_about_line(x, *r_AB, angle), x) / angle
    np.testing.assert_allclose(np.array(list(D.values())), np.broadcast_to(D[0.05], (4, 12)), atol=1e-10)
    pos0, vel0 = _keypoints_C(x, r_AB)
    moved = {"screw": [], "rotation": []}
    for chart, (retract, local) in {"screw": (screw_retract, screw_local),
                                    "rotation": (chart_retract, chart_local)}.items():
        d1 = local(_turned_about_line(x, *r_AB, 0.05), x) / 0.05
        for angle in np.linspace(0.0, 2.6, 7):
            pos, vel = _keypoints_C(retract(x, angle * d1), r_AB)
            moved[chart].append((np.abs(pos - pos0).max(), np.abs(vel - vel0).max()))
    screw, rotation = np.array(moved["screw"]), np.array(moved["rotation"])
    assert screw[:, 0].max() < 1e-12 and screw[:, 1].max() < 1e-13, screw  # here 3e-14 m and 2e-15 m/s
    assert rotation[1:, 0].min() > 0.01 and rotation[:, 0].max() > 1.0, rotation


def test_screw_transport_is_the_jacobian_of_the_change_of_chart():
    """screw_transport(P, m0, m1) = J P J^T, J the derivative of screw_local(screw_retract(m0, D), m1) at the
    posterior's place D = screw_local(m1, m0), here by central differences of a fixed step (the transport's own
    are scaled by each column's sd), for corrections of 0.6 to 30 deg; the same mean changes nothing."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(12, 12))
    P = (A @ A.T) * np.outer(*[np.r_[[0.1] * 3, [1e-3] * 3, [0.01] * 3, [1e-4] * 3]] * 2)
    for scale in (0.01, 0.1, 0.5):
        m0 = _states(rng, 1)[0]
        m1 = screw_retract(m0, np.r_[rng.normal(size=6) * 0.01, rng.normal(size=3) * scale,
                                     rng.normal(size=3) * 0.05 * scale])
        D0, h = screw_local(m1, m0), 1e-6
        f = lambda D: screw_local(screw_retract(m0, D), m1)  # noqa: E731
        J = np.stack([(f(D0 + e) - f(D0 - e)) / (2 * h) for e in np.eye(12) * h], axis=-1)
        want = J @ P @ J.T
        sd = np.sqrt(np.diag(want))
        np.testing.assert_allclose(screw_transport(P, m0, m1) / np.outer(sd, sd), want / np.outer(sd, sd), atol=1e-7)
    sd = np.sqrt(np.diag(P))
    np.testing.assert_allclose(screw_transport(P, m0, m0) / np.outer(sd, sd), P / np.outer(sd, sd), atol=1e-9)


def test_the_filter_configs_take_the_screw_chart():
    """FilterConfig.sigma_chart = "screw" is a valid setting, and the numpy filter runs it (the fused kernels are the
    additive chart's)."""
    from envisat_pose.filtering.estimator import FilterConfig
    from envisat_pose.filtering.step_update import uses_fused_kernel

    cfg = FilterConfig(sigma_chart="screw")
    assert cfg.sigma_chart == "screw" and not uses_fused_kernel(cfg)


def test_screw_transport_of_a_tight_covariance_far_from_the_chaser():
    """A converged covariance (0.1 mm, 1 urad, ...) of a target 50 m away: the transport's information is the
    reference's to 1e-5 (here ~1e-7). The reference is built on its own: the map is affine in each position,
    velocity and rate coordinate alone (checked here by its second differences over a metre), so those columns are
    differences over 100 sd; the attitude columns Richardson-extrapolated differences of 1e-3 and 5e-4. A step of
    1e-5 sd on every column read round-off of the 50 m as 1 % of the information."""
    rng = np.random.default_rng(4)
    sds = np.r_[[1e-4] * 3, [1e-6] * 3, [1e-6] * 3, [1e-7] * 3]
    A = rng.normal(size=(12, 12))
    C = A @ A.T
    P = C / np.sqrt(np.outer(np.diag(C), np.diag(C))) * np.outer(sds, sds)
    worst = 0.0
    for _ in range(4):
        m0 = _states(rng, 1)[0] + np.r_[0.0, 0.0, 50.0, [0.0] * 9]
        m1 = screw_retract(m0, rng.normal(size=12) * sds * 3)
        D0 = screw_local(m1, m0)
        f = lambda D: screw_local(screw_retract(m0, D), m1)  # noqa: E731
        cols = []
        for j, e in enumerate(np.eye(12)):
            cd = lambda h: (f(D0 + h * e) - f(D0 - h * e)) / (2 * h)  # noqa: E731
            if j in range(MRP.start, MRP.stop):
                cols.append((4 * cd(5e-4) - cd(1e-3)) / 3)
            else:
                np.testing.assert_allclose(f(D0 + e) - 2 * f(D0) + f(D0 - e), 0.0, atol=1e-12)  # affine
                cols.append(cd(100 * sds[j]))
        J = np.stack(cols, axis=-1)
        want = J @ P @ J.T
        Li = np.linalg.inv(np.linalg.cholesky(want))
        worst = max(worst, np.abs(np.linalg.eigvalsh(Li @ screw_transport(P, m0, m1) @ Li.T) - 1.0).max())
    assert worst < 1e-5, worst


def test_the_error_mrp_of_a_rotation_vector_is_the_smaller_set_and_quiet_at_any_angle():
    """error_mrp_from_rotvec: |a| <= 1 (the shadow past 180 deg, not past 360), Gamma(a) the turn by phi (a
    passive DCM, exp(-[phi x])), and no floating-point warning at 360 deg, where the unused branch divided by 0."""
    import warnings

    from scipy.linalg import expm

    from envisat_pose.attitude import skew
    from envisat_pose.filtering.screw_chart import error_mrp_from_rotvec

    u = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    for t in (0.0, 1e-9, 1.0, np.pi - 1e-9, np.pi + 1e-6, 4.0, 2 * np.pi - 1e-6, 2 * np.pi, 7.0):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            a = error_mrp_from_rotvec(t * u)
        assert np.linalg.norm(a) <= 1.0 + 1e-12
        np.testing.assert_allclose(mrp_to_dcm(a), expm(-skew(t * u)), atol=1e-12)
