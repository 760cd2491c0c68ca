"""The Rerun logger: truth, estimates, error series and labelled samples written as a `.rrd` recording.

The one module of the project that talks to Rerun (design.md, Conventions). It takes plain arrays and the core's
contracts and writes the design's layout:

    world                                  the chaser's LVLH frame C, centred on the chaser (m); annotation context
    world/target                           true pose of T in C (translation rho_C, rotation R_C_from_T)
    world/target/model/{body,array,boom}   the MJCF's main body, solar array and boom (static, in T)
    world/target_est                       run 0's estimated pose; .../model the same parts, .../position_3sigma the
                                           3-sigma ellipsoid of the position covariance (axes in C, drawn in T_est)
    world/corners_true                     the truth's corner sites A-H in C (green visible, red hidden)
    world/chaser/camera                    the pinhole of models/envisat.xml (camera `chaser_cam`), static
    world/chaser/camera/image              the camera image (compressed PNG/JPEG) where there is one
    world/chaser/camera/image/corners_true the corners in the image (in frame; green visible, red hidden)
    world/chaser/camera/image/{mask,depth} a dataset sample's segmentation and depth
    metrics/error/<block>/<axis>           error of every run (one series per run), with .../filter_3sigma (+-3 sigma
                                           of the filter's P) and .../sample_3sigma (+-3 sigma of the runs' spread)
    metrics/{range_m,visible_corners,in_frame_corners}

Timelines: `sim_time` (duration, s) and `frame` (sequence: the truth's sample, the filter's step or the dataset's
sample index). Long series go in through `send_columns`; model data is logged once as static. Each file is
written under a temporary name and renamed when complete (envisat_pose.io.atomic_path).

Two conventions change at this edge: Rerun quaternions are (x, y, z, w), ours (w, x, y, z); Rerun's pixel (0, 0)
covers [0, 1]^2 (centre 0.5), ours follow OpenCV (centre 0), so image points and the principal point get +0.5.
"""

from __future__ import annotations

import uuid
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import timedelta
from typing import Iterable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from envisat_pose.attitude import mrp_to_dcm, mrp_to_quat, rotmat_to_quat
from envisat_pose.contracts import Estimates, TruthTrajectory
from envisat_pose.geometry import CORNER_NAMES, EDGES, PinholeCamera, load_camera, load_geometry, model_path
from envisat_pose.io import atomic_path
from envisat_pose.state import MRP, POS, RATE, VEL
from envisat_pose.status import STATUSES as STATUS_NAMES  # the tracker's statuses by code
from envisat_pose.status import legend_json

from .stats import component_errors, display_transform

APPLICATION_ID = "envisat_pose"
KEYPOINT_CLASS = 0  # class of the annotation context whose keypoints are the corners A-H
BLOCKS = ("position_m", "velocity_m_s", "attitude_deg", "angular_velocity_deg_s")
AXES = ("x", "y", "z")
# statistics' units (m, m/s, rad, rad/s; analysis.stats) -> what the plots show (m, m/s, deg, deg/s)
DISPLAY_SCALE = np.array([1.0] * 6 + [180.0 / np.pi] * 6)
MASK_CLASSES = ("background", "face +x", "face -x", "face +y", "face -y", "face +z", "face -z", "array and boom",
                "appendages")  # design.md, Shard: mask values 0-8

VISIBLE_RGB = (40, 200, 60)
HIDDEN_RGB = (220, 50, 50)
TRUE_RGB = (200, 200, 210)
EST_RGB = (60, 140, 255)
SIGMA_RGB = (220, 50, 50)
SAMPLE_SIGMA_RGB = (20, 20, 20)
IMAGE_PLANE_M = 8.0  # where the viewer draws the image plane in 3D, m in front of the camera


# ---------------------------------------------------------------- model data from the MJCF

@dataclass(frozen=True)
class Part:
    """A solid of body `target` as Rerun draws it: a box (half_sizes_m) or a cylinder (radius_m, length_m
    along its local z), centred at center_T_m, rotated by quat_xyzw (part frame -> T)."""

    name: str
    kind: str
    center_T_m: np.ndarray
    quat_xyzw: np.ndarray
    half_sizes_m: np.ndarray | None = None
    radius_m: float = 0.0
    length_m: float = 0.0


def _vec(text: str | None, default: str) -> np.ndarray:
    return np.array([float(v) for v in (text or default).split()])


def _wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Our (w, x, y, z) -> Rerun's (x, y, z, w)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def target_parts(path: str | None = None) -> list[Part]:
    """The main body (the box spanned by the corners, load_geometry) and every other solid geom of body `target`
    in models/envisat.xml that the plain scene shows (boxes and `fromto` cylinders; the face plates are the body,
    geom group 4, the hidden appendages, is left out). Read with ElementTree like the core's geometry."""
    path = path or model_path()
    g = load_geometry(path)
    lo, hi = g.corners_T_m.min(axis=0), g.corners_T_m.max(axis=0)
    parts = [Part("body", "box", 0.5 * (lo + hi), np.array([0.0, 0.0, 0.0, 1.0]), half_sizes_m=0.5 * (hi - lo))]
    target = next(b for b in ET.parse(path).getroot().iter("body") if b.get("name") == "target")
    for geom in target.iter("geom"):
        name = geom.get("name", "")
        if name.startswith("face_") or geom.get("group") == "4":
            continue
        size = _vec(geom.get("size"), "0")
        if geom.get("type") == "box" and len(size) == 3:
            quat = _wxyz_to_xyzw(_vec(geom.get("quat"), "1 0 0 0"))
            parts.append(Part(name, "box", _vec(geom.get("pos"), "0 0 0"), quat, half_sizes_m=size))
        elif geom.get("type") == "cylinder" and geom.get("fromto"):
            a, b = _vec(geom.get("fromto"), "").reshape(2, 3)
            axis = (b - a) / np.linalg.norm(b - a)
            # the rotation taking the cylinder's local z onto its axis
            z = np.array([0.0, 0.0, 1.0])
            c = np.cross(z, axis)
            if np.linalg.norm(c) < 1e-12:
                q = np.array([1.0, 0.0, 0.0, 0.0]) if axis[2] > 0 else np.array([0.0, 1.0, 0.0, 0.0])
            else:
                ang = np.arccos(np.clip(axis[2], -1.0, 1.0))
                q = np.concatenate([[np.cos(ang / 2)], np.sin(ang / 2) * c / np.linalg.norm(c)])
            parts.append(Part(name, "cylinder", 0.5 * (a + b), _wxyz_to_xyzw(q), radius_m=float(size[0]),
                              length_m=float(np.linalg.norm(b - a))))
    return parts


