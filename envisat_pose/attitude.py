"""Attitude math in one place: MRP, quaternions, rotation matrices, batched over leading dimensions.

Conventions (shared/reference.md, section 3):
- Quaternions are (w, x, y, z), MuJoCo's order, Hamilton product. `quat_to_rotmat(q)` is the active rotation
  R(q); for a body quaternion (MuJoCo `xquat`) it is R_parent_from_body.
- An MRP p of frame T relative to frame C gives `Gamma(p) = R_T_from_C` (v_T = Gamma v_C), the passive
  direction cosine matrix. For the same relative orientation the quaternion q has R(q) = R_C_from_T = Gamma^T,
  and p = q_vec / (1 + q_w).
- The shadow set keeps |p| <= 1: p -> -p / (p.p) describes the same orientation.
All functions accept arrays of shape (..., 3), (..., 4) or (..., 3, 3) and broadcast over the leading axes.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v x], so that skew(a) @ b = a x b. (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def mrp_to_dcm(p_mrp: np.ndarray) -> np.ndarray:
    """Gamma(p) = I - a1 [p x] + a2 [p x]^2 (passive DCM, R_T_from_C). (..., 3) -> (..., 3, 3)."""
    p = np.asarray(p_mrp, dtype=float)
    pp = _dot(p, p)[..., None, None]
    S = skew(p)
    a1 = 4.0 * (1.0 - pp) / (1.0 + pp) ** 2
    a2 = 8.0 / (1.0 + pp) ** 2
    return np.eye(3) - a1 * S + a2 * (S @ S)


gamma = mrp_to_dcm


def mrp_kinematics_matrix(p_mrp: np.ndarray) -> np.ndarray:
    """B(p) with p' = B(p) w: 1/4 [(1 - p.p) I + 2 [p x] + 2 p p^T]. (..., 3) -> (..., 3, 3).

    w is the angular velocity of T relative to C expressed in T (rad/s); p' is per second.
    """
    p = np.asarray(p_mrp, dtype=float)
    pp = _dot(p, p)[..., None, None]
    return 0.25 * ((1.0 - pp) * np.eye(3) + 2.0 * skew(p) + 2.0 * p[..., :, None] * p[..., None, :])


def mrp_rate(p_mrp: np.ndarray, w_rad_s: np.ndarray) -> np.ndarray:
    """MRP derivative p' = B(p) w, (..., 3), 1/s."""
    return np.einsum("...ij,...j->...i", mrp_kinematics_matrix(p_mrp), w_rad_s)


def mrp_shadow(p_mrp: np.ndarray) -> np.ndarray:
    """Switch to the shadow set where p.p > 1: p -> -p / (p.p). Same orientation, |p| <= 1. (..., 3)."""
    p = np.asarray(p_mrp, dtype=float)
    pp = _dot(p, p)[..., None]
    return np.where(pp > 1.0, -p / np.where(pp > 1.0, pp, 1.0), p)


def align_mrp(p_mrp: np.ndarray, p_ref: np.ndarray) -> np.ndarray:
    """p or its shadow -p/(p.p), whichever is closer to p_ref (same orientation, comparable set). (..., 3)."""
    pp = np.einsum("...i,...i->...", p_mrp, p_mrp)[..., None]
    shadow = -p_mrp / np.where(pp > 0.0, pp, 1.0)
    closer = np.linalg.norm(shadow - p_ref, axis=-1) < np.linalg.norm(p_mrp - p_ref, axis=-1)
    return np.where((closer & (pp[..., 0] > 0.0))[..., None], shadow, p_mrp)


