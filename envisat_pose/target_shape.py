"""What a target's shape says about its keypoints: the skeleton (keypoint pairs joined along the geometry's sharp
edges) and the symmetries (rotations about the centre of mass that map the keypoint set onto itself). Pure numpy
over the arrays envisat_pose.target reads from the MJCF file; frames and units as there (T, metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.target_mesh import TriangleMesh

SNAP_REACH_FRACTION = 0.005  # a keypoint farther than this share of the reach from every sharp edge has no links
MAX_TURN_DEG = 35.0  # a path along the edges bends by at most this much at each point between two keypoints
SYMMETRY_REACH_FRACTION = 1e-3  # a rotation is a symmetry when every keypoint lands this close to one, x reach
SHAPE_REACH_FRACTION = 0.02  # ... and the rendered surface lands this close to itself (sampled), x reach


@dataclass(frozen=True, eq=False)
class Symmetry:
    """A rotation about T's origin (the centre of mass) that maps the keypoint set onto itself.

    R_T: (3, 3), X_k -> R_T @ X_k. perm: (K,) int, R_T @ X[k] = X[perm[k]] within the tolerance. axis_T: (3,) unit
    axis; angle_deg. shape_keeps: the rendered surface maps onto itself too; materials_keep: and each surface
    point onto one of the same colour (only then can no image tell the two poses apart)."""

    R_T: np.ndarray
    perm: np.ndarray
    axis_T: np.ndarray
    angle_deg: float
    shape_keeps: bool
    materials_keep: bool

    @property
    def broken_by(self) -> str:
        """'shape', 'materials' or '' (nothing breaks it: the image cannot tell the twins apart)."""
        return "shape" if not self.shape_keeps else "materials" if not self.materials_keep else ""


def fibonacci_directions(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere (the golden-angle spiral), (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


# ---------------------------------------------------------------- skeleton


def _nearest_on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For one point p (3,), its distance to each segment a[i]-b[i] (S,) and the parameter t (S,) in [0, 1]."""
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * d - p, axis=1), t


def skeleton(keypoints_T_m: np.ndarray, points: np.ndarray, edges: np.ndarray, reach_m: float
             ) -> tuple[tuple[int, int], ...]:
    """Keypoint pairs (i < j) joined by a path along the sharp edges (points (P, 3), edges (E, 2): target_mesh.
    feature_edges) that passes no third keypoint and bends by at most MAX_TURN_DEG where it meets another edge:
    a box's 12 edges between its 8 corners (not its faces' diagonals, which turn 90 deg at a corner), neighbouring
    points on a rim (a 32-sided polygon turns 11.25 deg). A keypoint no such path joins to another (one farther
    than SNAP_REACH_FRACTION x reach_m from every sharp edge, one whose paths turn sharply, as from the middle of a
    panel's edge at its corners, one alone on its rim) is joined to its nearest keypoint instead (nearest_links), so
    every keypoint has a link to draw and COCO's skeleton is never empty."""
    pairs = set(edge_pairs(keypoints_T_m, points, edges, reach_m))
    return tuple(sorted(pairs | nearest_links(keypoints_T_m, pairs)))


def nearest_links(keypoints_T_m: np.ndarray, pairs: set[tuple[int, int]]) -> set[tuple[int, int]]:
    """(i < j) pairs joining each keypoint in none of pairs to its nearest other keypoint (the lowest index on a
    tie)."""
    linked = {k for pair in pairs for k in pair}
    out = set()
    for k in range(len(keypoints_T_m) if len(keypoints_T_m) > 1 else 0):
        if k not in linked:
            d = np.linalg.norm(keypoints_T_m - keypoints_T_m[k], axis=1)
            d[k] = np.inf
            j = int(np.argmin(d))
            out.add((min(k, j), max(k, j)))
    return out


