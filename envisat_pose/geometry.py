"""Target geometry read from models/envisat.xml, the one source of truth: corners, faces, visibility.

Frames: T is the target body frame (origin at the centre of mass, x long). Lengths in metres.
Reads the MJCF with the standard library only, so packages that do not use MuJoCo (filtering) share it.
"""

from __future__ import annotations

import functools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

CORNER_NAMES = ("A", "B", "C", "D", "E", "F", "G", "H")
# The 12 edges of the main body box, as pairs of corner indices (A=0 .. H=7).
EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))
FACE_NAMES = ("px", "mx", "py", "my", "pz", "mz")


def model_path() -> str:
    """Absolute path of models/envisat.xml (ENVISAT_MODEL overrides it)."""
    default = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "models", "envisat.xml")
    return os.environ.get("ENVISAT_MODEL", default)


@dataclass(frozen=True)
class TargetGeometry:
    """The main-body box as the marker model sees it.

    corners_T_m: (8, 3) corners A-H in T, m.
    face_normals_T: (6, 3) outward unit normals in the order of FACE_NAMES.
    face_offsets_m: (6,) h_k: a point x is outside face k's plane when n_k . x > h_k.
    face_corners: (6, 8) bool, which corners belong to which face.
    """

    corners_T_m: np.ndarray
    face_normals_T: np.ndarray
    face_offsets_m: np.ndarray
    face_corners: np.ndarray

    @property
    def half_sizes_m(self) -> np.ndarray:
        """(a, b, c), half the box's extent along x, y, z of T, m."""
        return np.abs(self.corners_T_m).max(axis=0)


def _parse_vec(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split()])


@functools.lru_cache(maxsize=4)
def load_geometry(path: str | None = None) -> TargetGeometry:
    """Read corners corner_A..corner_H of body `target` and build the face table of the box they span."""
    path = path or model_path()
    root = ET.parse(path).getroot()
    target = next((b for b in root.iter("body") if b.get("name") == "target"), None)
    if target is None:
        raise ValueError(f"{path}: no body named 'target'")
    sites = {s.get("name"): s for s in target.iter("site")}
    corners = []
    for name in CORNER_NAMES:
        site = sites.get(f"corner_{name}")
        if site is None:
            raise ValueError(f"{path}: body 'target' has no site 'corner_{name}'")
        corners.append(_parse_vec(site.get("pos", "0 0 0")))
    corners_T = np.array(corners)
    normals, offsets, members = [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            h = np.max(sign * corners_T[:, axis])
            normals.append(n)
            offsets.append(h)
            members.append(np.isclose(sign * corners_T[:, axis], h))
    return TargetGeometry(corners_T, np.array(normals), np.array(offsets), np.array(members))


def visible_faces(c_T_m: np.ndarray, geometry: TargetGeometry | None = None) -> np.ndarray:
    """Faces seen from the viewpoint c_T (chaser position in T, m): n_k . c_T > h_k. (..., 3) -> (..., 6) bool."""
    g = geometry or load_geometry()
    return np.einsum("kj,...j->...k", g.face_normals_T, c_T_m) > g.face_offsets_m


def visible_corners(c_T_m: np.ndarray, geometry: TargetGeometry | None = None) -> np.ndarray:
    """Corners of the convex box seen from c_T: a corner is visible when one of its faces is. (..., 8) bool.

    This is the exact test of the reference sheet (section 4) for the box alone; the solar array can hide
    corners too, which only a rendered depth test sees.
    """
    g = geometry or load_geometry()
    faces = visible_faces(c_T_m, g)
    return np.einsum("...k,kc->...c", faces.astype(np.int64), g.face_corners.astype(np.int64)) > 0