PART_RGB = {"body": (190, 150, 70), "array": (40, 60, 150), "boom": (150, 150, 150)}


def log_target_model(rec: rr.RecordingStream, entity: str, parts: list[Part], rgb=None, fill="solid") -> None:
    """The target's parts under `entity`/model, static, in T."""
    mode = rr.components.FillMode.Solid if fill == "solid" else rr.components.FillMode.MajorWireframe
    for p in parts:
        color = rgb or PART_RGB.get(p.name, (170, 170, 170))
        path = f"{entity}/model/{p.name}"
        if p.kind == "box":
            rec.log(path, rr.Boxes3D(half_sizes=[p.half_sizes_m], centers=[p.center_T_m], quaternions=[p.quat_xyzw],
                                     colors=[color], fill_mode=mode), static=True)
        else:
            rec.log(path, rr.Cylinders3D(lengths=[p.length_m], radii=[p.radius_m], centers=[p.center_T_m],
                                         quaternions=[p.quat_xyzw], colors=[color], fill_mode=mode), static=True)


def corner_annotation() -> rr.AnnotationContext:
    """Class KEYPOINT_CLASS: keypoints 0-7 named A-H, connected by the 12 edges of the main body."""
    return rr.AnnotationContext([rr.ClassDescription(
        info=rr.AnnotationInfo(id=KEYPOINT_CLASS, label="ENVISAT main body"),
        keypoint_annotations=[rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(CORNER_NAMES)],
        keypoint_connections=list(EDGES))])


def log_camera(rec: rr.RecordingStream, camera: PinholeCamera, static: bool = True) -> None:
    """world/chaser/camera: the mount (K in C) and the pinhole (x right, y down, z boresight: Rerun's RDF)."""
    rec.log("world/chaser/camera", rr.Transform3D(translation=camera.pos_C_m, mat3x3=camera.R_K_from_C.T),
            static=True)
    rec.log("world/chaser/camera", rr.Pinhole(
        focal_length=camera.f_px, principal_point=[camera.cu_px + 0.5, camera.cv_px + 0.5],  # OpenCV -> Rerun
        resolution=[camera.width_px, camera.height_px], camera_xyz=rr.ViewCoordinates.RDF,
        image_plane_distance=IMAGE_PLANE_M), static=static)


def log_static_scene(rec: rr.RecordingStream, camera: PinholeCamera | None = None, estimate: bool = False) -> None:
    """Everything that does not change: the annotation context, the frame's axes, the target's model (true and,
    with estimate=True, estimated), the chaser's camera."""
    rec.log("world", corner_annotation(), static=True)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_X_UP, static=True)  # C: x radial out (up)
    parts = target_parts()
    log_target_model(rec, "world/target", parts)
    if estimate:
        log_target_model(rec, "world/target_est", parts, rgb=EST_RGB, fill="wireframe")
    log_camera(rec, camera or load_camera())


# ---------------------------------------------------------------- time series

def _times(t_s: np.ndarray, frames: np.ndarray | None = None) -> list:
    """The two timelines of a series: sim_time (duration, s) and frame (sequence)."""
    t_s = np.asarray(t_s, dtype=float)
    frames = np.arange(len(t_s)) if frames is None else np.asarray(frames)
    return [rr.TimeColumn("frame", sequence=frames.astype(np.int64)), rr.TimeColumn("sim_time", duration=t_s)]


def pose_columns(x: np.ndarray):
    """Transform3D columns of T in C from states (T, 12): translation rho_C, rotation R_C_from_T (xyzw)."""
    q_wxyz = mrp_to_quat(x[:, MRP])  # R(q) = Gamma(p)^T = R_C_from_T (envisat_pose.attitude)
    return rr.Transform3D.columns(translation=x[:, POS], quaternion=_wxyz_to_xyzw(q_wxyz))


def _point_colors(visible: np.ndarray) -> np.ndarray:
    return np.where(visible[..., None], np.array(VISIBLE_RGB, dtype=np.uint8), np.array(HIDDEN_RGB, dtype=np.uint8))


def log_truth_series(rec: rr.RecordingStream, t_s: np.ndarray, x: np.ndarray, corners_C_m: np.ndarray,
                     visible: np.ndarray, corners_px: np.ndarray, in_frame: np.ndarray,
                     frames: np.ndarray | None = None) -> None:
    """The truth over time, N samples: world/target's pose from x (N, 12); world/corners_true the corner sites
    corners_C_m (N, 8, 3) in C, coloured by visible (N, 8); the in-frame corners_px (N, 8, 2) (OpenCV px) as
    .../image/corners_true; metrics range_m, visible_corners, in_frame_corners."""
    N = len(t_s)
    idx = _times(t_s, frames)
    rec.send_columns("world/target", idx, pose_columns(x))
    ids = np.tile(np.arange(8), N)
    rec.send_columns("world/corners_true", idx, rr.Points3D.columns(
        positions=corners_C_m.reshape(-1, 3), colors=_point_colors(visible).reshape(-1, 3), keypoint_ids=ids,
        class_ids=np.full(8 * N, KEYPOINT_CLASS)).partition([8] * N))
    m = in_frame
    rec.send_columns("world/chaser/camera/image/corners_true", idx, rr.Points2D.columns(
        positions=corners_px[m] + 0.5,  # OpenCV pixel centres -> Rerun's
        colors=_point_colors(visible)[m], keypoint_ids=np.broadcast_to(np.arange(8), m.shape)[m],
        class_ids=np.full(int(m.sum()), KEYPOINT_CLASS)).partition(m.sum(axis=1)))
    rec.send_columns("metrics/range_m", idx, rr.Scalars.columns(scalars=np.linalg.norm(x[:, POS], axis=1)))
    rec.send_columns("metrics/visible_corners", idx, rr.Scalars.columns(scalars=visible.sum(axis=1).astype(float)))
    rec.send_columns("metrics/in_frame_corners", idx, rr.Scalars.columns(scalars=in_frame.sum(axis=1).astype(float)))


