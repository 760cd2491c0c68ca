"""Recordings written whole from arrays (`--rrd` of simulate, estimate, montecarlo, dataset inspect): each file is
written under a temporary name, with its footer, and renamed when complete (envisat_pose.io.atomic_path)."""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass
from typing import Iterable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from envisat_pose.contracts import Estimates, TruthTrajectory
from envisat_pose.io import atomic_path, no_room_error
from envisat_pose.target import Target, default_target

from .recording_layout import (
    APPLICATION_ID,
    IMAGE_PLANE_M,
    KEYPOINT_CLASS,
    _point_colors,
    _times,
    _wxyz_to_xyzw,
    corner_annotation,
    estimate_bands,
    estimate_blueprint,
    keypoints_noun,
    load_camera,
    log_error_series,
    log_estimate_series,
    log_nees_series,
    log_static_scene,
    log_target_mesh,
    log_truth_series,
    mask_annotation,
    pose_columns,
    rotmat_to_quat,
    runs_nees,
    samples_blueprint,
    truth_blueprint,
)

# ---------------------------------------------------------------- files

FLUSH_POLL_S = 2.0  # flush_file waits this long at a time, checking between waits that the file still grows
FLUSH_STALL_POLLS = 30  # waits in a row without a byte written, room left, before flush_file gives up (a minute)


def flush_file(rec: rr.RecordingStream, tmp: str) -> None:
    """Flush a recording saved to the file tmp. Rerun's file writer runs on its own thread: a write the OS refuses
    there (a full disk) is only logged, and Rerun's flush then either raises a RuntimeError without the reason or
    waits forever. Here it waits FLUSH_POLL_S at a time while the file grows; once the writer is gone, or wrote
    nothing over a wait and the folder takes no more bytes, it raises the OSError (ENOSPC, EDQUOT, EFBIG) naming
    tmp that the verbs say in one line (io.no_room_error); a writer gone with room left, or stalled over
    FLUSH_STALL_POLLS waits, is Rerun's RuntimeError."""
    size, stalled = -1, 0
    while True:
        try:
            rec.flush(timeout_sec=FLUSH_POLL_S)
            return
        except RuntimeError as err:
            if "timed out" not in str(err):  # the writer thread is gone
                raise no_room_error(tmp, err) from err
            now = os.path.getsize(tmp) if os.path.exists(tmp) else -1
            if now != size:  # still writing: wait on
                size, stalled = now, 0
                continue
            refused = no_room_error(tmp, err)
            stalled += 1
            if refused is not err or stalled >= FLUSH_STALL_POLLS:
                raise refused from err


def recording_name(path: str, what: str) -> str:
    """The name the viewer lists a recording by: its file's name and what it holds ("est.rrd: cubesat_3u
    estimates, 3 runs"). Without one (no properties are sent) every recording of a folder that `envisat view`
    opens was listed alike, as envisat_pose."""
    return f"{os.path.basename(path)}: {what}" if what else os.path.basename(path)


class _Recording:
    """A recording saved to `path` atomically, named `what` in the viewer (recording_name):
    `with _Recording(path, blueprint, what) as rec: ...`."""

    def __init__(self, path: str, blueprint: rrb.Blueprint, what: str = ""):
        self.path, self.blueprint, self.what = path, blueprint, what

    def __enter__(self) -> rr.RecordingStream:
        self._atomic = atomic_path(self.path, suffix=".rrd")
        self.tmp = self._atomic.__enter__()
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()), send_properties=False)
        self.rec.set_log_time_enabled(False)  # only the two timelines of the design, sim_time and frame
        self.rec.set_log_tick_enabled(False)
        self.rec.save(self.tmp, default_blueprint=self.blueprint)
        self.rec.send_recording_name(recording_name(self.path, self.what))
        return self.rec

    def __exit__(self, *exc) -> bool:
        try:
            flush_file(self.rec, self.tmp)
            self.rec.disconnect()  # closes the file before it is renamed
        except BaseException as err:  # a Ctrl-C or a full disk in the flush: the file is not put in place
            exc = (type(err), err, err.__traceback__)
            raise
        finally:
            self._atomic.__exit__(*exc)  # renamed only when the body and the flush both completed
        return False


