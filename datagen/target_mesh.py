"""The target's surface as one triangle mesh in its body frame T, from its MJCF file (the one source of the
target's geometry): what a 6-D pose format ships as the object model (BOP's models/obj_000001.ply) and what an
object's projected outline is computed from.

Every geom of body `target` becomes triangles in T (metres): boxes exactly (8 vertices), cylinders and capsules as
32-sided prisms, spheres and ellipsoids as 16 x 32 latitude-longitude grids, meshes as compiled (MuJoCo stores a
mesh's vertices in the mesh's own frame; the geom's pose puts them in T). Planes and height fields are skipped.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import quat_to_rotmat

APPENDAGE_GROUP = 4  # geom group of the clutter `appendages` switches on (models/envisat.xml)
_SIDES = 32  # polygon sides of a round geom's cross-section
_RINGS = 16  # latitude rings of a sphere or an ellipsoid


@dataclass(frozen=True)
class TriangleMesh:
    """vertices_T_m: (V, 3) in T, m; faces: (F, 3) int vertex indices, counter-clockwise seen from outside."""

    vertices_T_m: np.ndarray
    faces: np.ndarray


def _box(half: np.ndarray) -> TriangleMesh:
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    # vertex index = 4 * (x > 0) + 2 * (y > 0) + (z > 0); two triangles per face, outward winding
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return TriangleMesh(signs * half, np.array(faces))


def _prism(radius: float, half_length: float) -> TriangleMesh:
    ang = 2 * np.pi * np.arange(_SIDES) / _SIDES
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], axis=1)
    verts = np.vstack([np.c_[ring, np.full(_SIDES, -half_length)], np.c_[ring, np.full(_SIDES, half_length)],
                       [[0, 0, -half_length], [0, 0, half_length]]])
    faces = []
    lo, hi = 2 * _SIDES, 2 * _SIDES + 1
    for i in range(_SIDES):
        j = (i + 1) % _SIDES
        faces += [(i, j, _SIDES + j), (i, _SIDES + j, _SIDES + i), (lo, j, i), (hi, _SIDES + i, _SIDES + j)]
    return TriangleMesh(verts, np.array(faces))


def _ellipsoid(radii: np.ndarray) -> TriangleMesh:
    lat = np.pi * np.arange(1, _RINGS) / _RINGS
    lon = 2 * np.pi * np.arange(_SIDES) / _SIDES
    grid = np.stack([np.outer(np.sin(lat), np.cos(lon)), np.outer(np.sin(lat), np.sin(lon)),
                     np.outer(np.cos(lat), np.ones(_SIDES))], axis=-1).reshape(-1, 3)
    verts = np.vstack([[[0, 0, 1]], grid, [[0, 0, -1]]]) * radii
    faces, last = [], len(verts) - 1
    for i in range(_SIDES):
        j = (i + 1) % _SIDES
        faces += [(0, 1 + i, 1 + j), (last, 1 + (_RINGS - 2) * _SIDES + j, 1 + (_RINGS - 2) * _SIDES + i)]
        for r in range(_RINGS - 2):
            a, b = 1 + r * _SIDES, 1 + (r + 1) * _SIDES
            faces += [(a + i, b + i, b + j), (a + i, b + j, a + j)]
    return TriangleMesh(verts, np.array(faces))


def _geom_mesh(model, g: int) -> TriangleMesh | None:
    """One geom's triangles in its own frame (None: a type with no closed surface)."""
    import mujoco

    kind, size = int(model.geom_type[g]), np.asarray(model.geom_size[g], dtype=float)
    t = mujoco.mjtGeom
    if kind == t.mjGEOM_BOX:
        return _box(size)
    if kind == t.mjGEOM_CYLINDER:
        return _prism(size[0], size[1])
    if kind == t.mjGEOM_CAPSULE:  # the prism plus its caps' extent: a conservative outline
        return _prism(size[0], size[1] + size[0])
    if kind == t.mjGEOM_SPHERE:
        return _ellipsoid(np.full(3, size[0]))
    if kind == t.mjGEOM_ELLIPSOID:
        return _ellipsoid(size)
    if kind == t.mjGEOM_MESH:
        m = int(model.geom_dataid[g])
        v0, nv = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
        f0, nf = int(model.mesh_faceadr[m]), int(model.mesh_facenum[m])
        return TriangleMesh(np.array(model.mesh_vert[v0:v0 + nv], dtype=float),
                            np.array(model.mesh_face[f0:f0 + nf], dtype=int))
    return None


@functools.lru_cache(maxsize=8)
def target_mesh(model_path: str, appendages: bool) -> TriangleMesh:
    """The surface of body `target` of the MJCF at model_path in T, m: every geom MuJoCo renders in the
    factory's scene (the appendages' group too when `appendages`). Cached: treat the arrays as read-only."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(model_path)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "target")
    if body < 0:
        raise ValueError(f"{model_path}: no body named 'target'")
    verts, faces, n = [], [], 0
    for g in np.flatnonzero(model.geom_bodyid == body):
        if int(model.geom_group[g]) == APPENDAGE_GROUP and not appendages:
            continue
        part = _geom_mesh(model, int(g))
        if part is None:
            continue
        R_T_from_geom = quat_to_rotmat(model.geom_quat[g])
        verts.append(part.vertices_T_m @ R_T_from_geom.T + model.geom_pos[g])
        faces.append(part.faces + n)
        n += len(part.vertices_T_m)
    return TriangleMesh(np.vstack(verts), np.vstack(faces))


def ply_bytes(mesh: TriangleMesh, scale: float = 1.0) -> bytes:
    """The mesh as an ASCII PLY file (vertices x, y, z as float, scaled by `scale`; triangles as vertex lists)."""
    v = mesh.vertices_T_m * scale
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(mesh.faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = [f"{a:.6f} {b:.6f} {c:.6f}" for a, b, c in v] + [f"3 {a} {b} {c}" for a, b, c in mesh.faces]
    return (head + "\n".join(rows) + "\n").encode("ascii")
