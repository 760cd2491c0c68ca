"""The paper's UKF through filterpy 2.0.0: the reference implementation our batched filter is tested against.

MRP shadow-set handling sits in filterpy's hooks: `x_mean_fn` (sigma points brought to the central point's set
before averaging, the mean switched to |p| <= 1) and `residual_x` (a sigma point's MRP brought to the set of the
point it is compared with); `state_add` is plain addition, and after an update that takes |p| over 1 the mean
and the covariance are switched together (`shadow_switch`), since a hook cannot touch P.
A varying number of corners is passed as a full R matrix and an hx that returns only the measured corners.
Only the tests and the benchmarks import this module: filterpy is their extra (`pip install envisat-pose[test]`),
not a dependency of the package.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from envisat_pose.filtering.dynamics import MU_EARTH_M3_S2, load_inertia_T_kg_m2, propagate
from envisat_pose.filtering.measurements import measure
from envisat_pose.filtering.step_update import split_factors
from envisat_pose.filtering.ukf import shadow_switch, state_mean, state_residual
from envisat_pose.geometry import PinholeCamera


def _fx(x: np.ndarray, dt: float, c0: np.ndarray, J_T: np.ndarray, mu_m3_s2: float, max_step_s: float) -> np.ndarray:
    """filterpy's fx: one sigma point (12,) through the filter's RK4 model."""
    return propagate(x, c0, dt, J_T, mu_m3_s2, max_step_s)


def make_reference_ukf(x0: np.ndarray, P0: np.ndarray, Q: np.ndarray, alpha: float = 1.0, beta: float = 2.0,
                       kappa: float = 0.0) -> UnscentedKalmanFilter:
    """A filterpy UKF on the 12-state with the MRP hooks; x0 (12,), P0 and Q (12, 12)."""
    points = MerweScaledSigmaPoints(12, alpha=alpha, beta=beta, kappa=kappa)
    ukf = UnscentedKalmanFilter(dim_x=12, dim_z=24, dt=1.0, hx=None, fx=_fx, points=points,
                                x_mean_fn=state_mean, residual_x=state_residual, state_add=np.add)
    ukf.x = np.array(x0, dtype=float)
    ukf.P = np.array(P0, dtype=float)
    ukf.Q = np.array(Q, dtype=float)
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)  # so that an update may come before the first predict
    return ukf


def reference_predict(ukf: UnscentedKalmanFilter, dt_s: float, c0: np.ndarray, J_T: np.ndarray | None = None,
                      mu_m3_s2: float = MU_EARTH_M3_S2, max_step_s: float = 1.0) -> None:
    """filterpy predict with the chaser state c0 (4,) at the start of the step."""
    J_T = load_inertia_T_kg_m2() if J_T is None else J_T
    ukf.predict(dt=dt_s, c0=np.asarray(c0, dtype=float), J_T=J_T, mu_m3_s2=mu_m3_s2, max_step_s=max_step_s)


def reference_update(ukf: UnscentedKalmanFilter, z: np.ndarray, mask_c: np.ndarray, R_c: np.ndarray, kind: str,
                     camera: PinholeCamera | None = None, split: tuple[float, int] | None = None) -> int:
    """filterpy update with the measured corners only. z (K, m), mask_c (K,) bool, R_c (K, m, m). split: (gain,
    most), FilterConfig's split_gain and split_max: where filterpy's innovation covariance S says the prior is
    ratio = tr(S - R) / tr(R) > gain times wider than the noise, the update is made again from the prior in
    n = min(ceil(ratio / gain), most) updates with R times step_update.split_factors', each from sigma points about
    the last one's result. Returns n (1: one update)."""
    mask_c = np.asarray(mask_c, dtype=bool)
    if not mask_c.any():
        ukf.update(None)
        n = 1
    else:
        blocks = np.broadcast_to(R_c, z.shape + (z.shape[-1],))[mask_c]
        R = np.zeros((blocks.shape[0] * blocks.shape[1],) * 2)
        m = blocks.shape[1]
        for i, b in enumerate(blocks):
            R[i * m:(i + 1) * m, i * m:(i + 1) * m] = b
        hx = lambda x: measure(x, kind, camera)[mask_c].ravel()  # noqa: E731
        x_prior, P_prior = ukf.x.copy(), ukf.P.copy()
        ukf.update(z[mask_c].ravel(), R=R, hx=hx)
        n = 1
        if split is not None:
            ratio = np.trace(ukf.S - R) / np.trace(R)
            n = int(min(max(np.ceil(ratio / split[0]), 1), split[1]))
        if n > 1:
            ukf.x, ukf.P = x_prior, P_prior
            for factor in split_factors(np.array([ratio]), split[0], split[1])[0, :n]:
                ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
                ukf.update(z[mask_c].ravel(), R=R * factor, hx=hx)
                ukf.x, ukf.P = shadow_switch(ukf.x, ukf.P)
    ukf.x, ukf.P = shadow_switch(ukf.x, ukf.P)
    ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
    return n