def position_ellipsoids(x_hat: np.ndarray, P: np.ndarray, n_sigma: float = 3.0):
    """The n-sigma ellipsoid of the position covariance P[:3, :3] (in C), expressed in the estimated target frame
    (so it can hang under world/target_est): half sizes (T, 3) m and rotations (T, 4) xyzw (ellipsoid -> T_est).
    x_hat (T, 12), P (T, 12, 12)."""
    w, V = np.linalg.eigh(P[:, POS, POS])
    V = V * np.where(np.linalg.det(V) < 0, -1.0, 1.0)[:, None, None]  # a proper rotation
    R_Test_from_ell = mrp_to_dcm(x_hat[:, MRP]) @ V  # Gamma(p) = R_T_from_C
    return n_sigma * np.sqrt(np.maximum(w, 0.0)), _wxyz_to_xyzw(rotmat_to_quat(R_Test_from_ell))


def log_estimate_series(rec: rr.RecordingStream, t_s: np.ndarray, x_hat: np.ndarray, P: np.ndarray,
                        frames: np.ndarray | None = None) -> None:
    """One run's estimate over T steps: world/target_est's pose from x_hat (T, 12) and the 3-sigma position
    ellipsoid from P (T, 12, 12)."""
    idx = _times(t_s, frames)
    rec.send_columns("world/target_est", idx, pose_columns(x_hat))
    half, quat = position_ellipsoids(x_hat, P)
    T = len(t_s)
    rec.send_columns("world/target_est/position_3sigma", idx, rr.Ellipsoids3D.columns(
        centers=np.zeros((T, 3)), half_sizes=half, quaternions=quat))
    rec.log("world/target_est/position_3sigma", rr.Ellipsoids3D.from_fields(
        colors=[EST_RGB], fill_mode=rr.components.FillMode.MajorWireframe), static=True)


def error_entity(i: int) -> str:
    """metrics/error/<block>/<axis> of state component i (0..11)."""
    return f"metrics/error/{BLOCKS[i // 3]}/{AXES[i % 3]}"


def log_error_series(rec: rr.RecordingStream, t_s: np.ndarray, err: np.ndarray, filter_3sigma: np.ndarray,
                     sample_3sigma: np.ndarray | None = None, frames: np.ndarray | None = None,
                     run_ids: Iterable[int] | None = None) -> None:
    """Error series with their bands, per state component, in the statistics' units (analysis.stats: attitude a
    rotation vector, rad), shown in BLOCKS' units. err (R, T, 12): one series per run; filter_3sigma (T, 12):
    the filter's 3 sigma (from P); sample_3sigma (T, 12): 3 sigma of the runs' spread, or None."""
    R, T = err.shape[0], len(t_s)
    idx = _times(t_s, frames)
    run_ids = list(range(R)) if run_ids is None else list(run_ids)
    for i in range(12):
        path, s = error_entity(i), DISPLAY_SCALE[i]
        if R:
            rec.log(path, rr.SeriesLines(names=[f"run {r}" for r in run_ids], widths=[1.0] * R), static=True)
            rec.send_columns(path, idx,
                             rr.Scalars.columns(scalars=(err[:, :, i].T * s).reshape(-1)).partition([R] * T))
        bands = [("filter_3sigma", filter_3sigma, SIGMA_RGB)]
        if sample_3sigma is not None:
            bands.append(("sample_3sigma", sample_3sigma, SAMPLE_SIGMA_RGB))
        for name, sig, rgb in bands:
            rec.log(f"{path}/{name}", rr.SeriesLines(names=[f"+{name}", f"-{name}"], colors=[rgb, rgb],
                                                     widths=[2.0, 2.0]), static=True)
            band = np.stack([sig[:, i], -sig[:, i]], axis=1) * s
            rec.send_columns(f"{path}/{name}", idx, rr.Scalars.columns(scalars=band.reshape(-1)).partition([2] * T))


def estimate_bands(x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray):
    """Errors and bands of R runs in the statistics' units: err (R, T, 12); the filter's 3 sigma (T, 12) =
    3 sqrt(mean over runs of the variance of A P A^T) (A: analysis.stats.display_transform, the MRP block as a
    rotation vector), as analysis.stats.CampaignStats.filter_3sigma; 3 x the sample std over runs (ddof 1) or
    None for one run."""
    err = component_errors(x_true, x_hat)
    var = np.zeros(x_hat.shape[1:])
    for r in range(x_hat.shape[0]):  # one run at a time: A P A^T of every run at once would double P's memory
        A = display_transform(x_hat[r, :, MRP])
        var += np.einsum("tij,tjk,tik->ti", A, P[r], A)
    filt = 3.0 * np.sqrt(var / x_hat.shape[0])
    samp = 3.0 * err.std(axis=0, ddof=1) if err.shape[0] > 1 else None
    return err, filt, samp


# ---------------------------------------------------------------- blueprints

def _scene_views(image: bool) -> rrb.Vertical:
    cam = rrb.Spatial2DView(origin="world/chaser/camera", name="camera image" if image else "camera (corners)",
                            contents=["$origin/**", "- $origin/image/mask/**", "- $origin/image/depth/**"])
    return rrb.Vertical(rrb.Spatial3DView(origin="world", name="3D: chaser LVLH frame C (m)"), cam,
                        row_shares=[3, 2])


def error_plots() -> rrb.Grid:
    """The 12 error plots, one per state component, each with its runs and +-3 sigma bands."""
    return rrb.Grid(*[rrb.TimeSeriesView(origin=error_entity(i), name=f"{BLOCKS[i // 3]} {AXES[i % 3]} error")
                      for i in range(12)], grid_columns=3)


