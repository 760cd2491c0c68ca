"""The recording's layout (analysis/recording.py lists the entities): constants, the target's model (any Target:
its surface, skeleton and keypoints), the series loggers and the blueprints (what the viewer shows at load). Two
conventions change at this edge: Rerun quaternions are (x, y, z, w), ours (w, x, y, z); Rerun's pixel (0, 0)
covers [0, 1]^2 (centre 0.5), ours follow OpenCV (centre 0), so image points and the principal point get +0.5."""

from __future__ import annotations

from typing import Iterable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from envisat_pose.attitude import mrp_to_dcm, mrp_to_quat, rotmat_to_quat
from envisat_pose.geometry import PinholeCamera, load_camera
from envisat_pose.state import MRP, N_STATE, POS, RATE, VEL
from envisat_pose.target import Target, default_target

from .stats import chi2_mean_bounds, component_errors, display_transform, nees_of_errors, state_errors

APPLICATION_ID = "envisat_pose"
KEYPOINT_CLASS = 0  # class of the annotation context whose keypoints are the target's (ENVISAT: corners A-H)
BLOCKS = ("position_m", "velocity_m_s", "attitude_deg", "angular_velocity_deg_s")
AXES = ("x", "y", "z")
# statistics' units (m, m/s, rad, rad/s; analysis.stats) -> what the plots show (m, m/s, deg, deg/s)
DISPLAY_SCALE = np.array([1.0] * 6 + [180.0 / np.pi] * 6)
MASK_CLASSES = ("background", "face +x", "face -x", "face +y", "face -y", "face +z", "face -z", "array and boom",
                "appendages")  # design.md, Shard: mask values 0-8 (a target taking the class appearance)

VISIBLE_RGB = (40, 200, 60)
HIDDEN_RGB = (220, 50, 50)
EST_RGB = (60, 140, 255)
SIGMA_RGB = (220, 50, 50)
SAMPLE_SIGMA_RGB = (20, 20, 20)
IMAGE_PLANE_M = 8.0  # where the viewer draws the image plane in 3D, m in front of the camera


DETECTED_RGB = (255, 200, 0)
ROI_RGB = (0, 200, 255)


def _wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Our (w, x, y, z) -> Rerun's (x, y, z, w)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


# ---------------------------------------------------------------- the target's model (envisat_pose.target)

def rgb8(rgb) -> np.ndarray:
    """Colours (..., 3) in [0, 1] -> uint8 (..., 3), rounded."""
    return np.clip(np.round(np.asarray(rgb, dtype=float) * 255.0), 0, 255).astype(np.uint8)


def surface_triangles(target: Target) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The target's drawn surface (Target.mesh: its triangles, in the same order) as Rerun draws it flat-shaded,
    each triangle with three vertices of its own (F triangles): positions (3F, 3) in T, m; normals (3F, 3), the
    triangle's unit outward normal (zero for a degenerate one); colours (3F, 3) uint8, the material rgb of the
    triangle's geom (TargetGeom.rgb, via the surface's face -> geom map)."""
    surface = target.surface
    keep = target.drawn()[surface.face_geom]
    tri = surface.mesh.vertices_T_m[surface.mesh.faces[keep]]  # (F, 3 vertices, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
    rgb = rgb8([g.rgb for g in target.geoms])[surface.face_geom[keep]]
    return tri.reshape(-1, 3), np.repeat(n, 3, axis=0), np.repeat(rgb, 3, axis=0)


def log_target_mesh(rec: rr.RecordingStream, entity: str, target: Target) -> None:
    """`entity`/model, static: the target's drawn surface as one Mesh3D in T (surface_triangles: flat-shaded,
    each triangle in its geom's material colour)."""
    pos, normals, colors = surface_triangles(target)
    rec.log(f"{entity}/model", rr.Mesh3D(vertex_positions=pos, triangle_indices=np.arange(len(pos)).reshape(-1, 3),
                                         vertex_normals=normals, vertex_colors=colors), static=True)