def write_truth_recording(path: str, truth: TruthTrajectory, target: Target | None = None) -> str:
    """`envisat simulate --rrd`: the truth (target pose, keypoints, visibility over time) as a recording, the
    target drawn as `target` (the truth's own: its config's target.file; None: default_target())."""
    with _Recording(path, truth_blueprint(target), f"{(target or default_target()).name} truth") as rec:
        log_static_scene(rec, target=target)
        log_truth_series(rec, truth.t_s, truth.x, truth.corners_C_m, truth.visible, truth.corners_px, truth.in_frame,
                         noun=keypoints_noun(target))
    return path


def truth_rows(truth: TruthTrajectory, t_s: np.ndarray) -> np.ndarray:
    """Indices of the truth's samples at the times t_s (the filter's grid is a subsample of the truth's)."""
    k = np.clip(np.searchsorted(truth.t_s, t_s - 1e-9), 0, len(truth.t_s) - 1)
    if not np.allclose(truth.t_s[k], t_s, atol=1e-6):
        raise ValueError("the estimates' times are not samples of the truth")
    return k


def write_estimates_recording(path: str, est: Estimates, truth: TruthTrajectory | None = None,
                              max_error_runs: int | None = None, target: Target | None = None,
                              nees_rt: np.ndarray | None = None) -> str:
    """`envisat estimate --rrd`: truth and run 0's estimate with its 3-sigma ellipsoid, the error series of
    every run (the first max_error_runs if given) with the filter's and the runs' +-3 sigma bands, and the NEES
    averaged over all runs with its 95 % band. With the truth trajectory, its keypoints and visibility at the
    filter's steps too. target: the truth's (None: default). nees_rt (R, T): the runs' NEES in the filter's chart
    (filtering.estimator.nees; None: the additive chart's, runs_nees)."""
    err, filt, samp = estimate_bands(est.x_true, est.x_hat, est.P)
    n = err.shape[0] if max_error_runs is None else min(err.shape[0], max_error_runs)
    nees_rt = runs_nees(est.x_true, est.x_hat, est.P) if nees_rt is None else np.asarray(nees_rt, dtype=float)
    what = f"{(target or default_target()).name} estimates, {len(est.x_hat)} run{'s' * (len(est.x_hat) != 1)}"
    with _Recording(path, estimate_blueprint(target), what) as rec:
        log_static_scene(rec, estimate=True, target=target)
        _log_truth_on_grid(rec, est.t_s, est.x_true[0], truth, target)
        log_estimate_series(rec, est.t_s, est.x_hat[0], est.P[0])
        log_error_series(rec, est.t_s, err[:n], filt, samp)
        log_nees_series(rec, est.t_s, nees_rt.mean(axis=0), runs=nees_rt.shape[0])
    return path


def _log_truth_on_grid(rec, t_s, x_true, truth: TruthTrajectory | None, target: Target | None = None) -> None:
    if truth is None:
        rec.send_columns("world/target", _times(t_s), pose_columns(x_true))
        return
    k = truth_rows(truth, t_s)
    log_truth_series(rec, t_s, x_true, truth.corners_C_m[k], truth.visible[k], truth.corners_px[k], truth.in_frame[k],
                     noun=keypoints_noun(target))


def write_campaign_recording(path: str, t_s: np.ndarray, x_true: np.ndarray, x_hat0: np.ndarray, P0: np.ndarray,
                             sample_err: np.ndarray, filter_3sigma: np.ndarray, sample_3sigma: np.ndarray | None,
                             truth: TruthTrajectory | None = None, target: Target | None = None,
                             nees_mean: np.ndarray | None = None, nees_bounds: np.ndarray | None = None,
                             runs: int = 1) -> str:
    """`envisat montecarlo --rrd`: the truth x_true (T, 12) and run 0's estimate x_hat0 (T, 12) with its
    3-sigma ellipsoid from P0 (T, 12, 12); the kept sample runs' errors sample_err (S, T, 12) with the campaign's
    filter_3sigma and sample_3sigma (T, 12) over all runs (analysis.stats.CampaignStats); the campaign's NEES,
    nees_mean (T,) over its `runs` runs with its band nees_bounds (2,) (CampaignStats; None: run 0's own NEES in
    the additive chart and the band of one run). target: the campaign's (None: default_target())."""
    what = f"{(target or default_target()).name} Monte Carlo" + (f", {runs} runs" if nees_mean is not None else "")
    if nees_mean is None:
        nees_mean, nees_bounds, runs = runs_nees(x_true, x_hat0, P0), None, 1
    with _Recording(path, estimate_blueprint(target), what) as rec:
        log_static_scene(rec, estimate=True, target=target)
        _log_truth_on_grid(rec, t_s, x_true, truth, target)
        log_estimate_series(rec, t_s, x_hat0, P0)
        log_error_series(rec, t_s, sample_err, filter_3sigma, sample_3sigma)
        log_nees_series(rec, t_s, nees_mean, runs=runs, bounds=nees_bounds)
    return path


