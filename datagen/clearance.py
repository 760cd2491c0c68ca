"""The whole target as oriented boxes, and how far the chaser (the camera) stays from it.

Every geom of body `target` in the MuJoCo model (the six face plates, the boom, the solar array) becomes
the oriented box of MuJoCo's own local bounding box (`geom_aabb`: a box is itself, a cylinder its bounding
box), placed in T by `geom_pos` / `geom_quat`; the main body's solid box (its corner sites) is added. T is the target body's frame (origin at the centre of mass),
as everywhere in the project. Distances are signed: positive outside a box, negative inside.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import mrp_to_dcm, quat_to_rotmat
from envisat_pose.config import ConfigError
from envisat_pose.datagen.target_scene import scene_xml
from envisat_pose.geometry import CORNER_NAMES, model_path
from envisat_pose.state import MRP, POS, RATE, VEL
from envisat_pose.target import load_target

# 8 sign patterns of a box's corners, (8, 3)
_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)


@dataclass(frozen=True)
class TargetBoxes:
    """The target's geoms as oriented boxes in T.

    names: (G,) geom names. centre_T_m: (G, 3) box centres, m. R_T_from_box: (G, 3, 3) box axes in T.
    half_m: (G, 3) half sizes along the box axes, m.
    """

    names: tuple[str, ...]
    centre_T_m: np.ndarray
    R_T_from_box: np.ndarray
    half_m: np.ndarray

    @property
    def corners_T_m(self) -> np.ndarray:
        """Every box corner in T, (8 G, 3) m: their convex hull holds the whole target."""
        local = _SIGNS[None, :, :] * self.half_m[:, None, :]  # (G, 8, 3)
        pts = self.centre_T_m[:, None, :] + np.einsum("gij,gkj->gki", self.R_T_from_box, local)
        return pts.reshape(-1, 3)

    @property
    def reach_m(self) -> float:
        """Farthest point of the target from its centre of mass, m (the solar array's outer corner)."""
        return float(np.linalg.norm(self.corners_T_m, axis=1).max())


def target_boxes(model) -> TargetBoxes:
    """The geoms of body `target` of a compiled MjModel as oriented boxes in T (the body frame), plus the
    main body as one solid box (named 'body', the bounding box of the corner sites): its faces are thin
    plates, and the inside of the box is target too."""
    body = model.body("target").id
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body]
    names = tuple(model.geom(g).name for g in geoms) + ("body",)
    R_geom = np.array([quat_to_rotmat(model.geom_quat[g]) for g in geoms])  # R_T_from_geom
    aabb = np.array([model.geom_aabb[g] for g in geoms])  # centre (3) and half sizes (3), geom frame
    centre = np.array([model.geom_pos[g] for g in geoms]) + np.einsum("gij,gj->gi", R_geom, aabb[:, :3])
    try:
        sites = np.array([model.site_pos[model.site(f"corner_{c}").id] for c in CORNER_NAMES])
    except KeyError:  # a target without corner_ sites: its own geoms only
        return TargetBoxes(names[:-1], centre, R_geom, aabb[:, 3:].copy())
    lo, hi = sites.min(axis=0), sites.max(axis=0)
    return TargetBoxes(names, np.vstack([centre, 0.5 * (lo + hi)]), np.concatenate([R_geom, np.eye(3)[None]]),
                       np.vstack([aabb[:, 3:], 0.5 * (hi - lo)]))


@functools.lru_cache(maxsize=16)
def _scene_model(path: str, sha256: str):
    """The compiled scene of a target file (its sha256 in the key: an edited file compiles again)."""
    import mujoco

    return mujoco.MjModel.from_xml_string(scene_xml(load_target(path)))


def target_file_boxes(given: str, field: str = "target") -> TargetBoxes:
    """target_boxes of the scene of a `target` file (ENVISAT: project_target_boxes); a bad file is a ConfigError
    naming `field`."""

    t = load_target(given, field)
    return _file_boxes(t.path, t.sha256)


@functools.lru_cache(maxsize=16)
def _file_boxes(path: str, sha256: str) -> TargetBoxes:
    return target_boxes(_scene_model(path, sha256))


@functools.lru_cache(maxsize=1)
def _project_model():
    import mujoco

    return mujoco.MjModel.from_xml_path(model_path())


@functools.lru_cache(maxsize=1)
def project_target_boxes() -> TargetBoxes:
    """target_boxes of models/envisat.xml (compiled once per process)."""
    return target_boxes(_project_model())


def project_znear_m() -> float:
    """The near clipping plane of models/envisat.xml, m: visual/map znear times the model's extent."""
    m = _project_model()
    return float(m.vis.map.znear * m.stat.extent)


def box_distance_m(points_T_m: np.ndarray, boxes: TargetBoxes) -> np.ndarray:
    """Signed distance of each point to each box, m: (N, 3) -> (N, G); negative inside a box."""
    p = np.asarray(points_T_m, dtype=float)[:, None, :] - boxes.centre_T_m[None]  # (N, G, 3)
    local = np.abs(np.einsum("gji,ngj->ngi", boxes.R_T_from_box, p))  # box axes: R^T (p - c)
    q = local - boxes.half_m[None]
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(q.max(axis=-1), 0.0)
    return outside + inside


