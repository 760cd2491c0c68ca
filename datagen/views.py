"""The factory's views: per-sample seeds, random-mode views (range, bearing and attitude drawn under the
clearance and near-plane rules, sun and Earth backdrop) and sequence-mode views (the MuJoCo truth at the frame
times, the sun and the Earth's shadow along the chaser's orbit). A view carries no appearance yet
(factory.with_appearance). The closed loop draws its frames' seeds here too."""

from __future__ import annotations

import functools
import math

import numpy as np

from envisat_pose.attitude import mrp_to_dcm, quat_to_mrp, quat_to_rotmat, rotmat_to_quat
from envisat_pose.config import ConfigError
from envisat_pose.datagen.clearance import TargetBoxes, clearance_m, target_file_boxes
from envisat_pose.datagen.earth import EARTH_TEXTURE_SET_SIZE, draw_backdrop, earth_in_frame, earth_quat_C
from envisat_pose.datagen.generate_config import GenerateConfig, config_from_json, config_json
from envisat_pose.datagen.orbit import chaser_orbit
from envisat_pose.datagen.render_view import View
from envisat_pose.datagen.scenario import EARTH_RADIUS_M, scenario_config
from envisat_pose.datagen.target_scene import scene_clip_planes_m
from envisat_pose.geometry import load_camera
from envisat_pose.state import MRP, POS
from envisat_pose.target import load_target

# Camera mount on the chaser, from camera chaser_cam of models/envisat.xml (boresight +y_C, image up +x_C).
# Rows are the K axes (x right, y down, z boresight) in C.
R_K_FROM_C = load_camera().R_K_from_C
# Random mode redraws a view whose camera is too near the target or whose near plane cuts it, at most this often.
MAX_VIEW_DRAWS = 1000


def sample_seed(root_seed: int, shard_index: int, sample_index: int) -> int:
    """The seed of sample i of a shard: SeedSequence(root).spawn(...)[shard].spawn(...)[i], as one integer.

    The label stores it; `numpy.random.default_rng(seed)` replays every draw of the sample.
    """
    ss = np.random.SeedSequence(root_seed, spawn_key=(shard_index, sample_index))
    return int(ss.generate_state(1, dtype=np.uint64)[0])


def unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def view_is_clear(rho_C_m: np.ndarray, R_C_from_T: np.ndarray, boxes: TargetBoxes, margin_m: float,
                  znear_m: float) -> bool:
    """Whether the camera (at the origin of C) keeps margin_m from every target geom and every target point
    lies beyond the near plane (z_K > znear_m: nothing clipped). rho_C_m (3,) m, R_C_from_T (3, 3)."""
    c_T = -R_C_from_T.T @ rho_C_m
    if clearance_m(c_T[None], boxes)[0][0] < margin_m:
        return False
    z_K = (R_K_FROM_C @ (rho_C_m[:, None] + R_C_from_T @ boxes.corners_T_m.T))[2]
    return bool(z_K.min() > znear_m)