@dataclass(frozen=True)
class Sample:
    """A dataset sample as the recording shows it: image_png (PNG bytes of the 8-bit image as training sees it),
    label (the label dict: corners_px, or another target's keypoint_names and keypoints_px; visible, in_frame,
    K, R_cam_from_target, t_cam_from_target_m, depth_scale_m, x, scene), mask (H, W) uint8 or None, depth_png
    (16-bit PNG bytes) or None."""

    key: str
    image_png: bytes
    label: dict
    mask: np.ndarray | None = None
    depth_png: bytes | None = None


def label_keypoints(label: dict, target: Target) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A label's keypoints of `target`, K of them: (px (K, 2) OpenCV, visible (K,) bool, in_frame (K,) bool), read
    from keypoints_px where the target's labels name their keypoints (Target.labels_name_keypoints), else from
    the shard contract's corners_px. ValueError when the label's keypoints are not the target's (their names,
    or their count)."""
    names = label.get("keypoint_names", list(target.keypoint_names))
    px = np.asarray(label["keypoints_px" if target.labels_name_keypoints else "corners_px"], dtype=float)
    if list(names) != list(target.keypoint_names) or px.shape != (target.num_keypoints, 2):
        raise ValueError(f"the label's keypoints ({list(names)}, {px.shape[0]} points) are not those of the target "
                         f"{target.name!r} ({list(target.keypoint_names)})")
    return px, np.asarray(label["visible"], dtype=bool), np.asarray(label["in_frame"], dtype=bool)


def write_samples_recording(path: str, samples: Iterable[Sample], target: Target | None = None,
                            mask_values: dict[str, int] | None = None) -> str:
    """`envisat dataset inspect --rrd`: per sample (timeline `frame` = its index; `sim_time` where the label's
    scene has t_s), the image (its PNG as stored), the labelled keypoints (label_keypoints), the mask, the depth,
    the camera's intrinsics and the target's pose in the camera. target: the dataset's (None: default_target());
    mask_values: {geom name: mask value} its masks were written with (None: the factory's classes, MASK_CLASSES)."""
    target = target or default_target()
    base = load_camera()
    with _Recording(path, samples_blueprint(target), f"{target.name} dataset samples") as rec:
        rec.log("world", corner_annotation(target), static=True)
        rec.log("world/chaser/camera/image/mask", mask_annotation(mask_values), static=True)
        log_target_mesh(rec, "world/target", target)
        rec.log("world/chaser/camera", rr.Transform3D(translation=base.pos_C_m, mat3x3=base.R_K_from_C.T),
                static=True)
        for i, s in enumerate(samples):
            rec.set_time("frame", sequence=i)
            _log_sample(rec, s, target, base)
    return path


def _log_sample(rec: rr.RecordingStream, s: Sample, target: Target, base) -> None:
    """One sample at the current time: the pinhole (its label's K), image, keypoints, mask, depth, and the
    target's pose in C (base: the chaser camera's mount)."""
    lab = s.label
    t = lab.get("scene", {}).get("t_s")
    if t is not None:
        rec.set_time("sim_time", duration=float(t))
    K = np.asarray(lab["K"], dtype=float)
    h, w = (s.mask.shape if s.mask is not None else (int(round(2 * K[1, 2] + 1)), int(round(2 * K[0, 2] + 1))))
    rec.log("world/chaser/camera", rr.Pinhole(
        focal_length=[K[0, 0], K[1, 1]], principal_point=[K[0, 2] + 0.5, K[1, 2] + 0.5],  # OpenCV -> Rerun
        resolution=[w, h], image_plane_distance=IMAGE_PLANE_M))
    rec.log("world/chaser/camera/image", rr.EncodedImage(contents=s.image_png, media_type="image/png"))
    px, vis, m = label_keypoints(lab, target)
    rec.log("world/chaser/camera/image/keypoints_true", rr.Points2D(
        positions=px[m] + 0.5, keypoint_ids=np.flatnonzero(m), class_ids=np.full(int(m.sum()), KEYPOINT_CLASS),
        colors=_point_colors(vis)[m], labels=[target.keypoint_names[k] for k in np.flatnonzero(m)]))
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