def clearance_m(points_T_m: np.ndarray, boxes: TargetBoxes) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each point to the nearest part of the target, m, and that part's geom index. (N,), (N,)."""
    d = box_distance_m(points_T_m, boxes)
    nearest = np.argmin(d, axis=1)
    return d[np.arange(len(d)), nearest], nearest


def chaser_in_T_m(x: np.ndarray) -> np.ndarray:
    """The chaser's position in T, c_T = -Gamma(p) rho, from 12-states (N, 12) -> (N, 3) m."""
    x = np.asarray(x, dtype=float)
    return -np.einsum("nij,nj->ni", mrp_to_dcm(x[:, MRP]), x[:, POS])


def chaser_speed_in_T_m_s(x: np.ndarray) -> np.ndarray:
    """|d c_T / dt| = |Gamma rho' + w_r x c_T|, m/s, (N, 12) -> (N,): how fast the chaser moves past the target."""
    x = np.asarray(x, dtype=float)
    G = mrp_to_dcm(x[:, MRP])
    c_T = -np.einsum("nij,nj->ni", G, x[:, POS])
    v = np.einsum("nij,nj->ni", G, x[:, VEL]) + np.cross(x[:, RATE], c_T)
    return np.linalg.norm(v, axis=1)


def interval_lower_bound_m(d_m: np.ndarray, speed_m_s: np.ndarray, dt_s: float) -> np.ndarray:
    """Least clearance possible between consecutive samples, m, (N,) -> (N - 1,).

    Clearance changes no faster than the chaser moves in T (a distance function is 1-Lipschitz), so on
    [t_k, t_k+1] it stays above (d_k + d_k+1 - v dt) / 2 with v the larger speed of the two ends.
    """
    v = np.maximum(speed_m_s[:-1], speed_m_s[1:])
    return np.minimum(np.minimum(d_m[:-1], d_m[1:]), 0.5 * (d_m[:-1] + d_m[1:] - v * dt_s))


def lower_bound_m(d_m: np.ndarray, speed_m_s: np.ndarray, dt_s: float) -> float:
    """Least clearance over the whole sampled interval, m: the samples and the bound between them."""
    if len(d_m) < 2:
        return float(np.min(d_m))
    return float(interval_lower_bound_m(d_m, speed_m_s, dt_s).min())


def check_keepout(t_s: np.ndarray, x: np.ndarray, margin_m: float, boxes: TargetBoxes,
                  field: str = "relative.rho0_C_m", value=None) -> None:
    """ConfigError unless the chaser keeps margin_m from every part of the target along the trajectory.

    t_s: (N,) s, evenly spaced. x: (N, 12) the paper's states. Two tiers: the distance to the centre of
    mass minus the target's reach (attitude-free, changes only with the slow translation), and, where
    that is short, the distance to each geom box at the samples with the bound between samples.
    The error names `field`, the time and the distance.
    """
    t_s, x = np.asarray(t_s, dtype=float), np.asarray(x, dtype=float)
    dt_s = float(t_s[1] - t_s[0]) if len(t_s) > 1 else 0.0
    sphere = np.linalg.norm(x[:, POS], axis=1) - boxes.reach_m
    if lower_bound_m(sphere, np.linalg.norm(x[:, VEL], axis=1), dt_s) >= margin_m:
        return
    d, nearest = clearance_m(chaser_in_T_m(x), boxes)
    value = value if value is not None else x[0, POS].round(6).tolist()
    expect = f"a relative trajectory that keeps the chaser keepout_margin_m = {margin_m:g} m from every part of " \
             "the target (body, boom, solar array)"
    k = int(np.argmax(d < margin_m)) if np.any(d < margin_m) else None
    if k is not None:
        inside = " (inside it)" if d[k] < 0 else ""
        raise ConfigError(field, value, f"{expect}; at t = {t_s[k]:g} s the chaser is {d[k]:.2f} m from geom "
                                        f"'{boxes.names[nearest[k]]}'{inside}")
    if len(t_s) >= 2:
        low = interval_lower_bound_m(d, chaser_speed_in_T_m_s(x), dt_s)
        if low.min() < margin_m:
            j = int(np.argmax(low < margin_m))
            raise ConfigError(field, value, f"{expect}; between t = {t_s[j]:g} and {t_s[j + 1]:g} s the chaser "
                                            f"may come within {max(low[j], 0.0):.2f} m of the target (sampled every "
                                            f"{dt_s:g} s: a shorter dt_s resolves it)")


def farthest_depth_m(rho_K_m: np.ndarray, R_K_from_T: np.ndarray, boxes: TargetBoxes) -> np.ndarray:
    """Largest depth along the boresight of any target point per view, m. rho_K_m (N, 3), R_K_from_T (N, 3, 3)."""
    z = rho_K_m[:, 2:3] + np.einsum("nj,kj->nk", R_K_from_T[:, 2, :], boxes.corners_T_m)
    return z.max(axis=1)

