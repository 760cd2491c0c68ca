"""The target's surface as one triangle mesh in its body frame T, from its compiled MJCF model (the one source of
the target's geometry, read by envisat_pose.target): what a 6-D pose format ships as the object model (BOP's
models/obj_000001.ply), what an object's projected outline is computed from, and where the target's skeleton and
symmetries are read.

Every geom of body `target` becomes triangles in T (metres): boxes exactly (8 vertices), cylinders and capsules as
32-sided prisms, spheres and ellipsoids as 16 x 32 latitude-longitude grids, meshes as compiled (MuJoCo stores a
mesh's vertices in the mesh's own frame; the geom's pose puts them in T). Planes and height fields are skipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import quat_to_rotmat

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


@dataclass(frozen=True)
class BodyMesh:
    """The triangles of every geom of a body, in T. mesh: all of them; face_geom: (F,) the index (into the body's
    geoms, file order) of each triangle's geom."""

    mesh: TriangleMesh
    face_geom: np.ndarray

    def select(self, keep_geoms: np.ndarray) -> TriangleMesh:
        """The triangles of the geoms where keep_geoms (G,) bool is set, and only the vertices they use."""
        faces = self.mesh.faces[np.asarray(keep_geoms, bool)[self.face_geom]]
        used, inverse = np.unique(faces, return_inverse=True)
        return TriangleMesh(self.mesh.vertices_T_m[used], inverse.reshape(faces.shape))


def body_mesh(model, body: int) -> BodyMesh:
    """The surface of one body of a compiled MuJoCo model in the body's frame, m: every geom MuJoCo can draw
    (planes and height fields skipped), in the body's geom order."""
    verts, faces, owner, n = [np.zeros((0, 3))], [np.zeros((0, 3), int)], [np.zeros(0, int)], 0
    for i, g in enumerate(np.flatnonzero(model.geom_bodyid == body)):
        part = _geom_mesh(model, int(g))
        if part is None:
            continue
        R_T_from_geom = quat_to_rotmat(model.geom_quat[g])
        verts.append(part.vertices_T_m @ R_T_from_geom.T + model.geom_pos[g])
        faces.append(part.faces + n)
        owner.append(np.full(len(part.faces), i))
        n += len(part.vertices_T_m)
    return BodyMesh(TriangleMesh(np.vstack(verts), np.vstack(faces)), np.concatenate(owner))


def feature_edges(mesh: TriangleMesh, min_angle_deg: float = 20.0, merge_m: float = 1e-6) -> tuple[np.ndarray,
                                                                                                   np.ndarray]:
    """The mesh's sharp edges: (points (P, 3) m, edges (E, 2) indices into points). Vertices closer than merge_m
    are one point; an edge is sharp where its two triangles' normals differ by more than min_angle_deg or where it
    borders one triangle only (a polygon's sides meeting at less than the angle, a cylinder's wall, are not)."""
    v = mesh.vertices_T_m
    keys = np.round(v / merge_m).astype(np.int64)
    points_key, index = np.unique(keys, axis=0, return_inverse=True)
    index = index.reshape(-1)
    points = np.zeros((len(points_key), 3))
    np.add.at(points, index, v)
    points /= np.bincount(index, minlength=len(points))[:, None]
    tri = index[mesh.faces]
    n = np.cross(points[tri[:, 1]] - points[tri[:, 0]], points[tri[:, 2]] - points[tri[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 0
    tri, n = tri[ok], n[ok] / norm[ok, None]
    sides = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    owner = np.tile(np.arange(len(tri)), 3)
    sides_sorted = np.sort(sides, axis=1)
    order = np.lexsort((sides_sorted[:, 1], sides_sorted[:, 0]))
    sides_sorted, owner = sides_sorted[order], owner[order]
    start = np.r_[True, np.any(sides_sorted[1:] != sides_sorted[:-1], axis=1)]
    group = np.cumsum(start) - 1
    cos_min = np.cos(np.radians(min_angle_deg))
    sharp = np.zeros(group[-1] + 1 if len(group) else 0, bool)
    first = np.flatnonzero(start)
    counts = np.diff(np.r_[first, len(group)])
    sharp[counts == 1] = True
    two = np.flatnonzero(counts == 2)
    sharp[two] = np.einsum("ij,ij->i", n[owner[first[two]]], n[owner[first[two] + 1]]) < cos_min
    for g in np.flatnonzero(counts > 2):  # where more than two meet: any pair bent by more than the angle
        normals = n[owner[first[g]:first[g] + counts[g]]]
        sharp[g] = np.min(normals @ normals.T) < cos_min
    return points, sides_sorted[first[sharp]]


def ply_bytes(mesh: TriangleMesh, scale: float = 1.0) -> bytes:
    """The mesh as an ASCII PLY file (vertices x, y, z as float, scaled by `scale`; triangles as vertex lists)."""
    v = mesh.vertices_T_m * scale
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(mesh.faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = [f"{a:.6f} {b:.6f} {c:.6f}" for a, b, c in v] + [f"3 {a} {b} {c}" for a, b, c in mesh.faces]
    return (head + "\n".join(rows) + "\n").encode("ascii")
