"""A tracker's run logged to Rerun as it goes, frame by frame (`envisat run`, `envisat track`): TrackRecorder."""

from __future__ import annotations

import uuid
import warnings
from datetime import timedelta

import numpy as np
import rerun as rr
from rerun.sinks import spawn

from envisat_pose.analysis.sink_check import check_sink
from envisat_pose.analysis.viewer import viewer_executable
from envisat_pose.attitude import mrp_to_dcm, mrp_to_quat
from envisat_pose.geometry import PinholeCamera, project_K
from envisat_pose.io import atomic_path
from envisat_pose.state import MRP, POS
from envisat_pose.status import HAS_ESTIMATE, LOST, legend_json
from envisat_pose.status import STATUSES as STATUS_NAMES  # the tracker's statuses by code
from envisat_pose.target import Target, default_target

from .recording_layout import (
    APPLICATION_ID,
    AXES,
    AXIS_RGB,
    DETECTED_RGB,
    EST_RGB,
    HIDDEN_RGB,
    KEYPOINT_CLASS,
    NEES_BAND_12,
    PLOT_BLOCKS,
    ROI_RGB,
    VISIBLE_RGB,
    _wxyz_to_xyzw,
    log_nees_styles,
    log_static_scene,
    log_target_wireframe,
    position_ellipsoids,
    track_blueprint,
)
from .recording_writers import flush_file, recording_name
from .stats import component_errors, display_transform


def project_state_px(x: np.ndarray, camera: PinholeCamera, target: Target | None = None) -> np.ndarray:
    """The target's keypoints (K, 2) px (OpenCV) at a state x (12,) through the camera: its keypoints_T_m carried
    into C (rho + Gamma^T v) and projected. target None: default_target() (ENVISAT's corners A-H)."""
    X_T = (target or default_target()).keypoints_T_m
    points_C = x[POS] + X_T @ mrp_to_dcm(x[MRP])  # rho + Gamma^T v
    return project_K((points_C - camera.pos_C_m) @ camera.R_K_from_C.T, camera)


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
# A live viewer's flush at the end is bounded: Rerun's default waits forever (holding the interpreter, so Ctrl-C
# is not seen) when the viewer went away or was never reached.
LIVE_FLUSH_TIMEOUT_S = 10.0
FILE_FLUSH_TICK_S = 60.0


def file_batcher() -> rr.ChunkBatcherConfig:
    """The batcher of a recording written to a file by TrackRecorder (see FILE_CHUNK_ROWS)."""
    return rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=FILE_FLUSH_TICK_S), flush_num_rows=FILE_CHUNK_ROWS)


def status_event(t_s: float, status: int, events=()) -> str:
    """The events line of a change to status (code) at t_s: "t = 12.0 s: tracking"; a loss with the tracker's own
    reason where its events (TrackEstimate.events) give one ("t = 0.0 s: lost: innovations inconsistent: ...")."""
    why = next((e for e in events if e.startswith("lost: ")), None) if status == LOST else None
    return f"t = {t_s:.1f} s: {why or STATUS_NAMES[status]}"