def truth_blueprint() -> rrb.Blueprint:
    plots = rrb.Vertical(rrb.TimeSeriesView(origin="metrics/range_m", name="range (m)"),
                         rrb.TimeSeriesView(origin="metrics", contents=["metrics/visible_corners",
                                                                         "metrics/in_frame_corners"],
                                            name="visible / in-frame corners"))
    return rrb.Blueprint(rrb.Horizontal(_scene_views(False), plots, column_shares=[3, 2]), collapse_panels=True)


def estimate_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(rrb.Horizontal(_scene_views(False), error_plots(), column_shares=[2, 3]),
                         collapse_panels=True)


def samples_blueprint() -> rrb.Blueprint:
    cam = "world/chaser/camera"
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin=cam, name="image and corners",
                          contents=["$origin/**", "- $origin/image/mask/**", "- $origin/image/depth/**"]),
        rrb.Vertical(rrb.Spatial2DView(origin=cam, name="mask", contents=["$origin/image/mask/**",
                                                                           "$origin/image/corners_true/**"]),
                     rrb.Spatial2DView(origin=cam, name="depth", contents=["$origin/image/depth/**"]),
                     rrb.Spatial3DView(origin="world", name="3D: camera frame C (m)")),
        column_shares=[3, 2]), collapse_panels=True)


# ---------------------------------------------------------------- files

class _Recording:
    """A recording saved to `path` atomically: `with _Recording(path, blueprint) as rec: ...`."""

    def __init__(self, path: str, blueprint: rrb.Blueprint):
        self.path, self.blueprint = path, blueprint

    def __enter__(self) -> rr.RecordingStream:
        self._atomic = atomic_path(self.path, suffix=".rrd")
        tmp = self._atomic.__enter__()
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()), send_properties=False)
        self.rec.set_log_time_enabled(False)  # only the two timelines of the design, sim_time and frame
        self.rec.set_log_tick_enabled(False)
        self.rec.save(tmp, default_blueprint=self.blueprint)
        return self.rec

    def __exit__(self, *exc) -> bool:
        try:
            self.rec.flush()
            self.rec.disconnect()  # closes the file before it is renamed
        finally:
            self._atomic.__exit__(*exc)
        return False


def write_truth_recording(path: str, truth: TruthTrajectory) -> str:
    """`envisat simulate --rrd`: the truth (target pose, corners, visibility over time) as a recording."""
    with _Recording(path, truth_blueprint()) as rec:
        log_static_scene(rec)
        log_truth_series(rec, truth.t_s, truth.x, truth.corners_C_m, truth.visible, truth.corners_px, truth.in_frame)
    return path


def truth_rows(truth: TruthTrajectory, t_s: np.ndarray) -> np.ndarray:
    """Indices of the truth's samples at the times t_s (the filter's grid is a subsample of the truth's)."""
    k = np.clip(np.searchsorted(truth.t_s, t_s - 1e-9), 0, len(truth.t_s) - 1)
    if not np.allclose(truth.t_s[k], t_s, atol=1e-6):
        raise ValueError("the estimates' times are not samples of the truth")
    return k


def write_estimates_recording(path: str, est: Estimates, truth: TruthTrajectory | None = None,
                              max_error_runs: int | None = None) -> str:
    """`envisat estimate --rrd`: truth and run 0's estimate with its 3-sigma ellipsoid, the error series of
    every run (the first max_error_runs if given) with the filter's and the runs' +-3 sigma bands. With the truth
    trajectory, its corners and visibility at the filter's steps too."""
    err, filt, samp = estimate_bands(est.x_true, est.x_hat, est.P)
    n = err.shape[0] if max_error_runs is None else min(err.shape[0], max_error_runs)
    with _Recording(path, estimate_blueprint()) as rec:
        log_static_scene(rec, estimate=True)
        _log_truth_on_grid(rec, est.t_s, est.x_true[0], truth)
        log_estimate_series(rec, est.t_s, est.x_hat[0], est.P[0])
        log_error_series(rec, est.t_s, err[:n], filt, samp)
    return path


def _log_truth_on_grid(rec, t_s, x_true, truth: TruthTrajectory | None) -> None:
    if truth is None:
        rec.send_columns("world/target", _times(t_s), pose_columns(x_true))
        return
    k = truth_rows(truth, t_s)
    log_truth_series(rec, t_s, x_true, truth.corners_C_m[k], truth.visible[k], truth.corners_px[k], truth.in_frame[k])


def write_campaign_recording(path: str, t_s: np.ndarray, x_true: np.ndarray, x_hat0: np.ndarray, P0: np.ndarray,
                             sample_err: np.ndarray, filter_3sigma: np.ndarray, sample_3sigma: np.ndarray | None,
                             truth: TruthTrajectory | None = None) -> str:
    """`envisat montecarlo --rrd`: the truth x_true (T, 12) and run 0's estimate x_hat0 (T, 12) with its
    3-sigma ellipsoid from P0 (T, 12, 12); the kept sample runs' errors sample_err (S, T, 12) with the campaign's
    filter_3sigma and sample_3sigma (T, 12) over all runs (analysis.stats.CampaignStats)."""
    with _Recording(path, estimate_blueprint()) as rec:
        log_static_scene(rec, estimate=True)
        _log_truth_on_grid(rec, t_s, x_true, truth)
        log_estimate_series(rec, t_s, x_hat0, P0)
        log_error_series(rec, t_s, sample_err, filter_3sigma, sample_3sigma)
    return path


DETECTED_RGB = (255, 200, 0)
ROI_RGB = (0, 200, 255)