def log_target_wireframe(rec: rr.RecordingStream, entity: str, target: Target, rgb=EST_RGB,
                         static: bool = True) -> None:
    """`entity`/model: the target's skeleton (Target.skeleton: keypoint pairs along its sharp edges) as line
    segments in T, and `entity`/model/keypoints its keypoints (named on hover), both in rgb: the light copy of
    the shape that an estimate's pose carries. static False: at the current time (a Clear can hide it again;
    Rerun never clears static data)."""
    X = target.keypoints_T_m
    rec.log(f"{entity}/model", rr.LineStrips3D([X[[i, j]] for i, j in target.skeleton], colors=[rgb],
                                               radii=[rr.Radius.ui_points(1.0)]), static=static)
    rec.log(f"{entity}/model/keypoints", rr.Points3D(X, colors=[rgb], radii=[rr.Radius.ui_points(3.0)],
                                                     labels=list(target.keypoint_names), show_labels=False),
            static=static)


def corner_annotation(target: Target | None = None) -> rr.AnnotationContext:
    """Class KEYPOINT_CLASS ("<name> keypoints"): keypoint i named target.keypoint_names[i], connected along
    target.skeleton (ENVISAT: A-H and the 12 edges of the main body). target None: default_target()."""
    target = target or default_target()
    return rr.AnnotationContext([rr.ClassDescription(
        info=rr.AnnotationInfo(id=KEYPOINT_CLASS, label=f"{target.name} keypoints"),
        keypoint_annotations=[rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(target.keypoint_names)],
        keypoint_connections=[(int(i), int(j)) for i, j in target.skeleton])])


def mask_classes(mask_values: dict[str, int] | None = None) -> tuple[str, ...]:
    """The label of each mask value 0..max: mask_values None: MASK_CLASSES (the factory's classes, design.md:
    what a target that takes the class appearance writes); else {geom name: mask value} of the target's renderer
    (datagen.render_view.target_mask_values): "background", then each value's geom names joined by " + " ("" for a
    value no geom takes)."""
    if mask_values is None:
        return MASK_CLASSES
    labels = ["background"] + [""] * max(mask_values.values(), default=0)
    for name, value in mask_values.items():
        labels[value] = f"{labels[value]} + {name}" if labels[value] else name
    return tuple(labels)


def mask_annotation(mask_values: dict[str, int] | None = None) -> rr.AnnotationContext:
    """The annotation context of a segmentation mask: class i labelled mask_classes(mask_values)[i]."""
    return rr.AnnotationContext([rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(mask_classes(mask_values))])


def log_camera(rec: rr.RecordingStream, camera: PinholeCamera, static: bool = True) -> None:
    """world/chaser/camera: the mount (K in C) and the pinhole (x right, y down, z boresight: Rerun's RDF)."""
    rec.log("world/chaser/camera", rr.Transform3D(translation=camera.pos_C_m, mat3x3=camera.R_K_from_C.T),
            static=True)
    rec.log("world/chaser/camera", rr.Pinhole(
        focal_length=camera.f_px, principal_point=[camera.cu_px + 0.5, camera.cv_px + 0.5],  # OpenCV -> Rerun
        resolution=[camera.width_px, camera.height_px], camera_xyz=rr.ViewCoordinates.RDF,
        image_plane_distance=IMAGE_PLANE_M), static=static)