def sample_cap(axis: np.ndarray, half_angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A unit vector uniform on the spherical cap of half_angle_deg around the unit vector `axis`. (3,)"""
    cos_t = rng.uniform(math.cos(math.radians(half_angle_deg)), 1.0)
    phi = rng.uniform(0.0, 2.0 * math.pi)
    a = unit(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = unit(np.cross(a, helper))
    e2 = np.cross(a, e1)
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    return cos_t * a + sin_t * (math.cos(phi) * e1 + math.sin(phi) * e2)


def sample_random_view(cfg: GenerateConfig, fovy_deg: float, rng: np.random.Generator,
                       znear_m: float | None = None, boxes: TargetBoxes | None = None) -> tuple:
    """A domain-randomized view (cfg.random's draws): uniform attitude, range uniform in [range_min_m,
    range_max_m] (m; not given, sized to the target: generate_config.sized_random_m), target centre off the
    boresight within max_offset_frac of the half field of view, random or configured sun, eclipse and Earth
    backdrop by their probabilities, a relative tumble rate uniform in [0, rate_max_deg_s] about a uniform axis
    (in x; the translation rate is zero).

    A pose whose camera comes within keepout_margin_m of any target geom (body, boom, array, clutter), or whose
    near plane (znear_m, m; default that of cfg.target's scene, target_scene.scene_clip_planes_m) cuts the target,
    is drawn again from the same rng: deterministic, at most MAX_VIEW_DRAWS times (then ConfigError). boxes: the
    target (default cfg.target's).

    Returns (View, x (12,), scene dict) without an appearance (see with_appearance). In random mode C is the camera
    mount's frame; the Earth's direction is drawn independently of it, except in views with the Earth backdrop (a
    share earth_probability): there the Earth (distance, nadir toward the image, attitude, texture) comes from
    earth.draw_backdrop with a generator spawned from rng, so poses, labels and the later draws of rng are the
    same with and without the Earth.
    """
    boxes = boxes if boxes is not None else target_file_boxes(cfg.target)
    znear_m = znear_m if znear_m is not None else scene_clip_planes_m(load_target(cfg.target))[0]
    r = cfg.random
    tan_half = math.tan(math.radians(fovy_deg) / 2.0)
    for _ in range(MAX_VIEW_DRAWS):
        q = unit(rng.standard_normal(4))
        range_m = rng.uniform(r.range_min_m, r.range_max_m)
        off = rng.uniform(-1.0, 1.0, size=2) * r.max_offset_frac * tan_half
        rho_C = R_K_FROM_C.T @ (range_m * unit([off[0], off[1], 1.0]))
        if view_is_clear(rho_C, quat_to_rotmat(q), boxes, r.keepout_margin_m, znear_m):
            break
    else:
        raise ConfigError("random.range_min_m", r.range_min_m,
                          f"ranges that allow a clear view: none of {MAX_VIEW_DRAWS} draws kept the camera "
                          f"random.keepout_margin_m = {r.keepout_margin_m:g} m from the target with all of it beyond "
                          f"the near plane ({znear_m:.2f} m)")
    if cfg.sun_dir is not None:
        sun_C = unit(cfg.sun_dir)
    else:
        backlit = rng.random() < r.backlit_probability
        sun_C = sample_cap(-unit(rho_C), 180.0 if backlit else r.sun_phase_max_deg, rng)
    eclipse = bool(rng.random() < r.eclipse_probability)
    earth_draw = bool(rng.random() < cfg.earth_probability)
    earth_C = unit(rng.standard_normal(3))
    w_T = unit(rng.standard_normal(3)) * math.radians(rng.uniform(0.0, r.rate_max_deg_s))
    view = View(rho_C, quat_to_rotmat(q), None if eclipse else sun_C, earth_C, earth_backdrop=earth_draw)
    if earth_draw:
        import dataclasses

        K = load_camera().scaled(cfg.resolution_px, cfg.resolution_px).K
        nadir_K, r_m, R_K_from_E, tex = draw_backdrop(rng.spawn(1)[0], r.earth_orbit_radius_m, K,
                                                      cfg.resolution_px, None if eclipse else R_K_FROM_C @ sun_C)
        view = dataclasses.replace(view, earth_dir_C=R_K_FROM_C.T @ nadir_K, earth_distance_m=r_m,
                                   earth_quat_C=rotmat_to_quat(R_K_FROM_C.T @ R_K_from_E), earth_texture=tex)
    x = np.concatenate([rho_C, np.zeros(3), quat_to_mrp(q), w_T])
    scene = {"mode": "random", "sun_dir_cam": (R_K_FROM_C @ sun_C).round(9).tolist(), "eclipse": eclipse,
             "earth_backdrop": earth_draw}
    return view, x, scene


@functools.lru_cache(maxsize=16)
def sequence_frames(cfg_json: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The truth of a sequence-mode config at its frame times: (t_s (N,), x (N, 12), sun_dir_C (N, 3),
    eclipse (N,) bool, nadir_C (N, 3) with chaser_r_m folded in as its norm)."""
    from envisat_pose.datagen.truth import sequence_truth  # MuJoCo: not for a verb's parser (factory reads this)

    cfg = config_from_json(cfg_json)
    seq = cfg.sequence
    scen, t_s, x = sequence_truth(seq.scenario, seq.range_scale, cfg.num_images, seq.frame_dt_s, cfg.seed, cfg.target)
    orb = chaser_orbit(scen.orbit, t_s)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(2**32 - 1,)))
    sun_N = unit(cfg.sun_dir) if cfg.sun_dir is not None else unit(rng.standard_normal(3))
    sun_C = np.einsum("nji,j->ni", orb.R_N_from_C, sun_N)
    # cylindrical Earth shadow: behind the Earth (r . s < 0) and within one Earth radius of the sun line
    along = orb.r_N_m @ sun_N
    perp = np.linalg.norm(orb.r_N_m - along[:, None] * sun_N, axis=1)
    eclipse = (along < 0) & (perp < EARTH_RADIUS_M)
    nadir_C = np.zeros((len(t_s), 3))
    nadir_C[:, 0] = -orb.r_m  # the Earth's centre is at -r x_C
    return t_s, x, sun_C, eclipse, nadir_C


@functools.lru_cache(maxsize=16)
def sequence_earth(cfg_json: str) -> tuple[np.ndarray, np.ndarray, int]:
    """The Earth of a sequence-mode config at its frame times: (quat_C (N, 4), the Earth's attitude in C (it
    turns with the orbit and its sidereal rate from an angle drawn from the seed); in_frame (N,) bool, whether
    its disc reaches the image; texture index)."""

    cfg = config_from_json(cfg_json)
    t_s, _, _, _, nadir_C = sequence_frames(cfg_json)
    seq = cfg.sequence
    scen = scenario_config(seq.scenario, duration_s=max(cfg.num_images - 1, 1) * seq.frame_dt_s,
                           dt_s=seq.frame_dt_s, seed=cfg.seed)
    orb = chaser_orbit(scen.orbit, t_s)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(2**32 - 1, 0xEA27)))
    theta0 = float(rng.uniform(0.0, 2.0 * math.pi))
    texture = int(rng.integers(0, EARTH_TEXTURE_SET_SIZE))
    K = load_camera().scaled(cfg.resolution_px, cfg.resolution_px).K
    in_frame = np.array([earth_in_frame(R_K_FROM_C @ n, float(np.linalg.norm(n)), K, cfg.resolution_px)
                         for n in nadir_C], dtype=bool)
    return earth_quat_C(t_s, orb.R_N_from_C, theta0), in_frame, texture


def sequence_view(cfg: GenerateConfig, k: int) -> tuple:
    """Frame k of a sequence-mode config: (View, x (12,), scene dict). The Earth is drawn (earth_probability
    above 0) in the frames where its disc reaches the image."""
    t_s, x, sun_C, eclipse, nadir_C = sequence_frames(config_json(cfg))
    xk = x[k]
    earth = False
    quat, texture = None, 0
    if cfg.earth_probability > 0:
        quats, in_frame, texture = sequence_earth(config_json(cfg))
        earth, quat = bool(in_frame[k]), quats[k]
    r_m = float(np.linalg.norm(nadir_C[k]))
    view = View(xk[POS], mrp_to_dcm(xk[MRP]).T, None if eclipse[k] else sun_C[k], unit(nadir_C[k]), r_m,
                earth_backdrop=earth, earth_quat_C=quat, earth_texture=texture)
    scene = {"mode": "sequence", "t_s": float(t_s[k]), "sun_dir_cam": (R_K_FROM_C @ sun_C[k]).round(9).tolist(),
             "eclipse": bool(eclipse[k]), "earth_backdrop": earth}
    return view, xk, scene
