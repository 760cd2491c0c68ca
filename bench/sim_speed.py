"""Truth-simulation speed: the compiled gravity plugin against the same force from Python, MuJoCo's threaded
rollouts, and a plain scipy integration of the same equations, in one run.

Each method simulates the default scenario (50 m V-bar hold, ENVISAT tumbling with a 134.74 s period) and is
scored by simulated seconds per wall second, and by its relative-position error at the end against two
independent inertial two-body propagations (so "matched accuracy" can be read off the table).

    .venv/bin/python bench/sim_speed.py [--duration-s 1000] [--rollouts 32] [--threads N] [--out FILE.json]

Prints a table and writes --out (default bench/results/sim_speed.json).
"""

from __future__ import annotations

import math
import os
import platform
import time
import xml.etree.ElementTree as ET

import mujoco
import mujoco.rollout
import numpy as np
from scipy.integrate import solve_ivp

from envisat_pose.attitude import mrp_rate, mrp_shadow, mrp_to_dcm
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.plugin import PLUGIN_NAME
from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.datagen.sim import TruthSim, model_xml
from envisat_pose.datagen.truth import initial_state
from envisat_pose.state import MRP, POS, RATE, VEL

HERE = os.path.dirname(os.path.abspath(__file__))


def model_without_plugin(cfg) -> mujoco.MjModel:
    """The same model with the gravity plugin removed (for the Python-force peers)."""
    root = ET.fromstring(model_xml(cfg))
    root.remove(root.find("extension"))
    for body in root.iter("body"):
        for p in body.findall("plugin"):
            body.remove(p)
    return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))


def make_differential_gravity(cfg):
    """The plugin's acceleration as a fast Python function of (t_s, rho_N): scalar Kepler with `math`, then
    -mu (r_c + rho)/|r_c + rho|^3 + mu r_c/|r_c|^3, m/s^2, in N. Written for speed, so the peer is fair."""
    o = cfg.orbit
    mu, a, e = o.mu_m3_s2, o.a_m, o.e
    n = math.sqrt(mu / a**3)
    orb0 = chaser_orbit(o, np.array([0.0]))
    # perigee and its quadrature direction in N, from the closed-form orbit at t = 0 (nu = nu0)
    nu0 = math.radians(o.nu0_deg)
    x0, y0 = orb0.R_N_from_C[0][:, 0], orb0.R_N_from_C[0][:, 1]
    p_hat = math.cos(nu0) * x0 - math.sin(nu0) * y0
    q_hat = math.sin(nu0) * x0 + math.cos(nu0) * y0
    E0 = 2 * math.atan2(math.sqrt(1 - e) * math.sin(nu0 / 2), math.sqrt(1 + e) * math.cos(nu0 / 2))
    M0 = E0 - e * math.sin(E0)
    b = a * math.sqrt(1 - e * e)

    def accel(t_s: float, rho_N: np.ndarray) -> np.ndarray:
        M = M0 + n * t_s
        E = M
        for _ in range(8):
            E -= (E - e * math.sin(E) - M) / (1 - e * math.cos(E))
        r_c = a * (math.cos(E) - e) * p_hat + b * math.sin(E) * q_hat
        R = r_c + rho_N
        return -mu * R / np.linalg.norm(R) ** 3 + mu * r_c / np.linalg.norm(r_c) ** 3

    return accel


def reference_rho_C(cfg, x0, t_end):
    """Relative position at t_end from two separate inertial two-body propagations (DOP853, tight)."""
    mu = cfg.orbit.mu_m3_s2
    orb0 = chaser_orbit(cfg.orbit, np.array([0.0]))
    R0, w0 = orb0.R_N_from_C[0], orb0.R_N_from_C[0] @ orb0.w_c_C_rad_s[0]
    f = lambda t, y: np.concatenate([y[3:], -mu * y[:3] / np.linalg.norm(y[:3]) ** 3])  # noqa: E731
    yc = np.concatenate([orb0.r_N_m[0], orb0.v_N_m_s[0]])
    yt = yc + np.concatenate([R0 @ x0[POS], R0 @ x0[VEL] + np.cross(w0, R0 @ x0[POS])])
    ends = [solve_ivp(f, (0, t_end), y, method="DOP853", rtol=1e-13, atol=1e-7).y[:, -1] for y in (yc, yt)]
    R_end = chaser_orbit(cfg.orbit, np.array([t_end])).R_N_from_C[0]
    return R_end.T @ (ends[1][:3] - ends[0][:3])