class TrackRecorder:
    """A tracker's run logged to Rerun as it goes, frame by frame (nothing kept in memory).

    sink: 'save:PATH' (a .rrd written under a temporary name and renamed by close(); chunks of FILE_CHUNK_ROWS
    rows, so memory stays nearly flat however long the run; the footer written), 'spawn' (a local viewer) or 'connect:URL' (a
    running viewer, e.g. rerun+http://127.0.0.1:9876/proxy). with_truth: error plots (the caller passes x_true
    per frame) instead of the estimate's own uncertainty. target: the tracked target, drawn and projected
    (None: default_target()). error_in_chart: (x_true, x_hat) -> the estimate's error (12,) in the chart of its
    covariance, for NEES and the error plots (filtering.ukf.chart_error of the filter's FilterConfig.sigma_chart;
    None: the additive chart's, analysis.stats.state_errors)."""

    def __init__(self, sink: str, camera: PinholeCamera, with_truth: bool, title: str = "",
                 target: Target | None = None, error_in_chart=None):
        self.camera, self.with_truth, self.error_in_chart = camera, with_truth, error_in_chart
        self.target = target or default_target()
        kind, _, arg = check_sink(sink)
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()), send_properties=False,
                                      batcher_config=file_batcher() if kind == "save" else None)
        self.rec.set_log_time_enabled(False)
        self.rec.set_log_tick_enabled(False)
        blueprint = track_blueprint(with_truth)
        self._atomic, self.sink = None, sink
        if kind == "save":
            self._atomic = atomic_path(arg, suffix=".rrd")
            self._tmp = self._atomic.__enter__()
            self.rec.save(self._tmp, default_blueprint=blueprint)
        elif kind == "spawn":
            # this environment's viewer, whether or not its bin folder is on PATH
            spawn(executable_path=viewer_executable(), default_blueprint=blueprint, recording=self.rec)
        else:
            self.rec.connect_grpc(arg or None, default_blueprint=blueprint)
        what = title or f"{self.target.name} tracker run"  # the name the viewer lists it by
        self.rec.send_recording_name(recording_name(arg, what) if kind == "save" else what)
        if title:
            self.rec.log("description", rr.TextDocument(title), static=True)
        # what the status series' codes mean (envisat_pose.status.legend(), JSON), beside the data
        self.rec.log("status_legend", rr.TextDocument(legend_json()), static=True)
        # the true surface only where a truth gives its pose; the estimate's skeleton is logged at the frames that
        # have an estimate (_log_estimate_3d), not static: a static shape cannot be cleared and stood at C's
        # origin (the chaser) before the first estimate, and at the last estimate while lost
        log_static_scene(self.rec, camera, target=self.target, truth=with_truth)
        self._log_series_styles()
        self.status = -1
        self._est_shown = self._image_shown = False  # world/target_est, the image drawn (since the last clear)

    def _log_series_styles(self) -> None:
        rec = self.rec
        if self.with_truth:
            for b, _, _, _ in PLOT_BLOCKS:
                for a, rgb in zip(AXES, AXIS_RGB):
                    rec.log(f"metrics/error/{b}/{a}", rr.SeriesLines(colors=[rgb], widths=[1.5], names=[a]), static=True)
                    rec.log(f"metrics/error/{b}/{a}/filter_3sigma", rr.SeriesLines(
                        colors=[rgb, rgb], widths=[0.5, 0.5], names=[f"+3s {a}", f"-3s {a}"]), static=True)
            log_nees_styles(rec)
        else:
            for a, rgb in zip(AXES, AXIS_RGB):
                rec.log(f"metrics/sigma3/position_m/{a}", rr.SeriesLines(colors=[rgb], names=[a]), static=True)
                rec.log(f"metrics/sigma3/attitude_deg/{a}", rr.SeriesLines(colors=[rgb], names=[a]), static=True)
        rec.log("metrics/tracker/p_best", rr.SeriesLines(colors=[(60, 140, 255)], widths=[1.5],
                                                         names=["best hypothesis"]), static=True)
        rec.log("metrics/tracker/status", rr.SeriesLines(colors=[(20, 20, 20)], widths=[1.5], names=["status"]),
                static=True)
        rec.log("metrics/nis", rr.SeriesLines(colors=[(200, 60, 120)], widths=[1.0], names=["NIS / dof"]), static=True)
        rec.log("world/chaser/camera/image/keypoints_detected", rr.Points2D.from_fields(radii=[3.0]), static=True)
        rec.log("world/chaser/camera/image/keypoints_estimated", rr.Points2D.from_fields(colors=[EST_RGB], radii=[2.0]),
                static=True)
        rec.log("world/chaser/camera/image/roi", rr.Boxes2D.from_fields(colors=[ROI_RGB]), static=True)
        rec.log("world/target_est/position_3sigma", rr.Ellipsoids3D.from_fields(
            colors=[EST_RGB], fill_mode=rr.components.FillMode.MajorWireframe), static=True)

    def log_frame(self, k: int, est: dict, image: np.ndarray | None, jpeg_quality: int = 80,
                  x_true: np.ndarray | None = None, corners_true_px: np.ndarray | None = None,
                  in_frame: np.ndarray | None = None) -> None:
        """Frame k: est holds x_hat (12,), P (12, 12), status (int), p_best, nis, nis_dof, corners_px (K, 2),
        visible (K,), rejected (K,), roi_px (3,) (NaN without), optionally events (status_event); image (H, W)
        uint8 or None; with a truth, x_true (12,), true keypoints corners_true_px (K, 2) where in_frame (K,)."""
        import cv2

        rec, cam = self.rec, self.camera
        rec.set_time("frame", sequence=int(k))
        t_s = float(est["t_s"]) if "t_s" in est else float(k)
        rec.set_time("sim_time", duration=t_s)
        ok = False
        if image is not None:
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
            if ok:
                rec.log("world/chaser/camera/image", rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
        if not ok and self._image_shown:  # no frame (the Earth's shadow): not the last frame's image held over
            rec.log("world/chaser/camera/image", rr.Clear(recursive=False))
        self._image_shown = ok
        status = int(est["status"])
        if status != self.status:
            rec.log("events", rr.TextLog(status_event(t_s, status, est.get("events", ())),
                                         level="WARN" if status == LOST else "INFO"))
            self.status = status
        rec.log("metrics/tracker/status", rr.Scalars(float(status)))
        rec.log("metrics/tracker/p_best", rr.Scalars(float(est["p_best"])))
        m = np.asarray(est["visible"], bool) & np.isfinite(est["corners_px"]).all(-1)
        rej = np.asarray(est["rejected"], bool)[m]
        rec.log("world/chaser/camera/image/keypoints_detected", rr.Points2D(
            np.asarray(est["corners_px"])[m] + 0.5, keypoint_ids=np.flatnonzero(m), class_ids=KEYPOINT_CLASS,
            colors=np.where(rej[:, None], np.array(HIDDEN_RGB, np.uint8), np.array(DETECTED_RGB, np.uint8))))
        x, P = np.asarray(est["x_hat"], float), np.asarray(est["P"], float)
        estimate = status in HAS_ESTIMATE  # tracking, or coasting (a prediction: shown, and scored, as one)
        if estimate:
            uv = project_state_px(x, cam, self.target)
            rec.log("world/chaser/camera/image/keypoints_estimated", rr.Points2D(
                uv + 0.5, keypoint_ids=np.arange(len(uv)), class_ids=KEYPOINT_CLASS))
        else:
            rec.log("world/chaser/camera/image/keypoints_estimated", rr.Clear(recursive=False))
        self._log_estimate_3d(x, P, estimate)
        roi = np.asarray(est["roi_px"], float)
        if np.isfinite(roi).all():
            rec.log("world/chaser/camera/image/roi", rr.Boxes2D(centers=[roi[0:2] + 0.5 * roi[2]],
                                                                half_sizes=[[0.5 * roi[2]] * 2]))
        else:
            rec.log("world/chaser/camera/image/roi", rr.Clear(recursive=False))
        # statistics' units (attitude rad): A maps either chart's MRP block to the attitude error's rotation vector
        # (the rotation chart's B(p) a to 4 a, a the error MRP), so the bands hold for both charts
        A = display_transform(x[MRP])
        sig3 = 3.0 * np.sqrt(np.maximum(np.diagonal(A @ P @ A.T), 0.0))
        if x_true is not None:
            rec.log("world/target", rr.Transform3D(translation=x_true[POS],
                                                   quaternion=_wxyz_to_xyzw(mrp_to_quat(x_true[MRP]))))
            if corners_true_px is not None:
                f = np.asarray(in_frame, bool)  # named on hover, as the detections are
                rec.log("world/chaser/camera/image/keypoints_true", rr.Points2D(
                    np.asarray(corners_true_px)[f] + 0.5, colors=[VISIBLE_RGB], radii=[1.5],
                    keypoint_ids=np.flatnonzero(f), class_ids=KEYPOINT_CLASS))
        if self.with_truth and x_true is not None and estimate:
            if self.error_in_chart is None:
                err = component_errors(x_true, x)
                nees = float(err @ np.linalg.solve(A @ P @ A.T, err))
            else:  # the error in P's chart, shown in the bands' units
                e = np.asarray(self.error_in_chart(x_true, x), float)
                err, nees = A @ e, float(e @ np.linalg.solve(P, e))
            for b, _, block, s in PLOT_BLOCKS:
                for j, a in enumerate(AXES):
                    rec.log(f"metrics/error/{b}/{a}", rr.Scalars(float(err[block][j] * s)))
                    rec.log(f"metrics/error/{b}/{a}/filter_3sigma", rr.Scalars([float(sig3[block][j] * s),
                                                                                float(-sig3[block][j] * s)]))
            rec.log("metrics/nees/value", rr.Scalars(nees))
            rec.log("metrics/nees/band", rr.Scalars(list(NEES_BAND_12)))
        elif not self.with_truth and estimate:
            for j, a in enumerate(AXES):
                rec.log(f"metrics/sigma3/position_m/{a}", rr.Scalars(float(sig3[POS][j])))
                rec.log(f"metrics/sigma3/attitude_deg/{a}", rr.Scalars(float(np.degrees(sig3[MRP][j]))))
            rec.log("metrics/range_est_m", rr.Scalars(float(np.linalg.norm(x[POS]))))
        if estimate and est["nis_dof"]:  # the tracker's own consistency, with or without a truth
            rec.log("metrics/nis", rr.Scalars(float(est["nis"]) / float(est["nis_dof"])))

    def _log_estimate_3d(self, x: np.ndarray, P: np.ndarray, estimate: bool) -> None:
        """world/target_est at the current frame: the estimated pose with the target's skeleton and the 3-sigma
        position ellipsoid where there is an estimate; cleared (the pose, skeleton and ellipsoid) from a frame
        without one (acquiring, lost) until the next estimate."""
        rec = self.rec
        if not estimate:
            if self._est_shown:
                rec.log("world/target_est", rr.Clear(recursive=True))
                self._est_shown = False
            return
        if not self._est_shown:
            log_target_wireframe(rec, "world/target_est", self.target, static=False)
            self._est_shown = True
        rec.log("world/target_est", rr.Transform3D(translation=x[POS], quaternion=_wxyz_to_xyzw(mrp_to_quat(x[MRP]))))
        half, quat = position_ellipsoids(x[None], P[None])
        rec.log("world/target_est/position_3sigma", rr.Ellipsoids3D(centers=[[0.0, 0.0, 0.0]], half_sizes=half,
                                                                     quaternions=quat))

    def close(self) -> None:
        """Flush; a saved recording is renamed to its path only now (complete). A live viewer that does not take
        what is left within LIVE_FLUSH_TIMEOUT_S (closed, gone, never reached) gets a warning, not a wait. A saved
        recording that could not be written whole (flush_file: a full disk) is removed, not renamed."""
        failed = None
        try:
            if self._atomic is not None:
                flush_file(self.rec, self._tmp)
            else:
                try:
                    self.rec.flush(timeout_sec=LIVE_FLUSH_TIMEOUT_S)
                except RuntimeError as e:
                    warnings.warn(f"the recording's viewer ({self.sink}) did not take all of it within "
                                  f"{LIVE_FLUSH_TIMEOUT_S:g} s ({e}); the job's other outputs are complete",
                                  stacklevel=2)
            self.rec.disconnect()
        except BaseException as err:
            failed = err
            raise
        finally:
            if self._atomic is not None:
                atomic, self._atomic = self._atomic, None
                atomic.__exit__(*((None, None, None) if failed is None else (type(failed), failed, None)))
