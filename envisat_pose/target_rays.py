"""Ray casts through a target file compiled alone (MuJoCo's mju_rayGeom / mj_rayMesh in the target's frame T):
what the Target's exact visibility and the scene builder's copy of the target are made from."""

from __future__ import annotations

import functools

import numpy as np

from envisat_pose.target_file import compile_alone


@functools.lru_cache(maxsize=16)
def _alone(path: str, sha256: str):
    """(model, data, the target's geom ids (G,), R_W_from_T (3, 3), p_W (3,)) of the file compiled alone, its
    kinematics done: the frame the rays are cast in."""
    import mujoco

    model = compile_alone(path)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    body = model.body("target").id
    return (model, data, np.flatnonzero(model.geom_bodyid == body), data.xmat[body].reshape(3, 3).copy(),
            data.xpos[body].copy())


def compiled_alone(target):
    """The file of `target` (an envisat_pose.target.Target) compiled alone (MuJoCo's MjModel, cached; treat as
    read-only): its body 'target' holds the target's geoms and sites in T, at full precision."""
    return _alone(target.path, target.sha256)[0]


def ray_hits_m(path: str, sha256: str, origin_T_m: np.ndarray, points_T_m: np.ndarray,
               geoms_on: np.ndarray) -> np.ndarray:
    """Distance along each ray from origin_T_m (3,) toward points_T_m (N, 3) to the first geom of the target
    where geoms_on (G,) is set (MuJoCo's mju_rayGeom / mj_rayMesh), m; inf where the ray meets none. (N,)."""
    import mujoco

    model, data, geom_ids, R_W_T, p_W = _alone(path, sha256)
    pnt = p_W + R_W_T @ np.asarray(origin_T_m, float)
    out = np.full(len(points_T_m), np.inf)
    for n, x in enumerate(np.asarray(points_T_m, float)):
        d = R_W_T @ (x - origin_T_m)
        vec = d / np.linalg.norm(d)
        for g, on in zip(geom_ids, geoms_on):
            if not on:
                continue
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                hit = mujoco.mj_rayMesh(model, data, int(g), pnt, vec)
            else:
                hit = mujoco.mju_rayGeom(data.geom_xpos[g], data.geom_xmat[g], model.geom_size[g], pnt, vec,
                                         int(model.geom_type[g]))
            if hit >= 0:
                out[n] = min(out[n], hit)
    return out