def log_image_series(rec: rr.RecordingStream, t_s: np.ndarray, images: list[bytes],
                     media_type: str = "image/jpeg", frames: np.ndarray | None = None) -> int:
    """world/chaser/camera/image: one encoded image (JPEG or PNG bytes) per frame; b'' (a skipped frame, e.g.
    in eclipse) logs nothing. Returns the number of images logged."""
    frames = np.arange(len(t_s)) if frames is None else np.asarray(frames)
    n = 0
    for k, blob in enumerate(images):
        if not blob:
            continue
        rec.set_time("frame", sequence=int(frames[k]))
        rec.set_time("sim_time", duration=float(t_s[k]))
        rec.log("world/chaser/camera/image", rr.EncodedImage(contents=blob, media_type=media_type))
        n += 1
    return n


def log_detection_series(rec: rr.RecordingStream, t_s: np.ndarray, corners_px: np.ndarray, visible: np.ndarray,
                         roi_px: np.ndarray | None = None, frames: np.ndarray | None = None) -> None:
    """The detector's named corners per frame as world/chaser/camera/image/corners_detected (keypoints A-H of
    the annotation context, so the viewer draws the 12 edges between found corners): corners_px (T, 8, 2)
    OpenCV px, visible (T, 8) bool (found). roi_px (T, 3) (x0, y0, side), NaN rows without a region of
    interest: .../image/roi as a box."""
    idx = _times(t_s, frames)
    m = np.asarray(visible, dtype=bool) & np.isfinite(corners_px).all(-1)
    rec.log("world/chaser/camera/image/corners_detected", rr.Points2D.from_fields(colors=[DETECTED_RGB], radii=[3.0]),
            static=True)
    rec.send_columns("world/chaser/camera/image/corners_detected", idx, rr.Points2D.columns(
        positions=np.asarray(corners_px)[m] + 0.5,  # OpenCV pixel centres -> Rerun's
        keypoint_ids=np.broadcast_to(np.arange(8), m.shape)[m],
        class_ids=np.full(int(m.sum()), KEYPOINT_CLASS)).partition(m.sum(axis=1)))
    rec.send_columns("metrics/detected_corners", idx, rr.Scalars.columns(scalars=m.sum(axis=1).astype(float)))
    if roi_px is not None:
        roi = np.asarray(roi_px, dtype=float)
        has = np.isfinite(roi).all(-1)
        rec.log("world/chaser/camera/image/roi", rr.Boxes2D.from_fields(colors=[ROI_RGB]), static=True)
        rec.send_columns("world/chaser/camera/image/roi", idx, rr.Boxes2D.columns(
            centers=roi[has, 0:2] + 0.5 * roi[has, 2:3], half_sizes=np.repeat(0.5 * roi[has, 2:3], 2, axis=1),
        ).partition(has.astype(int)))


def closed_loop_blueprint() -> rrb.Blueprint:
    cam = rrb.Spatial2DView(origin="world/chaser/camera", name="camera image, true (green/red) and detected corners",
                            contents=["$origin/**"])
    left = rrb.Vertical(cam, rrb.Spatial3DView(origin="world", name="3D: chaser LVLH frame C (m)"), row_shares=[1, 1])
    return rrb.Blueprint(rrb.Horizontal(left, error_plots(), column_shares=[2, 3]), collapse_panels=True)


def write_closed_loop_recording(path: str, est: Estimates, truth: TruthTrajectory, images: list[bytes],
                                corners_px: np.ndarray, visible: np.ndarray, roi_px: np.ndarray | None = None,
                                media_type: str = "image/jpeg") -> str:
    """`envisat run`: the truth, run 0's estimate with its 3-sigma ellipsoid, every run's errors with +-3 sigma
    bands, and run 0's camera: one encoded image per frame (images (T,) bytes, b'' when skipped), the true
    corners, the detected corners corners_px (T, 8, 2) where visible (T, 8), the region of interest roi_px
    (T, 3). Timelines: frame = the filter step, sim_time."""
    err, filt, samp = estimate_bands(est.x_true, est.x_hat, est.P)
    with _Recording(path, closed_loop_blueprint()) as rec:
        log_static_scene(rec, estimate=True)
        _log_truth_on_grid(rec, est.t_s, est.x_true[0], truth)
        log_estimate_series(rec, est.t_s, est.x_hat[0], est.P[0])
        log_error_series(rec, est.t_s, err, filt, samp)
        log_detection_series(rec, est.t_s, corners_px, visible, roi_px)
        log_image_series(rec, est.t_s, images, media_type)
    return path


@dataclass(frozen=True)
class Sample:
    """A dataset sample as the recording shows it: image_png (PNG bytes of the 8-bit image as training sees it),
    label (the label dict: corners_px, visible, in_frame, K, R_cam_from_target, t_cam_from_target_m,
    depth_scale_m, x, scene), mask (H, W) uint8 or None, depth_png (16-bit PNG bytes) or None."""

    key: str
    image_png: bytes
    label: dict
    mask: np.ndarray | None = None
    depth_png: bytes | None = None