def log_static_scene(rec: rr.RecordingStream, camera: PinholeCamera | None = None, estimate: bool = False,
                     target: Target | None = None, truth: bool = True) -> None:
    """Everything that does not change: the target's keypoint annotation, the frame's axes, the target's model
    (with truth=True world/target/model its solid surface, drawn at the true pose; with estimate=True
    world/target_est/model its skeleton and keypoints), the chaser's camera. target None: default_target()
    (ENVISAT). A run without a truth has no true pose: its surface would be drawn at C's origin, the chaser."""
    target = target or default_target()
    rec.log("world", corner_annotation(target), static=True)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_X_UP, static=True)  # C: x radial out (up)
    if truth:
        log_target_mesh(rec, "world/target", target)
    if estimate:
        log_target_wireframe(rec, "world/target_est", target)
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
                     frames: np.ndarray | None = None, noun: str = "corners") -> None:
    """The truth over time, N samples of the target's K keypoints: world/target's pose from x (N, 12);
    world/keypoints_true the keypoint sites corners_C_m (N, K, 3) in C, coloured by visible (N, K); the in-frame
    corners_px (N, K, 2) (OpenCV px) as .../image/keypoints_true; metrics range_m, visible_keypoints,
    in_frame_keypoints (their legends "visible <noun>", "in-frame <noun>": keypoints_noun)."""
    N, K = corners_C_m.shape[:2]
    idx = _times(t_s, frames)
    rec.send_columns("world/target", idx, pose_columns(x))
    ids = np.tile(np.arange(K), N)
    rec.send_columns("world/keypoints_true", idx, rr.Points3D.columns(
        positions=corners_C_m.reshape(-1, 3), colors=_point_colors(visible).reshape(-1, 3), keypoint_ids=ids,
        class_ids=np.full(K * N, KEYPOINT_CLASS)).partition([K] * N))
    m = in_frame
    rec.send_columns("world/chaser/camera/image/keypoints_true", idx, rr.Points2D.columns(
        positions=corners_px[m] + 0.5,  # OpenCV pixel centres -> Rerun's
        colors=_point_colors(visible)[m], keypoint_ids=np.broadcast_to(np.arange(K), m.shape)[m],
        class_ids=np.full(int(m.sum()), KEYPOINT_CLASS)).partition(m.sum(axis=1)))
    rec.send_columns("metrics/range_m", idx, rr.Scalars.columns(scalars=np.linalg.norm(x[:, POS], axis=1)))
    for entity, what in (("visible_keypoints", "visible"), ("in_frame_keypoints", "in-frame")):
        rec.log(f"metrics/{entity}", rr.SeriesLines(names=[f"{what} {noun}"]), static=True)
    rec.send_columns("metrics/visible_keypoints", idx, rr.Scalars.columns(scalars=visible.sum(axis=1).astype(float)))
    rec.send_columns("metrics/in_frame_keypoints", idx, rr.Scalars.columns(scalars=in_frame.sum(axis=1).astype(float)))


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


NEES_RGB = (20, 20, 20)
BAND_RGB = (150, 150, 150)


def log_nees_styles(rec: rr.RecordingStream, runs: int = 1) -> None:
    """metrics/nees/{value,band}'s lines (static): the NEES of one run ("NEES"), or its mean over runs ("mean NEES
    over R runs"), and the two ends of its 95 % band. A tracker's run and the estimate's and campaign's
    recordings draw it alike."""
    name = "NEES" if runs == 1 else f"mean NEES over {runs} runs"
    rec.log("metrics/nees/value", rr.SeriesLines(colors=[NEES_RGB], widths=[1.5], names=[name]), static=True)
    rec.log("metrics/nees/band", rr.SeriesLines(colors=[BAND_RGB] * 2, widths=[1.0, 1.0], names=["2.5 %", "97.5 %"]),
            static=True)


def log_nees_series(rec: rr.RecordingStream, t_s: np.ndarray, nees_mean: np.ndarray, runs: int,
                    bounds: np.ndarray | None = None, frames: np.ndarray | None = None) -> None:
    """metrics/nees/value: the NEES (12 dof) averaged over `runs` runs at each of T steps, nees_mean (T,);
    metrics/nees/band: its two-sided 95 % band, bounds (2,) (None: chi2_mean_bounds(12 runs, runs), each run one
    sample at a step)."""
    T = len(t_s)
    bounds = chi2_mean_bounds(N_STATE * runs, runs) if bounds is None else np.asarray(bounds, dtype=float)
    idx = _times(t_s, frames)
    log_nees_styles(rec, runs)
    rec.send_columns("metrics/nees/value", idx, rr.Scalars.columns(scalars=np.asarray(nees_mean, dtype=float)))
    rec.send_columns("metrics/nees/band", idx,
                     rr.Scalars.columns(scalars=np.tile(bounds.reshape(2), T)).partition([2] * T))


