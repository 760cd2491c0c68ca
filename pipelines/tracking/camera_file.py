"""A user's camera for `envisat track`: a TOML file of intrinsics (fx, fy, cx, cy in px, width, height, optional
OpenCV distortion), checked for sense, as the ideal pinhole the tracker uses and the remap that makes the frames
ideal; and, where known, how the camera stores light (`response`: "linear", "srgb" or a gamma such as 2.2;
envisat_pose/camera_response.py) and the width of its blur (`psf_sigma_px`: a Gaussian PSF's sigma, px), read by
read_camera_response. The camera's mount on the chaser is the MJCF's chaser_cam's."""

from __future__ import annotations

import os

import numpy as np

from envisat_pose.camera_response import Response, parse_response
from envisat_pose.config import ConfigError, InputError, load_toml
from envisat_pose.geometry import MIN_SIDE_PX, PinholeCamera, load_camera

# fx / fy beyond this factor is not a camera (pixels that far from square are a typo or a swapped key)
MAX_ASPECT = 3.0
KEYS = ("fx", "fy", "cx", "cy", "width", "height", "distortion", "response", "psf_sigma_px")
MAX_PSF_SIGMA_PX = 10.0  # a blur wider than this leaves no edge to locate


def camera_from_intrinsics(path: str) -> tuple[PinholeCamera, tuple | None]:
    """(the ideal pinhole the tracker uses, remap) from a camera TOML file: fx, fy, cx, cy (px), width, height,
    optional distortion (OpenCV's k1, k2, p1, p2[, k3...]). remap is None when the frames are already ideal
    (fx == fy, no distortion), else (map1, map2) for cv2.remap to a pinhole with f = sqrt(fx fy) and the same
    principal point. InputError naming the file and the key otherwise."""
    import cv2

    if not os.path.isfile(path):
        raise InputError(f"camera {path!r}: no such file (expected a camera TOML file: fx, fy, cx, cy, width, height)")
    data = load_toml(path, "camera")
    vals = {}
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        if key not in data:
            table = next((k for k, v in data.items() if isinstance(v, dict) and key in v), None)
            under = f"; it is under [{table}]: expected at the file's top level" if table else ""
            raise InputError(f"{path}: camera file has no {key!r} (expected fx, fy, cx, cy in px, width, height"
                             f"{under})")
        v = data[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise InputError(f"{path}: {key} = {v!r}: expected a number")
        vals[key] = float(v)
    for key in ("fx", "fy"):
        if vals[key] <= 0:
            raise InputError(f"{path}: {key} = {data[key]!r}: expected a positive focal length in px")
    for key in ("width", "height"):
        if vals[key] < MIN_SIDE_PX or vals[key] != int(vals[key]):
            raise InputError(f"{path}: {key} = {data[key]!r}: expected an image size in whole pixels, at least "
                             f"{MIN_SIDE_PX}")
    w, h = int(vals["width"]), int(vals["height"])
    for key, side in (("cx", w), ("cy", h)):
        if not 0.0 <= vals[key] <= side:
            raise InputError(f"{path}: {key} = {data[key]!r}: expected a principal point inside the image "
                             f"(0 to {side} px)")
    if not 1.0 / MAX_ASPECT <= vals["fx"] / vals["fy"] <= MAX_ASPECT:
        raise InputError(f"{path}: fx = {data['fx']!r}, fy = {data['fy']!r}: expected focal lengths within a factor "
                         f"{MAX_ASPECT:g} of each other (pixels that square, or nearly)")
    dist = data.get("distortion")
    if dist is not None:
        if not isinstance(dist, list) or len(dist) not in (4, 5, 8, 12, 14) \
                or not all(isinstance(d, (int, float)) and not isinstance(d, bool) and np.isfinite(d) for d in dist):
            raise InputError(f"{path}: distortion = {dist!r}: expected OpenCV's 4, 5, 8, 12 or 14 coefficients")
    unknown = sorted(set(data) - set(KEYS))
    if unknown:
        raise InputError(f"{path}: unknown camera keys {unknown} (expected {', '.join(KEYS)})")
    read_camera_response(path, data)
    f = float(np.sqrt(vals["fx"] * vals["fy"]))
    mount = load_camera()
    cam = PinholeCamera(f, vals["cx"], vals["cy"], w, h, mount.R_K_from_C, mount.pos_C_m)
    if vals["fx"] == vals["fy"] and not (dist and any(dist)):
        return cam, None
    K_user = np.array([[vals["fx"], 0, vals["cx"]], [0, vals["fy"], vals["cy"]], [0, 0, 1.0]])
    maps = cv2.initUndistortRectifyMap(K_user, np.asarray(dist or [0, 0, 0, 0], float), None, cam.K, (w, h),
                                       cv2.CV_32FC1)
    return cam, maps


def default_camera(path: str, size_px: tuple[int, int], generated: bool) -> PinholeCamera:
    """The MJCF's chaser_cam for frames given without a camera: a generated dataset's (generated) at its own size
    (the factory renders that camera at the dataset's resolution, the same field of view); a user's images or
    video at the camera's own size only. Frames of another size are refused in one line giving the numbers to
    write for frames resized from it: a crop or another lens read with the default's field of view gives a pose
    wrong by the focal lengths' ratio and still consistent (800-px crops of 1024-px frames: the range 21 % off,
    claimed as tracking)."""
    cam = load_camera()
    size = (int(size_px[0]), int(size_px[1]))
    if generated or size == (cam.width_px, cam.height_px):
        return cam if size == (cam.width_px, cam.height_px) else cam.scaled(*size)
    s = cam.scaled(*size)
    raise InputError(f"{path}: frames of {size[0]} x {size[1]} px, not the default camera's {cam.width_px} x "
                     f"{cam.height_px}: give your camera (--camera FILE.toml, camera= in Python) with fx, fy, cx, cy, "
                     f"width, height (frames resized from the default camera's, whole: fx = fy = {s.f_px:.6g}, "
                     f"cx = {s.cu_px:g}, cy = {s.cv_px:g}, width = {size[0]}, height = {size[1]})")


def camera_record(camera: PinholeCamera, given: str | None, undistorted: bool, default: bool | None = None) -> dict:
    """What a job's summary says of the camera it used: its pinhole (px), where it came from (the camera file
    given; `default`: the MJCF's chaser_cam at the frames' size, by default where no file was given) and whether
    the frames were undistorted to it."""
    default = given is None if default is None else default
    return {"file": given, "default": default, "f_px": float(camera.f_px), "cx_px": float(camera.cu_px),
            "cy_px": float(camera.cv_px), "width_px": int(camera.width_px), "height_px": int(camera.height_px),
            "undistorted": bool(undistorted)}


def read_camera_response(path: str, data: dict | None = None) -> tuple[Response | None, float | None]:
    """The camera response of a camera TOML file, (response, psf_sigma_px), each None where the file does not give
    it (adapt then estimates it from the frames). data: the file's parsed table (read from path when None).
    InputError naming the file and the key for a value that is no response or no blur width (0 to
    MAX_PSF_SIGMA_PX px)."""
    data = load_toml(path, "camera") if data is None else data
    response = None
    if "response" in data:
        try:
            response = parse_response(data["response"], "response")
        except ConfigError as err:
            raise InputError(f"{path}: response = {data['response']!r}: expected 'linear', 'srgb' or a gamma "
                             f"(a number such as 2.2) ({err})") from None
    sigma = data.get("psf_sigma_px")
    if sigma is not None:
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not 0.0 <= sigma <= MAX_PSF_SIGMA_PX:
            raise InputError(f"{path}: psf_sigma_px = {sigma!r}: expected a Gaussian PSF's sigma in px, 0 to "
                             f"{MAX_PSF_SIGMA_PX:g}")
        sigma = float(sigma)
    return response, sigma