def write_samples_recording(path: str, samples: Iterable[Sample]) -> str:
    """`envisat dataset inspect --rrd`: per sample (timeline `frame` = its index; `sim_time` where the label's
    scene has t_s), the image (its PNG as stored), the labelled corners, the mask, the depth, the camera's
    intrinsics and the target's pose in the camera."""
    base = load_camera()
    parts = target_parts()
    with _Recording(path, samples_blueprint()) as rec:
        rec.log("world", corner_annotation(), static=True)
        rec.log("world/chaser/camera/image/mask", rr.AnnotationContext(
            [rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(MASK_CLASSES)]), static=True)
        log_target_model(rec, "world/target", parts)
        rec.log("world/chaser/camera", rr.Transform3D(translation=base.pos_C_m, mat3x3=base.R_K_from_C.T),
                static=True)
        for i, s in enumerate(samples):
            rec.set_time("frame", sequence=i)
            t = s.label.get("scene", {}).get("t_s")
            if t is not None:
                rec.set_time("sim_time", duration=float(t))
            lab = s.label
            K = np.asarray(lab["K"], dtype=float)
            h, w = (s.mask.shape if s.mask is not None else (int(round(2 * K[1, 2] + 1)), int(round(2 * K[0, 2] + 1))))
            rec.log("world/chaser/camera", rr.Pinhole(
                focal_length=[K[0, 0], K[1, 1]], principal_point=[K[0, 2] + 0.5, K[1, 2] + 0.5],  # OpenCV -> Rerun
                resolution=[w, h], image_plane_distance=IMAGE_PLANE_M))
            rec.log("world/chaser/camera/image", rr.EncodedImage(contents=s.image_png, media_type="image/png"))
            px = np.asarray(lab["corners_px"], dtype=float)
            vis = np.asarray(lab["visible"], dtype=bool)
            m = np.asarray(lab["in_frame"], dtype=bool)
            rec.log("world/chaser/camera/image/corners_true", rr.Points2D(
                positions=px[m] + 0.5, keypoint_ids=np.arange(8)[m], class_ids=np.full(int(m.sum()), KEYPOINT_CLASS),
                colors=_point_colors(vis)[m], labels=[CORNER_NAMES[k] for k in np.flatnonzero(m)]))
            if s.mask is not None:
                rec.log("world/chaser/camera/image/mask", rr.SegmentationImage(s.mask, opacity=0.6))
            if s.depth_png is not None:
                rec.log("world/chaser/camera/image/depth", rr.EncodedDepthImage(
                    s.depth_png, media_type="image/png", meter=1.0 / float(lab["depth_scale_m"])))
            # the target's pose in the camera, then in C: R_C_from_T = R_K_from_C^T R_K_from_T
            R_KT = np.asarray(lab["R_cam_from_target"], dtype=float)
            t_K = np.asarray(lab["t_cam_from_target_m"], dtype=float)
            rec.log("world/target", rr.Transform3D(
                translation=base.R_K_from_C.T @ t_K + base.pos_C_m,
                quaternion=_wxyz_to_xyzw(rotmat_to_quat(base.R_K_from_C.T @ R_KT))))
    return path


def read_recording(path: str) -> tuple[dict, dict]:
    """Read a .rrd back as plain Python: (static, temporal), where static is {entity: {column: value}} and
    temporal is {entity: {column: [rows sorted by the frame timeline]}} (columns as Rerun names them)."""
    static: dict = {}
    temporal: dict = {}
    with warnings.catch_warnings():  # older TrackRecorder files have no footer (read whole, as here: nothing lost)
        warnings.filterwarnings("ignore", message=".*no footer/manifest.*")
        reader = rr.chunk.RrdReader(str(path))
    for chunk in reader.stream().collect().stream():
        d = chunk.to_record_batch().to_pydict()
        d.pop("rerun.controls.RowId", None)
        if "frame" in d:
            t = temporal.setdefault(chunk.entity_path, {})
            rows = len(t["frame"]) if "frame" in t else 0
            n = len(d["frame"])
            for k in set(t) | set(d):  # chunks of one entity may carry different columns (a Clear, say)
                t.setdefault(k, [None] * rows).extend(d.get(k, [None] * n))
        else:
            static.setdefault(chunk.entity_path, {}).update({k: v[-1] for k, v in d.items()})
    for t in temporal.values():
        order = np.argsort(t["frame"], kind="stable")
        for k in t:
            t[k] = [t[k][i] for i in order]
    return static, temporal


# ---------------------------------------------------------------- a tracker's run, streamed frame by frame

AXIS_RGB = ((230, 60, 60), (40, 170, 60), (60, 110, 240))  # x, y, z
PLOT_BLOCKS = (("position_m", "position error (m)", POS, 1.0), ("velocity_m_s", "velocity error (m/s)", VEL, 1.0),
               ("attitude_deg", "attitude error (deg)", MRP, 180.0 / np.pi),
               ("angular_velocity_deg_s", "angular velocity error (deg/s)", RATE, 180.0 / np.pi))
NEES_BAND_12 = (4.404, 23.337)  # chi-square 12 dof, 2.5 % and 97.5 %


def whole_run(view_kind, **kw):
    """A time-series view that shows the whole run on both timelines (not a trailing window) with its legend
    hidden (the series are named in the view's title and coloured x red, y green, z blue). Two settings make
    it: the data queried (time_ranges: every time, not the default window at the time cursor) and the plot's
    own x axis (axis_x: view_range infinite, each view on its own; without it the viewer opens a plot on the
    ~50 s before the cursor, which a file opens at its end: a 600 s run showed +9m30s..+10m20s)."""
    inf = rrb.TimeRangeBoundary.infinite()
    ranges = [rrb.VisibleTimeRange(tl, start=inf, end=inf) for tl in ("sim_time", "frame")]
    axis = rrb.TimeAxis(link="Independent", view_range=rrb.TimeRange(start=inf, end=inf))
    return view_kind(time_ranges=ranges, axis_x=axis, plot_legend=rrb.PlotLegend(visible=False), **kw)


def track_blueprint(with_truth: bool) -> rrb.Blueprint:
    """The camera image (detections, projected estimate, region of interest) and the 3D scene on the left; six
    plots on the right: with a truth the four error blocks with +-3 sigma, NEES, the hypotheses and status;
    without, the position and attitude 3 sigma, the range, NIS, the hypotheses and status."""
    cam = rrb.Spatial2DView(origin="world/chaser/camera", name="camera: detected (yellow, rejected red), estimate (blue)",
                            contents=["$origin/**"])
    left = rrb.Vertical(cam, rrb.Spatial3DView(origin="world", name="3D: chaser LVLH frame C (m)"), row_shares=[1, 1])
    if with_truth:
        plots = [whole_run(rrb.TimeSeriesView, origin=f"metrics/error/{b}",
                           name=f"{title}: x red, y green, z blue, +-3 sigma thin") for b, title, _, _ in PLOT_BLOCKS]
        plots.append(whole_run(rrb.TimeSeriesView, origin="metrics/nees", name="NEES (12 dof; 95 % band grey)"))
    else:
        plots = [whole_run(rrb.TimeSeriesView, origin="metrics/sigma3/position_m", name="position 3 sigma (m): x, y, z"),
                 whole_run(rrb.TimeSeriesView, origin="metrics/sigma3/attitude_deg", name="attitude 3 sigma (deg)"),
                 whole_run(rrb.TimeSeriesView, origin="metrics/range_est_m", name="estimated range (m)"),
                 whole_run(rrb.TimeSeriesView, origin="metrics/nis", name="NIS / dof")]
    plots.append(whole_run(rrb.TimeSeriesView, origin="metrics/tracker",
                           name="tracker: best hypothesis probability, status (0 acquiring, 1 tracking, 2 lost, "
                           "3 coasting)"))
    return rrb.Blueprint(rrb.Horizontal(left, rrb.Grid(*plots, grid_columns=2), column_shares=[2, 3]),
                         collapse_panels=True)