def mrp_compose(a_mrp: np.ndarray, p_mrp: np.ndarray) -> np.ndarray:
    """The MRP c of Gamma(c) = Gamma(a) Gamma(p): p's rotation followed by a's (a expressed in the frame p leads
    to). c = ((1 - p.p) a + (1 - a.a) p - 2 a x p) / (1 + (p.p)(a.a) - 2 a.p), the continuous branch from p
    where a is small (not switched to |c| <= 1); where the denominator vanishes (a turn of 360 deg) a's shadow,
    the same rotation, is composed instead. (..., 3), broadcast."""
    a = np.asarray(a_mrp, dtype=float)
    p = np.asarray(p_mrp, dtype=float)
    a, p = np.broadcast_arrays(a, p)
    aa, pp = _dot(a, a), _dot(p, p)
    den = 1.0 + pp * aa - 2.0 * _dot(a, p)
    near = np.abs(den) < 1e-6
    if np.any(near):
        a = np.where(near[..., None], -a / np.where(aa > 0.0, aa, 1.0)[..., None], a)
        aa = _dot(a, a)
        den = 1.0 + pp * aa - 2.0 * _dot(a, p)
    num = (1.0 - pp)[..., None] * a + (1.0 - aa)[..., None] * p - 2.0 * np.cross(a, p)
    return num / den[..., None]


def mrp_shadow_jacobian(p_mrp: np.ndarray) -> np.ndarray:
    """Jacobian of p -> -p / (p.p): S = (2 p p^T - (p.p) I) / (p.p)^2. Covariance maps as S P S^T."""
    p = np.asarray(p_mrp, dtype=float)
    pp = _dot(p, p)[..., None, None]
    return (2.0 * p[..., :, None] * p[..., None, :] - pp * np.eye(3)) / pp**2


def mrp_to_quat(p_mrp: np.ndarray) -> np.ndarray:
    """MRP -> quaternion (w, x, y, z) with R(q) = Gamma(p)^T. (..., 3) -> (..., 4)."""
    p = np.asarray(p_mrp, dtype=float)
    pp = _dot(p, p)[..., None]
    return np.concatenate([(1.0 - pp) / (1.0 + pp), 2.0 * p / (1.0 + pp)], axis=-1)


def quat_to_mrp(q: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) -> MRP with |p| <= 1 (q and -q give the same p). (..., 4) -> (..., 3)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0.0, -q, q)
    return q[..., 1:] / (1.0 + q[..., :1])


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Active rotation matrix of a quaternion (w, x, y, z), normalised first. (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> quaternion (w, x, y, z) with w >= 0, R = quat_to_rotmat(q). (..., 3, 3) -> (..., 4).

    Uses the largest of the four squared components (Shepperd's method), so it is accurate everywhere.
    """
    R = np.asarray(R, dtype=float)
    tr = np.trace(R, axis1=-2, axis2=-1)
    d = np.stack([tr, R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], axis=-1)
    k = np.argmax(d, axis=-1)
    q4 = np.stack(
        [
            np.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
            np.stack([R[..., 2, 1] - R[..., 1, 2], 1 + 2 * R[..., 0, 0] - tr, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
            np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 + 2 * R[..., 1, 1] - tr, R[..., 1, 2] + R[..., 2, 1]], -1),
            np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 + 2 * R[..., 2, 2] - tr], -1),
        ],
        axis=-2,
    )
    q = np.take_along_axis(q4, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def dcm_to_mrp(gamma_T_from_C: np.ndarray) -> np.ndarray:
    """Passive DCM Gamma = R_T_from_C -> MRP with |p| <= 1. (..., 3, 3) -> (..., 3)."""
    return quat_to_mrp(rotmat_to_quat(np.swapaxes(np.asarray(gamma_T_from_C, dtype=float), -1, -2)))


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of the rotation R_a R_b^T (the attitude error between two DCMs), rad, accurate near 0 and pi."""
    E = np.asarray(R_a) @ np.swapaxes(np.asarray(R_b), -1, -2)
    c = np.trace(E, axis1=-2, axis2=-1) - 1.0
    s = np.linalg.norm(np.stack([E[..., 2, 1] - E[..., 1, 2], E[..., 0, 2] - E[..., 2, 0], E[..., 1, 0] - E[..., 0, 1]], -1), axis=-1)
    return np.arctan2(s, c)


def mrp_error_angle_rad(p_a: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Rotation angle between the orientations of two MRPs, rad (shadow sets give 0)."""
    return rotation_angle_rad(mrp_to_dcm(p_a), mrp_to_dcm(p_b))