def runs_nees(x_true: np.ndarray, x_hat: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The NEES (R, T) of R runs in the additive chart (analysis.stats.state_errors): what a recording shows where
    its caller gives none in the filter's own chart."""
    return nees_of_errors(state_errors(x_true, x_hat), P)


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

def whole_run(view_kind, legend: bool = False, **kw):
    """A time-series view that shows the whole run on both timelines (not a trailing window), its legend hidden
    unless legend (a tracker's series are named in the view's title and coloured x red, y green, z blue); every
    plot of every recording is one (an estimate's 1800 s opened on its last ~50 s before). Two settings make
    it: the data queried (time_ranges: every time, not the default window at the time cursor) and the plot's
    own x axis (axis_x: view_range infinite, each view on its own; without it the viewer opens a plot on the
    ~50 s before the cursor, which a file opens at its end: a 600 s run showed +9m30s..+10m20s)."""
    inf = rrb.TimeRangeBoundary.infinite()
    ranges = [rrb.VisibleTimeRange(tl, start=inf, end=inf) for tl in ("sim_time", "frame")]
    axis = rrb.TimeAxis(link="Independent", view_range=rrb.TimeRange(start=inf, end=inf))
    return view_kind(time_ranges=ranges, axis_x=axis, plot_legend=rrb.PlotLegend(visible=legend), **kw)


def keypoints_noun(target: Target | None = None) -> str:
    """What a view's title calls the target's keypoints: those its labels name (Target.labels_name_keypoints)
    "keypoints", ENVISAT's "corners" (A-H implied; target None: the default)."""
    return "keypoints" if target is not None and target.labels_name_keypoints else "corners"


def _scene_views(image: bool, target: Target | None = None) -> rrb.Vertical:
    cam = rrb.Spatial2DView(origin="world/chaser/camera",
                            name="camera image" if image else f"camera ({keypoints_noun(target)})",
                            contents=["$origin/**", "- $origin/image/mask/**", "- $origin/image/depth/**"])
    return rrb.Vertical(rrb.Spatial3DView(origin="world", name="3D: chaser LVLH frame C (m)"), cam,
                        row_shares=[3, 2])


def error_plots() -> rrb.Grid:
    """The 12 error plots, one per state component, each with its runs and +-3 sigma bands, over the whole run
    (whole_run; legends shown: the runs and the two bands by name)."""
    return rrb.Grid(*[whole_run(rrb.TimeSeriesView, legend=True, origin=error_entity(i),
                                name=f"{BLOCKS[i // 3]} {AXES[i % 3]} error") for i in range(12)], grid_columns=3)


def truth_blueprint(target: Target | None = None) -> rrb.Blueprint:
    """The scene on the left; the range and the count of visible and in-frame keypoints on the right (ENVISAT's
    "corners"; another target's "keypoints", out of its K). target None: default_target()."""
    count = (f"visible / in-frame keypoints (of {target.num_keypoints})" if keypoints_noun(target) == "keypoints"
             else "visible / in-frame corners")
    plots = rrb.Vertical(whole_run(rrb.TimeSeriesView, legend=True, origin="metrics/range_m", name="range (m)"),
                         whole_run(rrb.TimeSeriesView, legend=True, origin="metrics",
                                   contents=["metrics/visible_keypoints", "metrics/in_frame_keypoints"], name=count))
    return rrb.Blueprint(rrb.Horizontal(_scene_views(False, target), plots, column_shares=[3, 2]),
                         collapse_panels=True)


def nees_plot(name: str = "NEES (12 dof; 95 % band grey)", legend: bool = False) -> rrb.TimeSeriesView:
    """metrics/nees over the whole run: the NEES, or its mean over runs, with its 95 % band."""
    return whole_run(rrb.TimeSeriesView, legend=legend, origin="metrics/nees", name=name)


def estimate_blueprint(target: Target | None = None) -> rrb.Blueprint:
    """The scene on the left (its camera view titled with target's keypoints_noun); the 12 error plots and, below
    them, the NEES with its band on the right."""
    right = rrb.Vertical(error_plots(), nees_plot("NEES (12 dof): mean over runs, 95 % band", legend=True),
                         row_shares=[4, 1])
    return rrb.Blueprint(rrb.Horizontal(_scene_views(False, target), right, column_shares=[2, 3]),
                         collapse_panels=True)


def samples_blueprint(target: Target | None = None) -> rrb.Blueprint:
    """A dataset's samples: the image with its labelled keypoints (titled with target's keypoints_noun), the
    mask, the depth and the 3D scene."""
    cam = "world/chaser/camera"
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin=cam, name=f"image and {keypoints_noun(target)}",
                          contents=["$origin/**", "- $origin/image/mask/**", "- $origin/image/depth/**"]),
        rrb.Vertical(rrb.Spatial2DView(origin=cam, name="mask", contents=["$origin/image/mask/**",
                                                                           "$origin/image/keypoints_true/**"]),
                     rrb.Spatial2DView(origin=cam, name="depth", contents=["$origin/image/depth/**"]),
                     rrb.Spatial3DView(origin="world", name="3D: camera frame C (m)")),
        column_shares=[3, 2]), collapse_panels=True)