def project_state_px(x: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """The corners A-H (8, 2) px (OpenCV) of a state (12,) through the camera (core geometry only)."""
    from envisat_pose.geometry import project_K

    corners_C = x[POS] + load_geometry().corners_T_m @ mrp_to_dcm(x[MRP])  # rho + Gamma^T v
    return project_K((corners_C - camera.pos_C_m) @ camera.R_K_from_C.T, camera)


# A file sink's chunks: Rerun's batcher cuts a chunk per entity at every flush, by default every 200 ms of wall
# time; at ~0.1 s a frame that is ~23 chunks a frame (one per entity logged) of 1-2 rows each, each with its own
# Arrow schema in the file, and Rerun's file sink keeps ~2 kB of metadata per chunk in memory for the file's
# footer (its chunk manifest) until the file is closed: the 45-70 MiB per 1000 lit frames an `envisat run` grew
# by (bench/memory.py). A file sink here therefore cuts a chunk every FILE_CHUNK_ROWS rows of an entity (frames,
# whatever the wall time; FILE_FLUSH_TICK_S flushes rarely logged entities): what is pending is at most
# FILE_CHUNK_ROWS rows of each entity (or Rerun's flush_num_bytes of images), the footer's manifest holds ~100x
# fewer chunks (~0.5 kB a frame) and the file is ~10x smaller (1803 frames at 128 px: 41 MB before, 4 MB). The
# footer is written (`rerun rrd verify` passes; Rerun warns on stderr when a file has none). A live viewer
# (spawn, connect) keeps Rerun's default, low-latency batching.
FILE_CHUNK_ROWS = 100
FILE_FLUSH_TICK_S = 60.0


def file_batcher() -> rr.ChunkBatcherConfig:
    """The batcher of a recording written to a file by TrackRecorder (see FILE_CHUNK_ROWS)."""
    return rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=FILE_FLUSH_TICK_S), flush_num_rows=FILE_CHUNK_ROWS)


