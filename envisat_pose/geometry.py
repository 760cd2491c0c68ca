"""Target geometry read from models/envisat.xml, the one source of truth: corners, faces, visibility.

Frames: T is the target body frame (origin at the centre of mass, x long). Lengths in metres.
Reads the MJCF with the standard library only, so packages that do not use MuJoCo (filtering) share it.
"""

from __future__ import annotations

import functools
import importlib.resources
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

CORNER_NAMES = ("A", "B", "C", "D", "E", "F", "G", "H")
CAMERA_NAME = "chaser_cam"  # the MJCF's camera on the chaser (models/envisat.xml), the project's one camera
MIN_SIDE_PX = 16  # the smallest image side, px, a camera or a frame may have
# The 12 edges of the main body box, as pairs of corner indices (A=0 .. H=7).
EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))
FACE_NAMES = ("px", "mx", "py", "my", "pz", "mz")
# The covering class of each face of the main body in the factory's appearance draws (never changes: the half-turn
# about x swaps +y gold foil with -y black foil and +z silver foil with -z radiator tiles, so it shows).
# datagen/appearance.py draws each class's appearance and perception/facecue.py tells them apart; the MJCF's own
# materials (sequence mode, the closed loop) are one fixed appearance of their own.
FACE_COVERING = {"px": "end_panel", "mx": "end_panel", "py": "mli_gold", "my": "mli_black", "pz": "mli_silver",
                 "mz": "radiator"}


def model_path() -> str:
    """Path of models/envisat.xml, shipped as package data of envisat_pose.models (ENVISAT_MODEL overrides it)."""
    override = os.environ.get("ENVISAT_MODEL")
    if override:
        return override
    return str(importlib.resources.files("envisat_pose.models").joinpath("envisat.xml"))


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


@functools.lru_cache(maxsize=4)
def load_array_outline(path: str | None = None) -> np.ndarray:
    """The solar array's outline in T, m: (4, 3) the corners of geom `array`'s mid-plane (a box of body `target`
    with no rotation of its own; its thinnest axis dropped), in order around it. The box's half-turns about y and z
    carry it to the other end of the body; the one about x maps it onto itself (perception/arraycue.py)."""
    path = path or model_path()
    root = ET.parse(path).getroot()
    target = next((b for b in root.iter("body") if b.get("name") == "target"), None)
    geom = None if target is None else next((g for g in target.iter("geom") if g.get("name") == "array"), None)
    if geom is None or geom.get("type") != "box":
        raise ValueError(f"{path}: body 'target' has no box geom named 'array'")
    if any(geom.get(k) for k in ("quat", "axisangle", "xyaxes", "zaxis", "euler")):
        raise ValueError(f"{path}: geom 'array' is rotated; its outline is read for an axis-aligned box only")
    pos, size = _parse_vec(geom.get("pos", "0 0 0")), _parse_vec(geom.get("size"))
    a, b = np.sort(np.argsort(size)[1:])  # the two long axes
    out = []
    for sa, sb in ((1, 1), (1, -1), (-1, -1), (-1, 1)):
        c = pos.copy()
        c[a] += sa * size[a]
        c[b] += sb * size[b]
        out.append(c)
    return np.array(out)


def visible_faces(c_T_m: np.ndarray, geometry: TargetGeometry | None = None) -> np.ndarray:
    """Faces seen from the viewpoint c_T (chaser position in T, m): n_k . c_T > h_k. (..., 3) -> (..., 6) bool."""
    g = geometry or load_geometry()
    return np.einsum("kj,...j->...k", g.face_normals_T, c_T_m) > g.face_offsets_m


def visible_corners(c_T_m: np.ndarray, geometry: TargetGeometry | None = None) -> np.ndarray:
    """Corners of the convex box seen from c_T: a corner is visible when one of its faces is. (..., 8) bool.

    This is the exact test of the reference sheet (section 4) for the box alone; the solar array can hide
    corners too, which only the ray casts through the whole target see (Target.truth_visible).
    """
    g = geometry or load_geometry()
    faces = visible_faces(c_T_m, g)
    return np.einsum("...k,kc->...c", faces.astype(np.int64), g.face_corners.astype(np.int64)) > 0