def edge_pairs(keypoints_T_m: np.ndarray, points: np.ndarray, edges: np.ndarray, reach_m: float
               ) -> tuple[tuple[int, int], ...]:
    """skeleton's pairs joined along the sharp edges alone (a keypoint no path reaches: in none)."""
    K, P = len(keypoints_T_m), len(points)
    if len(edges) == 0:
        return ()
    a, b = points[edges[:, 0]], points[edges[:, 1]]
    where = np.vstack([points, keypoints_T_m])  # graph nodes: mesh points 0..P-1, keypoints P..P+K-1
    snap_m = SNAP_REACH_FRACTION * reach_m
    alias = np.arange(P + K)  # a mesh point at a keypoint is that keypoint
    split: dict[int, list[tuple[float, int]]] = {}
    for k, x in enumerate(keypoints_T_m):
        at = np.flatnonzero(np.linalg.norm(points - x, axis=1) <= snap_m)
        if len(at):
            alias[at] = P + k
            continue
        dist, t = _nearest_on_segments(x, a, b)
        for e in np.flatnonzero(dist <= snap_m):  # on an edge between its ends
            split.setdefault(int(e), []).append((float(t[e]), P + k))
    neighbours: dict[int, set[int]] = {}
    for e, (i, j) in enumerate(edges):
        chain = [int(alias[i])] + [n for _, n in sorted(split.get(e, []))] + [int(alias[j])]
        for u, v in zip(chain[:-1], chain[1:]):
            if u != v:
                neighbours.setdefault(u, set()).add(v)
                neighbours.setdefault(v, set()).add(u)
    cos_turn = np.cos(np.radians(MAX_TURN_DEG))

    def heading(u: int, v: int) -> np.ndarray:
        d = where[v] - where[u]
        return d / max(np.linalg.norm(d), 1e-300)

    pairs = set()
    for k in range(K):
        start = P + k
        stack = [(start, v) for v in neighbours.get(start, ())]
        seen = set(stack)
        while stack:  # walk the directed edges, never turning sharply, stopping at the next keypoint
            u, v = stack.pop()
            if v >= P:
                if v != start:
                    pairs.add((min(k, v - P), max(k, v - P)))
                continue
            h = heading(u, v)
            for w in neighbours.get(v, ()):
                if w != u and (v, w) not in seen and float(h @ heading(v, w)) >= cos_turn:
                    seen.add((v, w))
                    stack.append((v, w))
    return tuple(sorted(pairs))


# ---------------------------------------------------------------- symmetries


