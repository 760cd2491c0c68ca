"""The filter's own motion model: chaser orbit, relative translation and relative attitude, RK4.

Independent of the MuJoCo truth (design.md): the reference sheet's corrected equations (shared/reference.md,
section 4), integrated with RK4 at the filter step and batched over any leading dimensions (runs x sigma points).

State (the paper's order, section 3): x = (rho_C_m, rhodot_C_m_s, p_mrp, w_r_T_rad_s), shape (..., 12).
Torque-free, translation (x[..., TRANSLATION] = rho, rho') and rotation (x[..., ROTATION] = p, w_r) are two
decoupled 6-state blocks: each
derivative depends only on its own block and on the chaser's orbit. With the gravity-gradient torque (optional,
as in the truth's MuJoCo plugin) the rotation also depends on rho, and `propagate` takes one RK4 step of the
full 12-state.

The chaser's orbit is known to the filter: at the start of every filter step it is taken from the truth's
`chaser_*` arrays (the chaser knows its own orbit from navigation), then propagated through the RK4 stages with
the polar two-body equations below, so the stage values of theta' and theta'' are consistent with the step.
Chaser state: c = (r_m, rdot_m_s, theta_rad, thetadot_rad_s), shape (..., 4).
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET

import numpy as np

from envisat_pose.attitude import mrp_rate, mrp_shadow, mrp_to_dcm
from envisat_pose.geometry import model_path
from envisat_pose.state import MRP, POS, RATE, VEL

MU_EARTH_M3_S2 = 3.986004418e14
# the two 6-state blocks of the 12-state (envisat_pose.state's layout), and the parts inside each block
TRANSLATION = slice(POS.start, VEL.stop)
ROTATION = slice(MRP.start, RATE.stop)
_RHODOT = slice(VEL.start - POS.start, VEL.stop - POS.start)
_P, _W = slice(0, MRP.stop - MRP.start), slice(RATE.start - MRP.start, RATE.stop - MRP.start)


@functools.lru_cache(maxsize=4)
def load_inertia_T_kg_m2(path: str | None = None) -> np.ndarray:
    """Target inertia about its CoM in T, kg m^2, (3, 3), read from `fullinertia` of body `target` in the MJCF.

    MuJoCo's fullinertia order is Ixx Iyy Izz Ixy Ixz Iyz.
    """
    path = path or model_path()
    root = ET.parse(path).getroot()
    body = next((b for b in root.iter("body") if b.get("name") == "target"), None)
    if body is None:
        raise ValueError(f"{path}: no body named 'target'")
    inertial = body.find("inertial")
    if inertial is None or inertial.get("fullinertia") is None:
        raise ValueError(f"{path}: body 'target' has no <inertial fullinertia=...>")
    ixx, iyy, izz, ixy, ixz, iyz = (float(v) for v in inertial.get("fullinertia").split())
    J = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    J.setflags(write=False)
    return J


def chaser_rate(c: np.ndarray, mu_m3_s2: float = MU_EARTH_M3_S2) -> np.ndarray:
    """Chaser polar two-body ODE: r'' = r th'^2 - mu/r^2, th'' = -2 r' th'/r. (..., 4) -> (..., 4)."""
    r, rd, thd = c[..., 0], c[..., 1], c[..., 3]
    rdd = r * thd**2 - mu_m3_s2 / r**2
    thdd = -2.0 * rd * thd / r
    return np.stack([rd, rdd, thd, thdd], axis=-1)


def chaser_thetaddot(c: np.ndarray) -> np.ndarray:
    """theta'' = -2 r' theta' / r, rad/s^2, (...,)."""
    return -2.0 * c[..., 1] * c[..., 3] / c[..., 0]


def translation_rate(x_tr: np.ndarray, c: np.ndarray, mu_m3_s2: float = MU_EARTH_M3_S2) -> np.ndarray:
    """Nonlinear relative translation in C (sheet, section 4). x_tr = (rho_C_m, rhodot_C_m_s), (..., 6).

    c: chaser state (..., 4), broadcast against x_tr's leading dims. Returns (rho', rho''), (..., 6).
    """
    x, y, z = x_tr[..., 0], x_tr[..., 1], x_tr[..., 2]
    xd, yd = x_tr[..., 3], x_tr[..., 4]
    r, thd = c[..., 0], c[..., 3]
    thdd = chaser_thetaddot(c)
    D = ((r + x) ** 2 + y**2 + z**2) ** 1.5
    xdd = 2.0 * thd * yd + thdd * y + thd**2 * x - mu_m3_s2 * (r + x) / D + mu_m3_s2 / r**2
    ydd = -2.0 * thd * xd - thdd * x + thd**2 * y - mu_m3_s2 * y / D
    zdd = -mu_m3_s2 * z / D
    return np.concatenate([x_tr[..., _RHODOT], np.stack([xdd, ydd, zdd], axis=-1)], axis=-1)


