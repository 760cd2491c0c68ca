"""Truth trajectories: simulate a scenario with MuJoCo and write the design's truth contract (run.npz)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np

from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.scenario import ScenarioConfig
from envisat_pose.datagen.sim import TruthSim
from envisat_pose.attitude import mrp_to_dcm, quat_to_mrp
from envisat_pose.config import InputError, to_json
from envisat_pose.geometry import load_geometry, visible_corners
from envisat_pose.io import save_npz


@dataclass
class TruthTrajectory:
    """A simulated truth, the contract between the simulator and everything downstream.

    t_s: (N,) s. x: (N, 12) = (rho_C_m, rhodot_C_m_s, p_mrp with |p| <= 1, w_r_T_rad_s), the paper's state.
    chaser_r_m, chaser_rdot_m_s, chaser_theta_rad, chaser_thetadot_rad_s: (N,) the chaser's polar orbit.
    corners_C_m: (N, 8, 3) corners A-H relative to the chaser, in C. visible: (N, 8) bool, exact face test.
    config_json: the full validated ScenarioConfig as JSON.
    """

    t_s: np.ndarray
    x: np.ndarray
    chaser_r_m: np.ndarray
    chaser_rdot_m_s: np.ndarray
    chaser_theta_rad: np.ndarray
    chaser_thetadot_rad_s: np.ndarray
    corners_C_m: np.ndarray
    visible: np.ndarray
    config_json: str

    def save(self, path: str) -> None:
        """Write an .npz atomically (temp file, then rename); the same trajectory gives the same bytes."""
        save_npz(path, {f.name: getattr(self, f.name) for f in dataclasses.fields(self)})

    @classmethod
    def load(cls, path: str) -> "TruthTrajectory":
        """Read a run.npz written by `envisat simulate` (no pickles are ever loaded)."""
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [f.name for f in dataclasses.fields(cls) if f.name not in z.files]
                if missing:
                    raise InputError(f"{path!r} is not a truth trajectory: missing keys {missing}")
                data = {f.name: z[f.name] for f in dataclasses.fields(cls)}
        except FileNotFoundError:
            raise InputError(f"truth file {path!r} does not exist") from None
        except (OSError, ValueError) as err:
            raise InputError(f"truth file {path!r} cannot be read as .npz: {err}") from None
        data["config_json"] = str(data["config_json"])
        return cls(**data)

    @property
    def config(self) -> dict:
        return json.loads(self.config_json)


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


def corners_in_chaser_frame(x: np.ndarray) -> np.ndarray:
    """Corner positions relative to the chaser in C: rho + Gamma^T v_i. (..., 12) -> (..., 8, 3) m."""
    v_T = load_geometry().corners_T_m
    G = mrp_to_dcm(x[..., 6:9])
    return x[..., None, 0:3] + np.einsum("...ij,ki->...kj", G, v_T)  # (Gamma^T v_k)_j = G_ij v_ki


def corner_visibility(x: np.ndarray) -> np.ndarray:
    """Exact face test from the chaser position in T, c_T = -Gamma rho. (..., 12) -> (..., 8) bool."""
    c_T = -np.einsum("...ij,...j->...i", mrp_to_dcm(x[..., 6:9]), x[..., 0:3])
    return visible_corners(c_T)


def simulate(cfg: ScenarioConfig, progress: bool = False) -> TruthTrajectory:
    """Simulate the scenario with MuJoCo (RK4, relative gravity in the C plugin) and sample it every dt_s."""
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed))
    sim = TruthSim(cfg)
    n = cfg.n_out
    t_s = np.arange(n) * cfg.dt_s
    x = np.empty((n, 12))
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
        x[k] = sim.relative_state()
        if bar is not None and (k % chunk == 0 or k == n - 1):
            bar.update(k + 1 - bar.n)
    if bar is not None:
        bar.close()
    orb = chaser_orbit(cfg.orbit, t_s)
    return TruthTrajectory(
        t_s=t_s,
        x=x,
        chaser_r_m=orb.r_m,
        chaser_rdot_m_s=orb.rdot_m_s,
        chaser_theta_rad=orb.theta_rad,
        chaser_thetadot_rad_s=orb.thetadot_rad_s,
        corners_C_m=corners_in_chaser_frame(x),
        visible=corner_visibility(x),
        config_json=to_json(cfg),
    )
