"""Ray casts through a target file compiled alone (MuJoCo's mju_rayGeom / mj_rayMesh in the target's frame T):
what the Target's exact visibility and the scene builder's copy of the target are made from."""

from __future__ import annotations

import copy
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


_CAST_GROUPS = np.array([1, 0, 0, 0, 0, 0], np.uint8)  # mj_multiRay's geomgroup: the _casting copy's group 0 alone


@functools.lru_cache(maxsize=32)
def _casting(path: str, sha256: str, geoms_on: tuple[bool, ...]):
    """(model, data) of a copy of the file compiled alone whose rays meet the target's geoms where geoms_on (G,) is
    set and no other: those in geom group 0 (_CAST_GROUPS), at alpha 1 without material (mj_multiRay passes over a
    geom of alpha 0: geoms_on alone decides), every other geom in group 5; and no body's bounding volume, so that
    mj_multiRay tries every geom on each ray as mj_ray does (its culling by bounding angles, the corners of a
    geom's box seen from the ray's origin, is not conservative). Its geoms stand where the original's do."""
    import mujoco

    original, _, geom_ids, _, _ = _alone(path, sha256)
    model = copy.deepcopy(original)
    on = geom_ids[np.asarray(geoms_on, bool)]
    model.geom_group[:] = 5
    model.geom_group[on] = 0
    model.geom_matid[on] = -1
    model.geom_rgba[on, 3] = 1.0
    model.body_bvhadr[:] = -1
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    return model, data


def compiled_alone(target):
    """The file of `target` (an envisat_pose.target.Target) compiled alone (MuJoCo's MjModel, cached; treat as
    read-only): its body 'target' holds the target's geoms and sites in T, at full precision."""
    return _alone(target.path, target.sha256)[0]


def ray_hits_m(path: str, sha256: str, origins_T_m: np.ndarray, points_T_m: np.ndarray,
               geoms_on: np.ndarray) -> np.ndarray:
    """Distance along each ray from each of origins_T_m (..., 3) toward each of points_T_m (K, 3) to the first geom
    of the target where geoms_on (G,) is set (MuJoCo's mju_rayGeom / mj_rayMesh, cast K rays at a time by
    mj_multiRay on the _casting copy), m; inf where the ray meets none. (..., K)."""
    import mujoco

    _, _, _, R_W_T, p_W = _alone(path, sha256)
    model, data = _casting(path, sha256, tuple(bool(on) for on in geoms_on))
    o = np.asarray(origins_T_m, float)
    lead, o = o.shape[:-1], o.reshape(-1, 3)
    points = np.asarray(points_T_m, float).reshape(-1, 3)
    pnt_W = p_W + o @ R_W_T.T
    d_W = (points[None] - o[:, None]) @ R_W_T.T  # (P, K, 3)
    vec_W = d_W / np.sqrt(d_W[..., None, :] @ d_W[..., :, None])[..., 0]  # its norm by BLAS's dot, as a ray's own
    out = np.full((len(o), len(points)), np.inf)
    geom, dist = np.empty(len(points), np.int32), np.empty(len(points))
    for n in range(len(o) if len(points) else 0):
        mujoco.mj_multiRay(model, data, pnt_W[n], vec_W[n].ravel(), _CAST_GROUPS, 1, -1, geom, dist, None,
                           len(points), mujoco.mjMAXVAL)
        out[n, geom >= 0] = dist[geom >= 0]
    return out.reshape(*lead, len(points))