# ---------------------------------------------------------------- a tracker's run: its blueprint

AXIS_RGB = ((230, 60, 60), (40, 170, 60), (60, 110, 240))  # x, y, z
PLOT_BLOCKS = (("position_m", "position error (m)", POS, 1.0), ("velocity_m_s", "velocity error (m/s)", VEL, 1.0),
               ("attitude_deg", "attitude error (deg)", MRP, 180.0 / np.pi),
               ("angular_velocity_deg_s", "angular velocity error (deg/s)", RATE, 180.0 / np.pi))
# one run's NEES: chi-square of the state's 12 dof, the two-sided 95 % band (stats.P_BAND: 4.40 and 23.34)
NEES_BAND_12 = tuple(float(b) for b in chi2_mean_bounds(N_STATE, 1))


def track_blueprint(with_truth: bool) -> rrb.Blueprint:
    """The camera image (detections, projected estimate, region of interest) and the 3D scene on the left; plots
    on the right: with a truth the four error blocks with +-3 sigma, NEES, and the hypotheses, status and NIS in
    one; without, the position and attitude 3 sigma, the range, NIS, the hypotheses and status."""
    cam = rrb.Spatial2DView(origin="world/chaser/camera", name="camera: detected (yellow, rejected red), estimate (blue)",
                            contents=["$origin/**"])
    left = rrb.Vertical(cam, rrb.Spatial3DView(origin="world", name="3D: chaser LVLH frame C (m)"), row_shares=[1, 1])
    if with_truth:
        plots = [whole_run(rrb.TimeSeriesView, origin=f"metrics/error/{b}",
                           name=f"{title}: x red, y green, z blue, +-3 sigma thin") for b, title, _, _ in PLOT_BLOCKS]
        plots.append(nees_plot())
    else:
        plots = [whole_run(rrb.TimeSeriesView, origin="metrics/sigma3/position_m", name="position 3 sigma (m): x, y, z"),
                 whole_run(rrb.TimeSeriesView, origin="metrics/sigma3/attitude_deg", name="attitude 3 sigma (deg)"),
                 whole_run(rrb.TimeSeriesView, origin="metrics/range_est_m", name="estimated range (m)"),
                 whole_run(rrb.TimeSeriesView, origin="metrics/nis", name="NIS / dof")]
    # with a truth, the tracker's own evidence (NIS / dof) shares the tracker's panel (six panels at most)
    nis = (["$origin/nis"], ", NIS / dof") if with_truth else ([], "")
    plots.append(whole_run(rrb.TimeSeriesView, origin="metrics", contents=["$origin/tracker/**", *nis[0]],
                           name="tracker: best hypothesis probability, status (0 acquiring, 1 tracking, 2 lost, "
                           f"3 coasting){nis[1]}"))
    return rrb.Blueprint(rrb.Horizontal(left, rrb.Grid(*plots, grid_columns=2), column_shares=[2, 3]),
                         collapse_panels=True)