def _rotation_from_pairs(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The proper rotation taking the frame of (a, b) to that of (c, d) (Kabsch on the two vectors and their
    cross product)."""
    A = np.stack([a, b, np.cross(a, b)])
    C = np.stack([c, d, np.cross(c, d)])
    U, _, Vt = np.linalg.svd(C.T @ A)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ S @ Vt


def _axis_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    """R's unit axis, its largest component positive (+0.0 for a zero one), and the right-handed angle about it in
    (0, 360) deg: the pair gives R back (a quarter-turn the other way is 270 deg about the same axis; before, the
    axis was flipped and the angle kept, so both quarter-turns of a square read 90 deg about +z)."""
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.linalg.norm(w) < 1e-9:  # a half-turn: the axis is the eigenvector of eigenvalue 1
        vals, vecs = np.linalg.eigh(0.5 * (R + R.T))
        w = vecs[:, int(np.argmax(vals))]
    axis = w / np.linalg.norm(w)
    if axis[int(np.argmax(np.abs(axis)))] < 0:
        axis, angle = -axis, 360.0 - angle
    return axis + 0.0, angle


def keypoint_rotations(keypoints_T_m: np.ndarray, reach_m: float, inverted: bool = False
                       ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every rotation about the origin but the identity that maps the keypoints onto themselves within
    SYMMETRY_REACH_FRACTION x reach_m: [(R_T (3, 3), perm (K,))]. inverted: onto their point reflection -X
    instead (the identity included): -R_T is then an improper symmetry, X[perm[k]] = -R_T @ X[k]."""
    X = np.asarray(keypoints_T_m, float)
    Y = -X if inverted else X
    tol = SYMMETRY_REACH_FRACTION * reach_m
    r = np.linalg.norm(X, axis=1)
    # a base pair far from the origin and far from parallel, so the frame it spans is well conditioned
    score = np.linalg.norm(np.cross(X[:, None], X[None]), axis=-1)
    i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    if score[i, j] < tol * max(r.max(), tol):
        return []  # the keypoints on one line through the origin: no rotation is fixed by them
    found: list[tuple[np.ndarray, np.ndarray]] = []
    for c in np.flatnonzero(np.abs(r - r[i]) <= tol):
        for d in np.flatnonzero(np.abs(r - r[j]) <= tol):
            if c == d or abs(np.dot(X[c], X[d]) - np.dot(X[i], X[j])) > 2 * tol * r.max():
                continue
            R = _rotation_from_pairs(X[i], X[j], Y[c], Y[d])
            if (not inverted and np.allclose(R, np.eye(3), atol=1e-9)) or any(np.allclose(R, Q, atol=1e-6)
                                                                               for Q, _ in found):
                continue
            moved = X @ R.T
            dist = np.linalg.norm(moved[:, None] - Y[None], axis=-1)
            perm = np.argmin(dist, axis=1)
            if np.all(dist[np.arange(len(X)), perm] <= tol) and len(set(perm.tolist())) == len(X):
                found.append((R, perm))
    return found


MAX_SAMPLES = 3000  # surface samples a symmetry is checked with (every n-th of the fixed grid beyond this)


def surface_samples(mesh: TriangleMesh, per_edge: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Points on the mesh's triangles (a fixed barycentric grid of per_edge steps per triangle, no random draw;
    every n-th beyond MAX_SAMPLES) and the index of the triangle each lies on: ((N, 3), (N,))."""
    n = per_edge
    bary = np.array([(i, j, n - i - j) for i in range(n + 1) for j in range(n + 1 - i)], float) / n
    tri = mesh.vertices_T_m[mesh.faces]  # (F, 3, 3)
    pts = np.einsum("sb,fbk->fsk", bary, tri).reshape(-1, 3)
    owner = np.repeat(np.arange(len(tri)), len(bary))
    step = max(1, int(np.ceil(len(pts) / MAX_SAMPLES)))
    return pts[::step], owner[::step]


def triangle_distances(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance from each point p (N, 3) to each triangle tri (F, 3, 3), (N, F): the nearest point of the triangle
    found in its plane, or on its nearest side when that point falls outside."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n_len = np.linalg.norm(n, axis=1)
    n_unit = n / np.maximum(n_len, 1e-300)[:, None]
    d = p[:, None] - a[None]  # (N, F, 3)
    h = np.einsum("nfk,fk->nf", d, n_unit)
    q = p[:, None] - h[..., None] * n_unit[None]  # the projection into each plane
    inside = np.ones(h.shape, bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("nfk,fk->nf", np.cross(v - u, q - u[None]), n_unit) >= 0
    best = np.where(inside, np.abs(h), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        t = np.clip(np.einsum("nfk,fk->nf", p[:, None] - u[None], e) / np.maximum(np.einsum("fk,fk->f", e, e),
                                                                                1e-300), 0, 1)
        best = np.minimum(best, np.linalg.norm(u[None] + t[..., None] * e[None] - p[:, None], axis=-1))
    return best


def maps_onto_itself(R: np.ndarray, mesh: TriangleMesh, face_rgb: np.ndarray, tol_m: float,
                     chunk: int = 64) -> tuple[bool, bool]:
    """(shape, materials): whether every surface sample turned by R lands within tol_m of the surface, and of a
    triangle of the same colour (face_rgb (F, 3))."""
    samples, owner = surface_samples(mesh)
    tri = mesh.vertices_T_m[mesh.faces]
    moved = samples @ R.T
    shape = materials = True
    for s in range(0, len(moved), chunk):
        dist = triangle_distances(moved[s:s + chunk], tri)  # (n, F)
        near = dist <= tol_m
        if not near.any(axis=1).all():
            return False, False
        same = np.all(np.abs(face_rgb[None, :, :] - face_rgb[owner[s:s + chunk], None, :]) < 1e-3, axis=-1)
        materials &= bool((near & same).any(axis=1).all())
    return shape, materials


def symmetries(keypoints_T_m: np.ndarray, mesh: TriangleMesh, face_rgb: np.ndarray, reach_m: float
               ) -> tuple[Symmetry, ...]:
    """The keypoint set's symmetries (keypoint_rotations), each checked against the rendered surface mesh and its
    triangles' colours face_rgb (F, 3)."""
    out = []
    for R, perm in keypoint_rotations(keypoints_T_m, reach_m):
        shape, materials = maps_onto_itself(R, mesh, face_rgb, SHAPE_REACH_FRACTION * reach_m)
        axis, angle = _axis_angle(R)
        out.append(Symmetry(R, perm, axis, angle, shape, materials))
    return tuple(sorted(out, key=lambda s: (s.angle_deg, tuple(-s.axis_T))))


def mirror_perm(keypoints_T_m: np.ndarray, mesh: TriangleMesh, face_rgb: np.ndarray, reach_m: float
                ) -> np.ndarray | None:
    """The keypoint permutation of a mirror symmetry (a reflection through a plane about the origin, S = -R_T of
    a half-turn R_T mapping the keypoints onto -X: keypoint_rotations(inverted=True)) that the rendered surface
    and its colours keep too, or None (the target is chiral: its mirror image is another object). S @ X[k] =
    X[perm[k]]; S is its own inverse, so is perm. Several: the first of keypoint_rotations' order."""
    for R, perm in keypoint_rotations(keypoints_T_m, reach_m, inverted=True):
        S = -R
        if not np.allclose(S @ S, np.eye(3), atol=1e-9) or np.allclose(S, -np.eye(3), atol=1e-9):
            continue  # a rotoreflection or the point inversion: no mirror plane
        if all(maps_onto_itself(S, mesh, face_rgb, SHAPE_REACH_FRACTION * reach_m)):
            return perm
    return None