@dataclass(frozen=True)
class PinholeCamera:
    """The chaser camera of models/envisat.xml (camera `chaser_cam`), the one camera of the project.

    Camera frame K: x right, y down, z along the boresight (OpenCV); pixels in the OpenCV convention (pixel
    centres at integer coordinates). f_px: focal length, px; (cu_px, cv_px): principal point, px;
    width_px, height_px: image size. R_K_from_C: (3, 3) rotation from the chaser frame C (the mount) to K;
    pos_C_m: (3,) camera centre in C, m.
    """

    f_px: float
    cu_px: float
    cv_px: float
    width_px: int
    height_px: int
    R_K_from_C: np.ndarray
    pos_C_m: np.ndarray

    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix (3, 3)."""
        return np.array([[self.f_px, 0.0, self.cu_px], [0.0, self.f_px, self.cv_px], [0.0, 0.0, 1.0]])

    def scaled(self, width_px: int, height_px: int) -> "PinholeCamera":
        """The same camera (field of view, mount) read out at another image size."""
        f = self.f_px * height_px / self.height_px
        return PinholeCamera(f, 0.5 * (width_px - 1), 0.5 * (height_px - 1), int(width_px), int(height_px),
                             self.R_K_from_C, self.pos_C_m)


def _camera_axes_rows(cam: ET.Element, path: str) -> np.ndarray:
    """Rows x_cam, y_cam, z_cam of a MuJoCo camera in its body's frame, from `xyaxes` (as MuJoCo: y is
    orthogonalized against x) or `quat` (w x y z). MuJoCo cameras look along -z_cam with y_cam up."""
    if cam.get("xyaxes"):
        v = _parse_vec(cam.get("xyaxes"))
        x = v[:3] / np.linalg.norm(v[:3])
        y = v[3:] - (v[3:] @ x) * x
        y = y / np.linalg.norm(y)
        return np.array([x, y, np.cross(x, y)])
    if cam.get("quat"):
        w, a, b, c = _parse_vec(cam.get("quat")) / np.linalg.norm(_parse_vec(cam.get("quat")))
        R = np.array([[1 - 2 * (b * b + c * c), 2 * (a * b - c * w), 2 * (a * c + b * w)],
                      [2 * (a * b + c * w), 1 - 2 * (a * a + c * c), 2 * (b * c - a * w)],
                      [2 * (a * c - b * w), 2 * (b * c + a * w), 1 - 2 * (a * a + b * b)]])
        return R.T
    if any(cam.get(k) for k in ("axisangle", "euler", "zaxis")):
        raise ValueError(f"{path}: camera {cam.get('name')!r}: give its orientation as xyaxes or quat")
    return np.eye(3)


@functools.lru_cache(maxsize=4)
def load_camera(path: str | None = None, name: str = CAMERA_NAME) -> PinholeCamera:
    """The pinhole of camera `name` in the MJCF: f = (H / 2) / tan(fovy / 2) px from `fovy` (deg) and
    `resolution`, the principal point at the image centre, and the mount from the camera's pose in its body
    (the chaser, whose frame is C). A test checks it against MuJoCo's compiled camera."""
    path = path or model_path()
    root = ET.parse(path).getroot()
    cam = next((c for c in root.iter("camera") if c.get("name") == name), None)
    if cam is None:
        raise ValueError(f"{path}: no camera named {name!r}")
    if cam.get("fovy") is None or cam.get("resolution") is None:
        raise ValueError(f"{path}: camera {name!r} needs fovy and resolution attributes")
    fovy_deg = float(cam.get("fovy"))
    width, height = (int(v) for v in _parse_vec(cam.get("resolution")))
    f = 0.5 * height / np.tan(np.radians(fovy_deg) / 2.0)
    axes = _camera_axes_rows(cam, path)
    # K = (x_cam, -y_cam, -z_cam): x right, y down, z along the boresight
    R_K_from_C = np.array([axes[0], -axes[1], -axes[2]])
    R_K_from_C.setflags(write=False)
    pos = _parse_vec(cam.get("pos", "0 0 0"))
    pos.setflags(write=False)
    return PinholeCamera(float(f), 0.5 * (width - 1), 0.5 * (height - 1), width, height, R_K_from_C, pos)


def project_K(points_K_m: np.ndarray, camera: PinholeCamera, min_depth_m: float = 1e-3) -> np.ndarray:
    """Pinhole projection of points in K, (..., 3) m -> (..., 2) px.

    A point at or behind the camera (z_K < min_depth_m) is projected with z_K = min_depth_m: it lands far
    outside the image on its own side of the principal point, never mirrored through it (a UKF sigma point
    with a corner behind the camera must not look like a corner in front of it).
    """
    z = np.maximum(points_K_m[..., 2], min_depth_m)
    return np.stack([camera.f_px * points_K_m[..., 0] / z + camera.cu_px,
                     camera.f_px * points_K_m[..., 1] / z + camera.cv_px], axis=-1)