class TrackRecorder:
    """A tracker's run logged to Rerun as it goes, frame by frame (nothing kept in memory).

    sink: 'save:PATH' (a .rrd written under a temporary name and renamed by close(); chunks of FILE_CHUNK_ROWS
    rows, so memory stays nearly flat however long the run; the footer written), 'spawn' (a local viewer) or 'connect:URL' (a
    running viewer, e.g. rerun+http://127.0.0.1:9876/proxy). with_truth: error plots (the caller passes x_true
    per frame) instead of the estimate's own uncertainty."""

    def __init__(self, sink: str, camera: PinholeCamera, with_truth: bool, title: str = ""):
        self.camera, self.with_truth = camera, with_truth
        kind, _, arg = sink.partition(":")
        if kind not in ("save", "spawn", "connect"):
            raise ValueError(f"recording sink {sink!r}: expected 'save:PATH', 'spawn' or 'connect:URL'")
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()), send_properties=False,
                                      batcher_config=file_batcher() if kind == "save" else None)
        self.rec.set_log_time_enabled(False)
        self.rec.set_log_tick_enabled(False)
        blueprint = track_blueprint(with_truth)
        self._atomic = None
        if kind == "save":
            self._atomic = atomic_path(arg, suffix=".rrd")
            self.rec.save(self._atomic.__enter__(), default_blueprint=blueprint)
        elif kind == "spawn":
            self.rec.spawn(default_blueprint=blueprint)
        else:
            self.rec.connect_grpc(arg or None, default_blueprint=blueprint)
        if title:
            self.rec.log("description", rr.TextDocument(title), static=True)
        # what the status series' codes mean (envisat_pose.status.legend(), JSON), beside the data
        self.rec.log("status_legend", rr.TextDocument(legend_json()), static=True)
        log_static_scene(self.rec, camera, estimate=True)
        self._log_series_styles()
        self.status = -1

    def _log_series_styles(self) -> None:
        rec = self.rec
        if self.with_truth:
            for b, _, _, _ in PLOT_BLOCKS:
                for a, rgb in zip(AXES, AXIS_RGB):
                    rec.log(f"metrics/error/{b}/{a}", rr.SeriesLines(colors=[rgb], widths=[1.5], names=[a]), static=True)
                    rec.log(f"metrics/error/{b}/{a}_3sigma", rr.SeriesLines(
                        colors=[rgb, rgb], widths=[0.5, 0.5], names=[f"+3s {a}", f"-3s {a}"]), static=True)
            rec.log("metrics/nees/value", rr.SeriesLines(colors=[(20, 20, 20)], widths=[1.5], names=["NEES"]), static=True)
            rec.log("metrics/nees/band", rr.SeriesLines(colors=[(150, 150, 150)] * 2, widths=[1.0, 1.0],
                                                        names=["2.5 %", "97.5 %"]), static=True)
        else:
            for a, rgb in zip(AXES, AXIS_RGB):
                rec.log(f"metrics/sigma3/position_m/{a}", rr.SeriesLines(colors=[rgb], names=[a]), static=True)
                rec.log(f"metrics/sigma3/attitude_deg/{a}", rr.SeriesLines(colors=[rgb], names=[a]), static=True)
        rec.log("metrics/tracker/p_best", rr.SeriesLines(colors=[(60, 140, 255)], widths=[1.5],
                                                         names=["best hypothesis"]), static=True)
        rec.log("metrics/tracker/status", rr.SeriesLines(colors=[(20, 20, 20)], widths=[1.5], names=["status"]),
                static=True)
        rec.log("world/chaser/camera/image/corners_detected", rr.Points2D.from_fields(radii=[3.0]), static=True)
        rec.log("world/chaser/camera/image/corners_estimated", rr.Points2D.from_fields(colors=[EST_RGB], radii=[2.0]),
                static=True)
        rec.log("world/chaser/camera/image/roi", rr.Boxes2D.from_fields(colors=[ROI_RGB]), static=True)
        rec.log("world/target_est/position_3sigma", rr.Ellipsoids3D.from_fields(
            colors=[EST_RGB], fill_mode=rr.components.FillMode.MajorWireframe), static=True)

    def log_frame(self, k: int, est: dict, image: np.ndarray | None, jpeg_quality: int = 80,
                  x_true: np.ndarray | None = None, corners_true_px: np.ndarray | None = None,
                  in_frame: np.ndarray | None = None) -> None:
        """Frame k: est holds x_hat (12,), P (12, 12), status (int), p_best, nis, nis_dof, corners_px (8, 2),
        visible (8,), rejected (8,), roi_px (3,) (NaN without); image (H, W) uint8 or None; with a truth, x_true
        (12,) and the true corners corners_true_px (8, 2) where in_frame (8,)."""
        import cv2

        rec, cam = self.rec, self.camera
        rec.set_time("frame", sequence=int(k))
        t_s = float(est["t_s"]) if "t_s" in est else float(k)
        rec.set_time("sim_time", duration=t_s)
        if image is not None:
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
            if ok:
                rec.log("world/chaser/camera/image", rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
        status = int(est["status"])
        if status != self.status:
            rec.log("events", rr.TextLog(f"t = {t_s:.1f} s: {STATUS_NAMES[status]}",
                                         level="WARN" if status == 2 else "INFO"))
            self.status = status
        rec.log("metrics/tracker/status", rr.Scalars(float(status)))
        rec.log("metrics/tracker/p_best", rr.Scalars(float(est["p_best"])))
        m = np.asarray(est["visible"], bool) & np.isfinite(est["corners_px"]).all(-1)
        rej = np.asarray(est["rejected"], bool)[m]
        rec.log("world/chaser/camera/image/corners_detected", rr.Points2D(
            np.asarray(est["corners_px"])[m] + 0.5, keypoint_ids=np.flatnonzero(m), class_ids=KEYPOINT_CLASS,
            colors=np.where(rej[:, None], np.array(HIDDEN_RGB, np.uint8), np.array(DETECTED_RGB, np.uint8))))
        x, P = np.asarray(est["x_hat"], float), np.asarray(est["P"], float)
        if status == 1:
            uv = project_state_px(x, cam)
            rec.log("world/chaser/camera/image/corners_estimated", rr.Points2D(
                uv + 0.5, keypoint_ids=np.arange(8), class_ids=KEYPOINT_CLASS))
            rec.log("world/target_est", rr.Transform3D(translation=x[POS],
                                                       quaternion=_wxyz_to_xyzw(mrp_to_quat(x[MRP]))))
            half, quat = position_ellipsoids(x[None], P[None])
            rec.log("world/target_est/position_3sigma", rr.Ellipsoids3D(centers=[[0.0, 0.0, 0.0]], half_sizes=half,
                                                                         quaternions=quat))
        else:
            rec.log("world/chaser/camera/image/corners_estimated", rr.Clear(recursive=False))
        roi = np.asarray(est["roi_px"], float)
        if np.isfinite(roi).all():
            rec.log("world/chaser/camera/image/roi", rr.Boxes2D(centers=[roi[0:2] + 0.5 * roi[2]],
                                                                half_sizes=[[0.5 * roi[2]] * 2]))
        else:
            rec.log("world/chaser/camera/image/roi", rr.Clear(recursive=False))
        A = display_transform(x[MRP])
        sig3 = 3.0 * np.sqrt(np.maximum(np.diagonal(A @ P @ A.T), 0.0))  # statistics' units (attitude rad)
        if x_true is not None:
            rec.log("world/target", rr.Transform3D(translation=x_true[POS],
                                                   quaternion=_wxyz_to_xyzw(mrp_to_quat(x_true[MRP]))))
            if corners_true_px is not None:
                f = np.asarray(in_frame, bool)
                rec.log("world/chaser/camera/image/corners_true", rr.Points2D(
                    np.asarray(corners_true_px)[f] + 0.5, colors=[VISIBLE_RGB], radii=[1.5]))
        if self.with_truth and x_true is not None and status == 1:
            err = component_errors(x_true, x)
            for b, _, block, s in PLOT_BLOCKS:
                for j, a in enumerate(AXES):
                    rec.log(f"metrics/error/{b}/{a}", rr.Scalars(float(err[block][j] * s)))
                    rec.log(f"metrics/error/{b}/{a}_3sigma", rr.Scalars([float(sig3[block][j] * s),
                                                                         float(-sig3[block][j] * s)]))
            e = component_errors(x_true, x)
            Pd = A @ P @ A.T
            rec.log("metrics/nees/value", rr.Scalars(float(e @ np.linalg.solve(Pd, e))))
            rec.log("metrics/nees/band", rr.Scalars(list(NEES_BAND_12)))
        elif not self.with_truth and status == 1:
            for j, a in enumerate(AXES):
                rec.log(f"metrics/sigma3/position_m/{a}", rr.Scalars(float(sig3[POS][j])))
                rec.log(f"metrics/sigma3/attitude_deg/{a}", rr.Scalars(float(np.degrees(sig3[MRP][j]))))
            rec.log("metrics/range_est_m", rr.Scalars(float(np.linalg.norm(x[POS]))))
            if est["nis_dof"]:
                rec.log("metrics/nis", rr.Scalars(float(est["nis"]) / float(est["nis_dof"])))

    def close(self) -> None:
        """Flush; a saved recording is renamed to its path only now (complete)."""
        try:
            self.rec.flush()
            self.rec.disconnect()
        finally:
            if self._atomic is not None:
                self._atomic.__exit__(None, None, None)
                self._atomic = None