def run_plugin(cfg, x0, nstep):
    sim = TruthSim(cfg)
    sim.set_state(x0, 0.0)
    t0 = time.perf_counter()
    sim.step(nstep)
    wall = time.perf_counter() - t0
    return wall, sim.relative_state()[POS]


def run_xfrc(cfg, x0, nstep):
    """Force from numpy into xfrc_applied before each step: held constant through RK4's stages."""
    model = model_without_plugin(cfg)
    sim = TruthSim(cfg, model=model)
    sim.set_state(x0, 0.0)
    d, b, a = sim.data, sim.target_id, sim.qpos_adr
    mass = model.body_mass[b]
    accel = make_differential_gravity(cfg)
    t0 = time.perf_counter()
    for _ in range(nstep):
        d.xfrc_applied[b, 0:3] = mass * accel(d.time, d.qpos[a : a + 3])
        mujoco.mj_step(model, d)
    wall = time.perf_counter() - t0
    return wall, TruthSim.relative_state(sim)[POS]


def run_passive_callback(cfg, x0, nstep):
    """Force from a Python passive callback: re-evaluated at every RK4 stage (exact, but slow)."""
    model = model_without_plugin(cfg)
    sim = TruthSim(cfg, model=model)
    sim.set_state(x0, 0.0)
    b = sim.target_id
    mass = model.body_mass[b]
    torque = np.zeros(3)
    accel = make_differential_gravity(cfg)

    def passive(m, d):
        rho = d.xipos[b].copy()
        force = mass * accel(d.time, rho)
        mujoco.mj_applyFT(m, d, force, torque, rho, b, d.qfrc_passive)

    mujoco.set_mjcb_passive(passive)
    try:
        t0 = time.perf_counter()
        sim.step(nstep)
        wall = time.perf_counter() - t0
    finally:
        mujoco.set_mjcb_passive(None)
    return wall, sim.relative_state()[POS]


def run_rollout(cfg, x0, nstep, nbatch, nthread):
    """MuJoCo's threaded rollout over nbatch initial conditions, with the plugin (C) in every thread."""
    sim = TruthSim(cfg)
    rng = np.random.default_rng(0)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    states = []
    for k in range(nbatch):
        x = x0.copy()
        x[POS] += rng.normal(0, 1.0, 3) * (k > 0)
        sim.set_state(x, 0.0)
        s = np.empty(mujoco.mj_stateSize(sim.model, spec))
        mujoco.mj_getState(sim.model, sim.data, s, spec)
        states.append(s)
    datas = [mujoco.MjData(sim.model) for _ in range(nthread)]
    t0 = time.perf_counter()
    out, _ = mujoco.rollout.rollout(sim.model, datas, np.array(states), nstep=nstep)
    wall = time.perf_counter() - t0
    mujoco.mj_setState(sim.model, sim.data, out[0, -1], spec)
    return wall, sim.relative_state()[POS]


