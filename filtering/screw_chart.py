"""The screw chart of the sigma points (FilterConfig.sigma_chart = "screw"): screw_retract, its inverse
screw_local and screw_transport, the covariance carried between the charts of two means (filtering/ukf.py runs
them as it runs the rotation chart's chart_retract, chart_local and chart_transport: CHART_MAPS).

The rotation chart composes the attitude error and turns the rate with the body, so a turn about a body line
through the centre of mass is straight in it; position and velocity stay additive in C. A turn about a line that
misses the centre of mass (two markers, the only ones measured, on such a line: a screw motion of the body) is
then curved, and every update, relinearized at a new mean, reads the curve as information. Here the attitude
error is an exact rotation vector and the position and velocity errors a twist in the body, so that turn, with
the body's motion relative to C kept, is a straight line at any angle below 2 pi.
"""

from __future__ import annotations

import numpy as np

from envisat_pose.attitude import mrp_compose, mrp_kinematics_matrix, mrp_shadow, mrp_to_dcm, skew
from envisat_pose.state import MRP, POS, RATE, VEL


def rotvec_from_chart_mrp(p: np.ndarray, D_p: np.ndarray) -> np.ndarray:
    """The screw chart's attitude deviation D_p (..., 3) at the mean's MRP p read as a rotation vector phi_T_rad
    (body frame): phi = 4 a with a = B(p)^T D_p / (1 + p.p)^2 the rotation chart's error MRP (D_p = B(p) phi / 4,
    the additive chart to first order)."""
    pp = np.einsum("...i,...i->...", p, p)
    return 16.0 * np.einsum("...ji,...j->...i", mrp_kinematics_matrix(p), D_p) / np.square(1.0 + pp)[..., None]


def error_mrp_from_rotvec(phi_T_rad: np.ndarray) -> np.ndarray:
    """The MRP of the turn by |phi| about phi's axis, the smaller of its two sets: tan(|phi| / 4) phi / |phi|, as
    sin(t / 2) / (1 + cos(t / 2)) (or its shadow -sin / (1 - cos) past |phi| = pi, where |tan(t / 4)| > 1: finite at
    any angle). (..., 3)."""
    th = np.linalg.norm(phi_T_rad, axis=-1, keepdims=True)
    u = phi_T_rad / np.where(th > 0.0, th, 1.0)
    s, c = np.sin(th / 2.0), np.cos(th / 2.0)
    return np.where(c >= 0.0, s / np.maximum(1.0 + c, 1e-300), -s / np.maximum(1.0 - c, 1e-300)) * u


def rotvec_from_error_mrp(a_mrp: np.ndarray) -> np.ndarray:
    """error_mrp_from_rotvec's inverse on |a| <= 1: the rotation vector 4 atan(|a|) a / |a| (|phi| <= pi). (..., 3)."""
    na = np.linalg.norm(a_mrp, axis=-1, keepdims=True)
    return np.where(na > 1e-12, 4.0 * np.arctan(na) / np.where(na > 1e-12, na, 1.0), 4.0) * a_mrp


