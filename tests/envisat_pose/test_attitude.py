"""MRP, quaternion and DCM identities, checked against scipy's Rotation and finite differences."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from envisat_pose import attitude as att


@pytest.fixture
def rotations():
    return Rotation.random(500, rng=np.random.default_rng(7))


def test_quaternion_matrix_agrees_with_scipy(rotations):
    q_wxyz = rotations.as_quat(scalar_first=True)
    np.testing.assert_allclose(att.quat_to_rotmat(q_wxyz), rotations.as_matrix(), atol=1e-14)
    q_back = att.rotmat_to_quat(rotations.as_matrix())
    # q and -q are the same rotation; rotmat_to_quat picks w >= 0
    np.testing.assert_allclose(np.abs(np.sum(q_back * q_wxyz, axis=-1)), 1.0, atol=1e-13)
    assert np.all(q_back[:, 0] >= 0)


def test_gamma_is_the_passive_dcm_of_the_quaternion(rotations):
    q = rotations.as_quat(scalar_first=True)
    p = att.quat_to_mrp(q)
    assert np.all(np.linalg.norm(p, axis=-1) <= 1.0 + 1e-15)
    # Gamma(p) = R_T_from_C is the transpose of the active rotation R(q) = R_C_from_T
    np.testing.assert_allclose(att.mrp_to_dcm(p), np.swapaxes(rotations.as_matrix(), -1, -2), atol=1e-14)
    G = att.mrp_to_dcm(p)
    np.testing.assert_allclose(G @ np.swapaxes(G, -1, -2), np.broadcast_to(np.eye(3), G.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(G), 1.0, atol=1e-13)


def test_round_trips_to_1e12(rotations):
    p = att.quat_to_mrp(rotations.as_quat(scalar_first=True))
    np.testing.assert_allclose(att.quat_to_mrp(att.mrp_to_quat(p)), p, atol=1e-12)
    np.testing.assert_allclose(att.dcm_to_mrp(att.mrp_to_dcm(p)), p, atol=1e-12)
    R = rotations.as_matrix()
    np.testing.assert_allclose(att.quat_to_rotmat(att.rotmat_to_quat(R)), R, atol=1e-12)


def test_shadow_set_leaves_gamma_unchanged():
    rng = np.random.default_rng(1)
    p_long = rng.standard_normal((300, 3)) * 3.0
    p_long = p_long[np.einsum("ij,ij->i", p_long, p_long) > 1.0]
    p_short = att.mrp_shadow(p_long)
    assert np.all(np.linalg.norm(p_short, axis=-1) <= 1.0)
    np.testing.assert_allclose(p_short, -p_long / np.sum(p_long**2, -1, keepdims=True), atol=0)
    np.testing.assert_allclose(att.mrp_to_dcm(p_short), att.mrp_to_dcm(p_long), atol=1e-13)
    inside = np.array([[0.1, -0.2, 0.3]])
    np.testing.assert_array_equal(att.mrp_shadow(inside), inside)


def test_shadow_jacobian_by_finite_differences():
    p = np.array([0.9, -0.7, 0.4])
    S = att.mrp_shadow_jacobian(p)
    f = lambda v: -v / np.dot(v, v)  # noqa: E731
    h = 1e-6
    S_fd = np.stack([(f(p + h * e) - f(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(S, S_fd, atol=1e-8)


def test_mrp_kinematics_match_the_dcm_rate():
    # For Gamma = R_T_from_C and w the rate of T relative to C in T: dGamma/dt = -[w x] Gamma.
    rng = np.random.default_rng(3)
    for _ in range(20):
        p = att.mrp_shadow(rng.standard_normal(3))
        w = rng.standard_normal(3)
        h = 1e-6
        pdot = att.mrp_rate(p, w)
        G_dot = (att.mrp_to_dcm(p + h * pdot) - att.mrp_to_dcm(p - h * pdot)) / (2 * h)
        np.testing.assert_allclose(G_dot, -att.skew(w) @ att.mrp_to_dcm(p), atol=1e-8)


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(4)
    a, b = rng.standard_normal((2, 10, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", att.skew(a), b), np.cross(a, b), atol=1e-15)


def test_rotation_angle(rotations):
    R = rotations.as_matrix()
    angle = att.rotation_angle_rad(R, np.broadcast_to(np.eye(3), R.shape))
    np.testing.assert_allclose(angle, rotations.magnitude(), atol=1e-9)
    tiny = Rotation.from_rotvec([1e-9, 0, 0]).as_matrix()
    assert abs(att.rotation_angle_rad(tiny, np.eye(3)) - 1e-9) < 1e-15