def run_scipy(cfg, x0, t_end, rtol):
    """solve_ivp (DOP853) of the reference sheet's equations: relative translation + MRP/attitude dynamics."""
    o = cfg.orbit
    mu = o.mu_m3_s2
    J = np.array([[17023.3, 397.1, -2171.4], [397.1, 124825.7, 344.2], [-2171.4, 344.2, 129112.2]])
    J_inv = np.linalg.inv(J)
    orb0 = chaser_orbit(o, np.array([0.0]))

    def rhs(t, y):
        r, rd, th, thd = y[12:16]
        thdd = -2 * rd * thd / r
        x, yy, z = y[POS]
        D = ((r + x) ** 2 + yy**2 + z**2) ** 1.5
        acc = np.array([2 * thd * y[4] + thdd * yy + thd**2 * x - mu * (r + x) / D + mu / r**2,
                        -2 * thd * y[3] - thdd * x + thd**2 * yy - mu * yy / D,
                        -mu * z / D])
        p, w_r = y[MRP], y[RATE]
        G = mrp_to_dcm(p)
        w_c, wd_c = np.array([0, 0, thd]), np.array([0, 0, thdd])
        w_t = w_r + G @ w_c
        wd_r = J_inv @ (-np.cross(w_t, J @ w_t)) + np.cross(w_r, G @ w_c) - G @ wd_c
        return np.concatenate([y[VEL], acc, mrp_rate(p, w_r), wd_r, [rd, r * thd**2 - mu / r**2, thd, thdd]])

    y0 = np.concatenate([x0, [orb0.r_m[0], orb0.rdot_m_s[0], orb0.theta_rad[0], orb0.thetadot_rad_s[0]]])
    t0 = time.perf_counter()
    # integrate in pieces of at most 30 s so the MRP can be switched to its shadow set between them
    t, y = 0.0, y0
    while t < t_end - 1e-9:
        t1 = min(t_end, t + 30.0)
        sol = solve_ivp(rhs, (t, t1), y, method="DOP853", rtol=rtol, atol=rtol * 1e-3)
        y = sol.y[:, -1].copy()
        y[MRP] = mrp_shadow(y[MRP])
        t = t1
    wall = time.perf_counter() - t0
    return wall, y[POS]


def main() -> None:
    from _common import (  # bench/_common.py
        WholeFlagParser,
        count,
        description,
        out_file,
        positive,
        provenance,
        write_json,
    )

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--duration-s", type=positive, default=1000.0)
    ap.add_argument("--rollouts", type=count(), default=32)
    ap.add_argument("--threads", type=count(), default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=count(0), default=1, help="the scenario's seed (the truth's random attitude)")
    ap.add_argument("--out", type=out_file, default=os.path.join(HERE, "results", "sim_speed.json"))
    args = ap.parse_args()
    cfg = scenario_config(duration_s=args.duration_s, dt_s=args.duration_s, max_physics_dt_s=0.05, seed=args.seed)
    x0 = initial_state(cfg, np.random.default_rng(np.random.SeedSequence(cfg.seed)))
    dt = cfg.physics_dt_s
    nstep = int(round(args.duration_s / dt))
    ref = reference_rho_C(cfg, x0, args.duration_s)

    rows = []

    def record(name, wall, rho_end, sims=1, note=""):
        sim_s = sims * args.duration_s
        rows.append({"method": name, "wall_s": wall, "sim_s_per_wall_s": sim_s / wall,
                     "rho_error_m": float(np.linalg.norm(rho_end - ref)), "note": note})

    record("mujoco + C plugin", *run_plugin(cfg, x0, nstep), note=f"RK4 dt={dt:g} s, one thread")
    record("mujoco + xfrc_applied (numpy)", *run_xfrc(cfg, x0, nstep), note="force held through each RK4 step")
    record("mujoco + passive callback (numpy)", *run_passive_callback(cfg, x0, nstep), note="force at every RK4 stage")
    record(f"mujoco rollout x{args.rollouts} + C plugin", *run_rollout(cfg, x0, nstep, args.rollouts, args.threads),
           sims=args.rollouts, note=f"{args.threads} threads; error of rollout 0")
    for rtol in (1e-8, 1e-10):
        record(f"scipy solve_ivp DOP853 rtol={rtol:g}", *run_scipy(cfg, x0, args.duration_s, rtol),
               note="reference sheet equations")

    base = rows[0]["sim_s_per_wall_s"]
    for r in rows:
        r["speed_vs_plugin"] = r["sim_s_per_wall_s"] / base
    print(f"\nTruth simulation speed, {args.duration_s:g} s of the default scenario (50 m V-bar, 134.74 s tumble)")
    print(f"{'method':42s} {'sim s / wall s':>15s} {'x plugin':>9s} {'|rho err| m':>12s}  note")
    for r in rows:
        print(f"{r['method']:42s} {r['sim_s_per_wall_s']:15.0f} {r['speed_vs_plugin']:9.3f} {r['rho_error_m']:12.2e}  {r['note']}")
    result = {
        "benchmark": "sim_speed", "duration_s": args.duration_s, "physics_dt_s": dt, "threads": args.threads,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "mujoco": mujoco.__version__},
        "plugin": PLUGIN_NAME, "rows": rows,
    }
    result["provenance"] = provenance(args)
    write_json(args.out, result, indent=2)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
