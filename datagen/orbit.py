"""The chaser's Keplerian orbit in closed form: polar coordinates (r, theta) and the LVLH frame C.

C: x radial out, z orbit normal, y = z x x (along-track). N: inertial. Units: m, s, rad.
This is the same Kepler solution the gravity plugin evaluates in C, so the chaser's frame and the relative
gravity refer to one chief.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ChaserOrbit:
    """The chaser's orbit at times t_s (N,).

    r_m, rdot_m_s, theta_rad (argument of latitude), thetadot_rad_s, thetaddot_rad_s2: (N,)
    r_N_m, v_N_m_s: (N, 3) inertial position and velocity.
    R_N_from_C: (N, 3, 3) columns are the LVLH axes in N.
    """

    r_m: np.ndarray
    rdot_m_s: np.ndarray
    theta_rad: np.ndarray
    thetadot_rad_s: np.ndarray
    thetaddot_rad_s2: np.ndarray
    r_N_m: np.ndarray
    v_N_m_s: np.ndarray
    R_N_from_C: np.ndarray

    @property
    def w_c_C_rad_s(self) -> np.ndarray:
        """Angular velocity of C relative to N, in C: (0, 0, theta'). (N, 3)."""
        return np.stack([np.zeros_like(self.thetadot_rad_s), np.zeros_like(self.thetadot_rad_s), self.thetadot_rad_s], -1)


def true_to_mean_anomaly(nu_rad: float, e: float) -> float:
    E = 2.0 * np.arctan2(np.sqrt(1.0 - e) * np.sin(nu_rad / 2.0), np.sqrt(1.0 + e) * np.cos(nu_rad / 2.0))
    return float(E - e * np.sin(E))


def solve_kepler(M_rad: np.ndarray, e: float) -> np.ndarray:
    """Eccentric anomaly E with E - e sin E = M (Newton, converged to machine precision)."""
    M = np.mod(np.asarray(M_rad, dtype=float), 2.0 * np.pi)
    E = M.copy() if e < 0.8 else np.full_like(M, np.pi)
    for _ in range(50):
        dE = (E - e * np.sin(E) - M) / (1.0 - e * np.cos(E))
        E = E - dE
        if np.all(np.abs(dE) < 1e-15):
            break
    return E


def chaser_orbit(orbit, t_s: np.ndarray) -> ChaserOrbit:
    """Evaluate the Keplerian orbit `orbit` (an OrbitConfig; true anomaly nu0 at t = 0) at times t_s."""
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    mu, a, e = orbit.mu_m3_s2, orbit.a_m, orbit.e
    deg = np.pi / 180.0
    n = np.sqrt(mu / a**3)
    M = true_to_mean_anomaly(orbit.nu0_deg * deg, e) + n * t
    E = solve_kepler(M, e)
    nu = 2.0 * np.arctan2(np.sqrt(1.0 + e) * np.sin(E / 2.0), np.sqrt(1.0 - e) * np.cos(E / 2.0))
    p = a * (1.0 - e**2)
    r = a * (1.0 - e * np.cos(E))
    rdot = np.sqrt(mu / p) * e * np.sin(nu)
    thetadot = np.sqrt(mu * p) / r**2
    thetaddot = -2.0 * rdot * thetadot / r
    theta = orbit.argp_deg * deg + nu
    raan, inc = orbit.raan_deg * deg, orbit.i_deg * deg
    cO, sO, ci, si = np.cos(raan), np.sin(raan), np.cos(inc), np.sin(inc)
    ct, st = np.cos(theta), np.sin(theta)
    x_hat = np.stack([cO * ct - sO * st * ci, sO * ct + cO * st * ci, st * si], -1)
    z_hat = np.broadcast_to(np.array([sO * si, -cO * si, ci]), x_hat.shape)
    y_hat = np.cross(z_hat, x_hat)
    R_N_from_C = np.stack([x_hat, y_hat, z_hat], axis=-1)
    r_N = r[:, None] * x_hat
    v_N = rdot[:, None] * x_hat + (r * thetadot)[:, None] * y_hat
    return ChaserOrbit(r, rdot, theta, thetadot, thetaddot, r_N, v_N, R_N_from_C)