def gravity_gradient_torque_T(rho_C_m: np.ndarray, p_mrp: np.ndarray, c: np.ndarray, J_T: np.ndarray,
                              mu_m3_s2: float = MU_EARTH_M3_S2) -> np.ndarray:
    """Gravity-gradient torque on the target about its CoM, in T, N m: tau = 3 mu / |R|^5 (R x J R).

    R is the target's CoM from the Earth's centre, R_T = Gamma (r e_x + rho_C) (C is LVLH, x radial out), as the
    truth's MuJoCo plugin applies it. rho_C_m (..., 3) m; p_mrp (..., 3); c chaser state (..., 4) (r_m first);
    J_T (3, 3) kg m^2. Returns (..., 3).
    """
    R_C = rho_C_m + c[..., 0, None] * np.array([1.0, 0.0, 0.0])
    R_T = np.einsum("...ij,...j->...i", mrp_to_dcm(p_mrp), R_C)
    R2 = np.einsum("...i,...i->...", R_T, R_T)
    return (3.0 * mu_m3_s2 / (R2 * R2 * np.sqrt(R2)))[..., None] * np.cross(R_T, R_T @ J_T.T)


def rotation_rate(x_rot: np.ndarray, c: np.ndarray, J_T: np.ndarray, tau_T: np.ndarray | None = None) -> np.ndarray:
    """MRP kinematics and relative attitude dynamics. x_rot = (p_mrp, w_r_T_rad_s), (..., 6).

    w_r' = J^-1 (tau - w_t x J w_t) + w_r x Gamma w_c - Gamma w_c',  w_t = w_r + Gamma w_c,
    with w_c = (0, 0, theta') and w_c' = (0, 0, theta'') in C. J_T: (3, 3) kg m^2. tau_T: external torque in T,
    N m, (..., 3) (None: torque-free). Returns (p', w_r'), (..., 6).
    """
    p, w_r = x_rot[..., _P], x_rot[..., _W]
    G = mrp_to_dcm(p)
    # Gamma w_c = theta' * third column of Gamma (w_c is along z_C)
    thd = c[..., 3]
    Gw_c = G[..., :, 2] * thd[..., None]
    Gw_cdot = G[..., :, 2] * chaser_thetaddot(c)[..., None]
    w_t = w_r + Gw_c
    Jw_t = w_t @ J_T.T
    if tau_T is None:
        w_r_dot = -np.cross(w_t, Jw_t) @ np.linalg.inv(J_T).T  # J^-1 (-w_t x J w_t), torque-free
    else:
        w_r_dot = (tau_T - np.cross(w_t, Jw_t)) @ np.linalg.inv(J_T).T  # J^-1 (tau - w_t x J w_t)
    w_r_dot = w_r_dot + np.cross(w_r, Gw_c) - Gw_cdot
    return np.concatenate([mrp_rate(p, w_r), w_r_dot], axis=-1)


def state_rate(x: np.ndarray, c: np.ndarray, J_T: np.ndarray, mu_m3_s2: float = MU_EARTH_M3_S2,
               gravity_gradient: bool = False) -> np.ndarray:
    """Derivative of the full 12-state, (..., 12) -> (..., 12); with gravity_gradient the rotation feels the
    gravity-gradient torque at the target's position rho (gravity_gradient_torque_T)."""
    tau_T = gravity_gradient_torque_T(x[..., POS], x[..., MRP], c, J_T, mu_m3_s2) if gravity_gradient else None
    return np.concatenate([translation_rate(x[..., TRANSLATION], c, mu_m3_s2),
                           rotation_rate(x[..., ROTATION], c, J_T, tau_T)], axis=-1)


def chaser_stages(c0: np.ndarray, dt_s: float, mu_m3_s2: float = MU_EARTH_M3_S2):
    """The chaser state at the four RK4 stages of one step and at its end: (c1, c2, c3, c4, c_end), each (..., 4)."""
    k1 = chaser_rate(c0, mu_m3_s2)
    c2 = c0 + 0.5 * dt_s * k1
    k2 = chaser_rate(c2, mu_m3_s2)
    c3 = c0 + 0.5 * dt_s * k2
    k3 = chaser_rate(c3, mu_m3_s2)
    c4 = c0 + dt_s * k3
    k4 = chaser_rate(c4, mu_m3_s2)
    c_end = c0 + dt_s / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return c0, c2, c3, c4, c_end


def _rk4_block(f, y0: np.ndarray, stages, dt_s: float) -> np.ndarray:
    """One RK4 step of y' = f(y, c) with the chaser's stage states `stages` (c1, c2, c3, c4)."""
    c1, c2, c3, c4 = stages
    k1 = f(y0, c1)
    k2 = f(y0 + 0.5 * dt_s * k1, c2)
    k3 = f(y0 + 0.5 * dt_s * k2, c3)
    k4 = f(y0 + dt_s * k3, c4)
    return y0 + dt_s / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


# the most a body may turn in one of the filter's RK4 sub-steps: RK4's error grows as (w h)^5, and 1 s steps of a
# tumble at 0.57 rad/s (an 11 s period) left the filter over-confident (mean NEES 26) where 0.1 s steps did not
MAX_TURN_PER_RK4_STEP_RAD = 0.2
# the most RK4 sub-steps one filter step takes: a batch shares its sub-step, so one run whose rate estimate ran
# away (a diverged run: |w| of 1e5 rad/s) would otherwise stall every run of the batch in millions of sub-steps and
# allocate their chaser stages (n_sub x 4 x 4); 100 sub-steps still resolve sigma points turning at up to 20 rad/s
# over a 1 s step and 1 rad/s over the rate sweep's slowest 20 s step (ENVISAT's: 0.05-0.06 rad/s)
MAX_RK4_SUBSTEPS = 100