def so3_left_jacobian(phi_rad: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian V(phi) = I + (1 - cos t) / t^2 [phi x] + (t - sin t) / t^3 [phi x]^2, t = |phi|: the
    turn exp([phi x]) moves a point r by (exp([phi x]) - I) r = V(phi) (phi x r), so the twist (phi, nu) of a turn
    about a line translates by V(phi) nu. (..., 3) -> (..., 3, 3)."""
    th = np.linalg.norm(phi_rad, axis=-1)[..., None, None]
    K = skew(phi_rad)
    small = th < 1e-4
    t = np.where(small, 1.0, th)
    c1 = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    c2 = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + c1 * K + c2 * (K @ K)


def so3_left_jacobian_inv(phi_rad: np.ndarray) -> np.ndarray:
    """V(phi)^-1 = I - [phi x] / 2 + (1 - (t / 2) cot(t / 2)) / t^2 [phi x]^2, t = |phi| < 2 pi (so3_left_jacobian).
    (..., 3) -> (..., 3, 3)."""
    th = np.linalg.norm(phi_rad, axis=-1)[..., None, None]
    K = skew(phi_rad)
    small = th < 1e-4
    t = np.where(small, 1.0, th)
    c2 = np.where(small, 1.0 / 12.0 + th**2 / 720.0, (1.0 - 0.5 * t * np.cos(t / 2.0) / np.sin(t / 2.0)) / t**2)
    return np.eye(3) - 0.5 * K + c2 * (K @ K)


def _apply(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", M, v)


def _apply_T(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...ji,...j->...i", M, v)


def screw_retract(mean: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The states at deviations D from mean in the screw chart: (..., 12) mean, D (..., 12) or (..., S, 12).

    With G = Gamma(p) the mean's attitude (T from C) and w its rate relative to C in T:
    attitude  Gamma_X = Gamma(a) G, a = error_mrp_from_rotvec(phi), phi = rotvec_from_chart_mrp(p, D_p) (exact
              rotation vector in T);
    rate      w_X = Gamma(a) (w + D_w - w x phi) (the rate relative to C in C, G^T (w + D_w - w x phi), unchanged
              where D_w = w x phi: the body turned, its motion not);
    position  rho_X = rho + G^T V(phi) G D_rho (the twist of a screw motion in T, so3_left_jacobian);
    velocity  rho'_X = rho' + D_v + W_X x (rho_X - rho) - W x D_rho, W = G^T w and W_X = G^T (w + D_w - w x phi)
              the rates relative to C in C (a body point's velocity in C is rho' + W x (r - rho)).
    A turn by t phi about the body line through a body point c, the body's motion relative to C kept, is then the
    line t (phi, G^T (c x phi), W x G^T (c x phi), w x phi) at any angle below 2 pi: the keypoints on that line
    do not move (nor their velocities), so where they alone are measured the update sees a straight unmeasured
    direction (tests/filtering/test_screw_chart.py). To first order in D it is the additive chart.
    What it bends instead: a translation with the attitude off, and through W the position and velocity errors of
    a body that turns fast relative to C. Where such a target goes unmeasured until both are large, the tight
    position-velocity relation an outage builds is curved here (tests/filtering/test_sigma_chart.py's 30 m rod,
    2.6 deg/s, 115 s with no measurement, 8 runs: mean NEES 25-520 at the outage's end and after all keypoints
    return, 8-20 in the rotation chart); it is meant for a target that turns slowly relative to C."""
    mean = np.asarray(mean, dtype=float)
    D = np.asarray(D, dtype=float)
    m = mean[..., None, :] if D.ndim == mean.ndim + 1 else mean
    m = np.broadcast_to(m, D.shape)
    p, w = m[..., MRP], m[..., RATE]
    G = mrp_to_dcm(p)
    phi = rotvec_from_chart_mrp(p, D[..., MRP])
    a = error_mrp_from_rotvec(phi)
    w_turned = w + D[..., RATE] - np.cross(w, phi)                 # the new rate, in the mean's body axes
    drho = _apply_T(G, _apply(so3_left_jacobian(phi), _apply(G, D[..., POS])))
    X = np.empty_like(D)
    X[..., POS] = m[..., POS] + drho
    X[..., VEL] = (m[..., VEL] + D[..., VEL] + np.cross(_apply_T(G, w_turned), drho)
                   - np.cross(_apply_T(G, w), D[..., POS]))
    X[..., MRP] = mrp_compose(a, p)
    X[..., RATE] = _apply(mrp_to_dcm(a), w_turned)
    return X


def screw_local(X: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """screw_retract's inverse: D with screw_retract(mean, D) = X (the smaller of the two error rotations,
    |phi| <= pi). X (..., S, 12) or (..., 12), mean (..., 12)."""
    X = np.asarray(X, dtype=float)
    mean = np.asarray(mean, dtype=float)
    m = mean[..., None, :] if X.ndim == mean.ndim + 1 else mean
    m = np.broadcast_to(m, X.shape)
    p, w = m[..., MRP], m[..., RATE]
    G = mrp_to_dcm(p)
    a = mrp_shadow(mrp_compose(X[..., MRP], -p))                   # Gamma(a) = Gamma(p_X) Gamma(p)^T
    phi = rotvec_from_error_mrp(a)
    w_turned = _apply_T(mrp_to_dcm(a), X[..., RATE])
    drho = X[..., POS] - m[..., POS]
    D = np.empty_like(X)
    D[..., POS] = _apply_T(G, _apply(so3_left_jacobian_inv(phi), _apply(G, drho)))
    D[..., VEL] = (X[..., VEL] - m[..., VEL] - np.cross(_apply_T(G, w_turned), drho)
                   + np.cross(_apply_T(G, w), D[..., POS]))
    D[..., MRP] = _apply(mrp_kinematics_matrix(p), phi)
    D[..., RATE] = w_turned - w + np.cross(w, phi)
    return D


SCREW_TRANSPORT_STEP = 1e-5  # screw_transport's central-difference step for the attitude columns, in sd of each
SCREW_TRANSPORT_MIN_STEP = 1e-6  # ... and at least this (D_p units): round-off, not curvature, limits a tight one


def screw_transport(cov: np.ndarray, mean_from: np.ndarray, mean_to: np.ndarray) -> np.ndarray:
    """A covariance in the screw chart at mean_from carried to the chart at mean_to: J P J^T with J the derivative
    of screw_local(screw_retract(mean_from, D), mean_to) at D0 = screw_local(mean_to, mean_from), by central
    differences (24 retractions and local charts a run: a few % of an update's cost). That map is affine in each
    position, velocity and rate coordinate alone (the others held), so those columns take a step of one sd and
    are exact but for round-off; the attitude columns, the only curved ones, take SCREW_TRANSPORT_STEP sd, at
    least SCREW_TRANSPORT_MIN_STEP (a step of 1e-5 sd on every column made the round-off of a 50 m position, eps
    |rho| / step, ~1 % of a 0.1 mm covariance's information). (..., 12, 12)."""
    n = cov.shape[-1]
    D0 = screw_local(mean_to, mean_from)
    sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 1e-300))  # (..., n)
    curved = np.zeros(n, dtype=bool)
    curved[MRP] = True
    h = np.where(curved, np.maximum(SCREW_TRANSPORT_STEP * sd, SCREW_TRANSPORT_MIN_STEP), sd)
    E = np.eye(n) * h[..., None, :]                                # (..., n, n): row j = h_j e_j
    f = screw_local(screw_retract(mean_from, D0[..., None, :] + np.concatenate([E, -E], axis=-2)), mean_to)
    J = np.swapaxes(f[..., :n, :] - f[..., n:, :], -1, -2) / (2.0 * h[..., None, :])
    out = J @ cov @ np.swapaxes(J, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))
