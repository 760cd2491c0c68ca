"""What the box's geometry alone says about its corners' names: its half-turn symmetries (the corner permutation
each one makes) and each face's winding in the image, computed once per geometry object.

The box (half sizes a != b != c, centred) maps onto itself under the half-turns about x, y and z of T (HALF_TURNS):
its corners alone cannot tell these 4 poses apart (perception/naming.py's docstring).
"""

from __future__ import annotations

import numpy as np

from envisat_pose.geometry import TargetGeometry

HALF_TURNS = {"I": (1.0, 1.0, 1.0), "x": (1.0, -1.0, -1.0), "y": (-1.0, 1.0, -1.0), "z": (-1.0, -1.0, 1.0)}


# per-geometry results of the functions below that depend on the geometry alone, computed once per geometry object
# (a naming asks for them every frame): {(function name, id(geometry)): (geometry, result)}
_GEOMETRY_CACHE: dict = {}


def _cached(name: str, geometry: TargetGeometry, compute):
    hit = _GEOMETRY_CACHE.get((name, id(geometry)))
    if hit is None or hit[0] is not geometry:
        hit = (geometry, compute(geometry))
        if len(_GEOMETRY_CACHE) > 64:
            _GEOMETRY_CACHE.clear()
        _GEOMETRY_CACHE[(name, id(geometry))] = hit
    return hit[1]


def symmetry_permutations(geometry: TargetGeometry) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """For each half-turn g of HALF_TURNS: (perm (8,), S (3, 3), d (3,)) with corners[perm[k]] = S corners[k] + d:
    the pose (R S, t + R d) shows corner perm[k] where (R, t) shows corner k."""
    cached = _cached("symmetry_permutations", geometry, _symmetry_permutations)
    return {name: tuple(a.copy() for a in v) for name, v in cached.items()}


def _symmetry_permutations(geometry: TargetGeometry) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    X = geometry.corners_T_m
    centre = X.mean(axis=0)
    out = {}
    for name, signs in HALF_TURNS.items():
        S = np.diag(signs)
        d = centre - S @ centre
        mapped = X @ S.T + d
        perm = np.argmin(np.linalg.norm(mapped[:, None, :] - X[None, :, :], axis=-1), axis=1)
        if sorted(perm) != list(range(8)) or not np.allclose(X[perm], mapped, atol=1e-6):
            raise ValueError(f"the box is not symmetric under the half-turn about {name}")
        out[name] = (perm, S, d)
    return out


def face_windings(geometry: TargetGeometry) -> np.ndarray:
    """(6, 4) corner indices of each face in the cyclic order of increasing image angle (y down) that every view
    from outside shows (perspective keeps a front-facing polygon's winding)."""
    return _cached("face_windings", geometry, _face_windings).copy()


def _face_windings(geometry: TargetGeometry) -> np.ndarray:
    X = geometry.corners_T_m
    out = []
    for k in range(6):
        idx = np.flatnonzero(geometry.face_corners[k])
        n = geometry.face_normals_T[k]
        # a camera on the outward normal looking back at the face: z_cam = -n, any x_cam in the face's plane
        z = -n
        x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        p = (X[idx] - X[idx].mean(axis=0)) @ R.T
        ang = np.arctan2(p[:, 1], p[:, 0])
        out.append(idx[np.argsort(ang)])
    return np.array(out)
