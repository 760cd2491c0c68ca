"""Truth trajectories: simulate a scenario with MuJoCo and write the design's truth contract (run.npz)."""

from __future__ import annotations

import functools
import json

import numpy as np

from envisat_pose.attitude import mrp_to_dcm, quat_to_mrp
from envisat_pose.contracts import TruthTrajectory
from envisat_pose.datagen.clearance import check_keepout, target_boxes
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.scenario import (
    ScenarioConfig,
    scenario_dict,
    sequence_scenario,
    truth_config_json,
)
from envisat_pose.datagen.sim import TruthSim
from envisat_pose.target import load_target


def initial_state(cfg: ScenarioConfig, rng: np.random.Generator) -> np.ndarray:
    """The 12-state at t = 0: configured translation, configured or uniformly random attitude, the tumble.

    The random attitude is a normalised 4D Gaussian (uniform on SO(3)), drawn from `rng`.
    """
    if cfg.target.p0_mrp is None:
        p0 = quat_to_mrp(rng.standard_normal(4))
    else:
        p0 = np.asarray(cfg.target.p0_mrp, dtype=float)
    w_c0_C = chaser_orbit(cfg.orbit, np.array([0.0])).w_c_C_rad_s[0]
    w_r0_T = cfg.target.w0_T_rad_s - mrp_to_dcm(p0) @ w_c0_C
    return np.concatenate([cfg.relative.rho0_C_m, cfg.relative.rhodot0_C_m_s, p0, w_r0_T])


def simulate_truth(cfg: ScenarioConfig, progress: bool = False) -> TruthTrajectory:
    """Simulate the scenario with MuJoCo (RK4, relative gravity in the C plugin) and sample it every dt_s; the
    named scenario cfg was made from (cfg.scenario, where one) is recorded in the truth's config."""
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed))
    sim = TruthSim(cfg)
    n, K = cfg.n_out, len(sim.target.keypoint_names)
    t_s = np.arange(n) * cfg.dt_s
    x = np.empty((n, 12))
    corners_C_m = np.empty((n, K, 3))
    corners_px = np.empty((n, K, 2))
    in_frame = np.empty((n, K), dtype=bool)
    c_T_m = np.empty((n, 3))
    sim.set_state(initial_state(cfg, rng), 0.0)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="step", desc="simulate", mininterval=0.5)
    chunk = max(1, n // 200)
    for k in range(n):
        if k > 0:
            sim.step(cfg.substeps)
            sim.data.time = t_s[k]  # remove the float round-off of summed steps
            sim.sync_chaser()
        x[k] = sim.relative_state()
        corners_C_m[k], corners_px[k], in_frame[k], c_T_m[k] = sim.corner_observation()
        if bar is not None and (k % chunk == 0 or k == n - 1):
            bar.update(k + 1 - bar.n)
    if bar is not None:
        bar.close()
    orb = chaser_orbit(cfg.orbit, t_s)
    traj = TruthTrajectory(
        t_s=t_s,
        x=x,
        chaser_r_m=orb.r_m,
        chaser_rdot_m_s=orb.rdot_m_s,
        chaser_theta_rad=orb.theta_rad,
        chaser_thetadot_rad_s=orb.thetadot_rad_s,
        corners_C_m=corners_C_m,
        visible=sim.target.truth_visible(c_T_m),
        corners_px=corners_px,
        in_frame=in_frame,
        config_json=truth_config_json(cfg, sim.target.sha256),
    )
    check_clearance(cfg, traj, sim.model)
    return traj


def sequence_truth(scenario: str, range_scale: float, num_images: int, frame_dt_s: float, seed: int,
                   target: str) -> tuple[ScenarioConfig, np.ndarray, np.ndarray]:
    """The truth an image-factory sequence shows: the named scenario of `target` (its file) started range_scale
    times as far (scenario.sequence_scenario), simulated from `seed` over num_images frames frame_dt_s apart: (its
    ScenarioConfig, t_s (N,), x (N, 12)). Cached: a sequence's config sizes its depth scale from it
    (generate_config.sequence_depth_m), then its frames read it (views.sequence_frames); cached by the target
    file's sha256 and the scenario's tables too, so an edited file (its inertia, a scenario file's start) is
    simulated again, as the target's other caches are."""
    return _sequence_truth(scenario, range_scale, num_images, frame_dt_s, seed, target,
                           load_target(target).sha256, json.dumps(scenario_dict(scenario), sort_keys=True))


@functools.lru_cache(maxsize=16)
def _sequence_truth(scenario: str, range_scale: float, num_images: int, frame_dt_s: float, seed: int, target: str,
                    target_sha256: str, scenario_json: str) -> tuple[ScenarioConfig, np.ndarray, np.ndarray]:
    """sequence_truth, simulated; the last two arguments are the cache's key only (the files' contents)."""
    scen = sequence_scenario(scenario, range_scale, num_images, frame_dt_s, seed, target)
    traj = simulate_truth(scen)
    t_s, x = traj.t_s[:num_images].copy(), traj.x[:num_images].copy()
    t_s.flags.writeable = x.flags.writeable = False  # shared by every caller of the cache
    return scen, t_s, x


def check_clearance(cfg: ScenarioConfig, traj: TruthTrajectory, model) -> None:
    """ConfigError (naming relative.rho0_C_m, the time and the distance) when the simulated chaser comes
    closer than cfg.keepout_margin_m to any geom of the target (body, boom, solar array) of `model`."""
    check_keepout(traj.t_s, traj.x, cfg.keepout_margin_m, target_boxes(model), field="relative.rho0_C_m",
                  value=list(cfg.relative.rho0_C_m))