def rk4_step_s(max_step_s: float, w_max_rad_s: float) -> float:
    """The filter's RK4 sub-step bound, s: max_step_s, or shorter where a body turning at w_max_rad_s (the
    fastest rate the step propagates) would turn more than MAX_TURN_PER_RK4_STEP_RAD in it."""
    w = float(w_max_rad_s)
    if not np.isfinite(w) or w <= 0.0:
        return float(max_step_s)
    return min(float(max_step_s), MAX_TURN_PER_RK4_STEP_RAD / w)


def trajectory_step_s(x: np.ndarray, max_step_s: float = 1.0) -> float:
    """rk4_step_s at the fastest relative rate |w_r| of the states x (..., 12), s: the sub-step that propagates a
    known trajectory (the PCRLB's Jacobians along the truth) as finely as the filter propagates its sigma points,
    instead of max_step_s whatever the tumble (1 s steps of a 60 deg/s tumble made the bound's attitude and rate
    1.3 and 2 times too tight at 0.1 Hz)."""
    rate = np.sqrt(np.sum(np.square(np.asarray(x, dtype=float)[..., RATE]), axis=-1))
    rate = rate[np.isfinite(rate)]
    return rk4_step_s(max_step_s, float(rate.max()) if rate.size else 0.0)


def sigma_step_s(max_step_s: float, mean: np.ndarray, cov: np.ndarray, spread: float,
                 dt_s: float | None = None) -> float:
    """rk4_step_s at the fastest rate of the sigma points of R runs (mean (R, 12), cov (R, 12, 12)), drawn
    sqrt(spread) columns of cov's square root from the mean (spread: the UKF's n + lambda): bounded by |w_mean| +
    sqrt(spread tr P_ww); runs that are not finite left out. dt_s: the step to propagate; the rate then shortens
    the sub-step to no less than dt_s / MAX_RK4_SUBSTEPS (max_step_s, if shorter, still holds)."""
    rate = np.sqrt(np.sum(np.square(mean[..., RATE]), axis=-1))
    bound = rate + np.sqrt(np.maximum(spread * np.trace(cov[..., RATE, RATE], axis1=-2, axis2=-1), 0.0))
    bound = bound[np.isfinite(bound)]
    step_s = rk4_step_s(max_step_s, float(bound.max()) if bound.size else 0.0)
    return step_s if dt_s is None else max(step_s, min(float(max_step_s), float(dt_s) / MAX_RK4_SUBSTEPS))


def propagate(x: np.ndarray, c0: np.ndarray, dt_s: float, J_T: np.ndarray | None = None,
              mu_m3_s2: float = MU_EARTH_M3_S2, max_step_s: float = 1.0, gravity_gradient: bool = False
              ) -> np.ndarray:
    """Propagate the 12-state over dt_s with RK4 (sub-steps no longer than max_step_s). No shadow switch.

    x: (..., 12). c0: chaser state at the start, (4,) or broadcastable to x[..., :4]. Returns (..., 12).
    Torque-free, the two 6-state blocks are integrated apart; with gravity_gradient (the torque couples them)
    each sub-step is one RK4 step of the full 12-state.
    The MRP switches to |p| <= 1 between sub-steps only; at the end it is left on the set it was propagated in
    and the caller switches (the UKF does it on the mean, after aligning the sigma points).
    """
    J_T = load_inertia_T_kg_m2() if J_T is None else J_T
    n_sub = max(1, int(np.ceil(dt_s / max_step_s - 1e-9)))
    h = dt_s / n_sub
    x_tr, x_rot = x[..., TRANSLATION], x[..., ROTATION]
    c = np.asarray(c0, dtype=float)
    for i in range(n_sub):
        c1, c2, c3, c4, c_end = chaser_stages(c, h, mu_m3_s2)
        st = (c1, c2, c3, c4)
        if gravity_gradient:
            x_full = _rk4_block(lambda y, cc: state_rate(y, cc, J_T, mu_m3_s2, True),
                                np.concatenate([x_tr, x_rot], axis=-1), st, h)
            x_tr, x_rot = x_full[..., TRANSLATION], x_full[..., ROTATION]
        else:
            x_tr = _rk4_block(lambda y, cc: translation_rate(y, cc, mu_m3_s2), x_tr, st, h)
            x_rot = _rk4_block(lambda y, cc: rotation_rate(y, cc, J_T), x_rot, st, h)
        if i < n_sub - 1:  # a long step may turn through 360 deg, where p -> infinity: switch between sub-steps
            x_rot = np.concatenate([mrp_shadow(x_rot[..., _P]), x_rot[..., _W]], axis=-1)
        c = c_end
    return np.concatenate([x_tr, x_rot], axis=-1)
