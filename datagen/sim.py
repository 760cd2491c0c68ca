"""The MuJoCo truth: the model built from the scenario's target file (default models/envisat.xml; another
target is put into ENVISAT's scene, datagen/target_scene.py) and a thin stateful wrapper around it.

World frame W: non-rotating (axes of N), origin at the chaser. The target body's frame is T (origin at its
centre of mass). The chaser is a mocap body turned to LVLH (C) at every `set_state` / `sync_chaser`.
State conversion to and from the paper's 12-state x = (rho_C_m, rhodot_C_m_s, p_mrp, w_r_T_rad_s) happens here,
at the boundary (shared/reference.md, section 3).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import mujoco
import numpy as np

from envisat_pose.attitude import dcm_to_mrp, mrp_to_dcm, quat_to_rotmat, rotmat_to_quat
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.plugin import PLUGIN_NAME
from envisat_pose.datagen.scenario import ScenarioConfig
from envisat_pose.datagen.target_scene import scene_xml
from envisat_pose.geometry import CAMERA_NAME, CORNER_NAMES
from envisat_pose.state import MRP, POS, RATE, VEL
from envisat_pose.target import load_target

CORNER_SITES = tuple(f"corner_{c}" for c in CORNER_NAMES)


def plugin_attributes(cfg: ScenarioConfig) -> dict[str, str]:
    """The gravity plugin's attributes for a scenario (the chief's orbit, epoch t = 0)."""
    o = cfg.orbit
    values = {
        "mu_m3_s2": o.mu_m3_s2, "a_m": o.a_m, "e": o.e, "i_deg": o.i_deg, "raan_deg": o.raan_deg,
        "argp_deg": o.argp_deg, "nu0_deg": o.nu0_deg, "epoch_s": 0.0,
        "gravity_gradient": 1 if cfg.target.gravity_gradient else 0,
    }
    return {k: repr(float(v)) if not isinstance(v, int) else str(v) for k, v in values.items()}


def model_xml(cfg: ScenarioConfig, path: str | None = None) -> str:
    """The MJCF text with the scenario's orbit in the plugin attributes and its physics step: the scene of
    `path` if given (an MJCF scene file), else of the scenario's target file (cfg.target.file)."""
    if path is not None:
        root = ET.parse(path).getroot()
    else:
        root = ET.fromstring(scene_xml(load_target(cfg.target.file, "target.file")))
    attrs = plugin_attributes(cfg)
    plugin = next(p for p in root.iter("plugin") if p.get("plugin") == PLUGIN_NAME)
    for conf in plugin.iter("config"):
        if conf.get("key") in attrs:
            conf.set("value", attrs[conf.get("key")])
    root.find("option").set("timestep", repr(cfg.physics_dt_s))
    return ET.tostring(root, encoding="unicode")


def build_model(cfg: ScenarioConfig, path: str | None = None) -> mujoco.MjModel:
    """Compile the model for a scenario."""
    return mujoco.MjModel.from_xml_string(model_xml(cfg, path))


class TruthSim:
    """The MuJoCo model and data of one truth simulation, addressed by name."""

    def __init__(self, cfg: ScenarioConfig, model: mujoco.MjModel | None = None):
        self.cfg = cfg
        self.model = model if model is not None else build_model(cfg)
        self.data = mujoco.MjData(self.model)
        self.target_id = self.model.body("target").id
        self.qpos_adr = self.model.joint("target_free").qposadr[0]
        self.qvel_adr = self.model.joint("target_free").dofadr[0]
        self.mocap_id = self.model.body("chaser").mocapid[0]

        self.target = load_target(cfg.target.file, "target.file")
        self.corner_site_ids = np.array([self.model.site(n).id for n in self.target.keypoint_sites])
        self.cam_id = self.model.camera(CAMERA_NAME).id

    def set_state(self, x: np.ndarray, t_s: float) -> None:
        """Put the target at the relative 12-state x at time t_s and turn the chaser to LVLH."""
        x = np.asarray(x, dtype=float)
        orb = chaser_orbit(self.cfg.orbit, np.array([t_s]))
        R_N_C = orb.R_N_from_C[0]
        w_c_C = orb.w_c_C_rad_s[0]
        rho_C, rhodot_C, p, w_r_T = x[POS], x[VEL], x[MRP], x[RATE]
        G = mrp_to_dcm(p)  # R_T_from_C
        d = self.data
        d.time = t_s
        a, v = self.qpos_adr, self.qvel_adr
        d.qpos[a : a + 3] = R_N_C @ rho_C
        d.qpos[a + 3 : a + 7] = rotmat_to_quat(R_N_C @ G.T)
        d.qvel[v : v + 3] = R_N_C @ (rhodot_C + np.cross(w_c_C, rho_C))
        # MuJoCo's free joint keeps the angular velocity in the body frame: w_t (T relative to N) in T.
        d.qvel[v + 3 : v + 6] = w_r_T + G @ w_c_C
        d.mocap_pos[self.mocap_id] = 0.0
        d.mocap_quat[self.mocap_id] = rotmat_to_quat(R_N_C)
        mujoco.mj_forward(self.model, d)

    def sync_chaser(self) -> None:
        """Turn the chaser mocap body to LVLH at the current time and recompute derived quantities."""
        R_N_C = chaser_orbit(self.cfg.orbit, np.array([self.data.time])).R_N_from_C[0]
        self.data.mocap_quat[self.mocap_id] = rotmat_to_quat(R_N_C)
        mujoco.mj_forward(self.model, self.data)

    def relative_state(self) -> np.ndarray:
        """The paper's 12-state of the current MuJoCo state: (rho_C_m, rhodot_C_m_s, p_mrp, w_r_T_rad_s)."""
        d = self.data
        orb = chaser_orbit(self.cfg.orbit, np.array([d.time]))
        R_N_C = orb.R_N_from_C[0]
        w_c_C = orb.w_c_C_rad_s[0]
        a, v = self.qpos_adr, self.qvel_adr
        rho_C = R_N_C.T @ d.qpos[a : a + 3]
        rhodot_C = R_N_C.T @ d.qvel[v : v + 3] - np.cross(w_c_C, rho_C)
        G = (R_N_C.T @ quat_to_rotmat(d.qpos[a + 3 : a + 7])).T  # R_T_from_C = (R_C_from_T)^T
        p = dcm_to_mrp(G)
        w_r_T = d.qvel[v + 3 : v + 6] - G @ w_c_C
        return np.concatenate([rho_C, rhodot_C, p, w_r_T])

    def corner_observation(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What the chaser sees of the K keypoints (ENVISAT: corners A-H) now, from MuJoCo's own sites and camera
        (sync_chaser first).

        Returns corners_C_m (K, 3) relative to the chaser in C; corners_px (K, 2) through camera chaser_cam
        (intrinsics from MuJoCo's compiled fovy and resolution, OpenCV pixel convention); in_frame (K,) bool,
        in front of the camera and inside the image; c_T_m (3,) the chaser's position in T.
        """
        m, d = self.model, self.data
        R_N_C = d.mocap_quat[self.mocap_id]
        R_N_C = quat_to_rotmat(R_N_C)
        chaser_W = d.mocap_pos[self.mocap_id]
        sites_W = d.site_xpos[self.corner_site_ids]
        corners_C = (sites_W - chaser_W) @ R_N_C
        # MuJoCo's camera frame: x right, y up, looking along -z; K = (x, -y, -z)
        R_W_cam = d.cam_xmat[self.cam_id].reshape(3, 3)
        p_K = (sites_W - d.cam_xpos[self.cam_id]) @ R_W_cam * np.array([1.0, -1.0, -1.0])
        width, height = (int(v) for v in m.cam_resolution[self.cam_id])
        f_px = 0.5 * height / np.tan(np.radians(m.cam_fovy[self.cam_id]) / 2.0)
        z = p_K[:, 2]
        safe_z = np.where(z > 0, z, 1.0)
        uv = f_px * p_K[:, :2] / safe_z[:, None] + 0.5 * (np.array([width, height]) - 1.0)
        in_frame = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5) \
            & (uv[:, 1] < height - 0.5)
        R_W_T = d.xmat[self.target_id].reshape(3, 3)
        c_T = (chaser_W - d.xpos[self.target_id]) @ R_W_T
        return corners_C, uv, in_frame, c_T

    def step(self, nstep: int) -> None:
        """Advance nstep RK4 steps (mj_step: mj_step1/2 would fall back to Euler)."""
        mujoco.mj_step(self.model, self.data, nstep=nstep)
