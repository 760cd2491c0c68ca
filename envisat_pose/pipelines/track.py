"""`envisat track`: the Tracker over a user's own frames (no truth needed; labels, where a dataset has them, score).

Inputs (`open_source`), every frame checked before any output is written (`check_source`):
- a folder written by `envisat generate --mode sequence` (manifest.json and shards): frame times from the labels'
  scene, the chaser's orbit from its scenario, the labels' truth for scoring;
- a folder of image files (PNG, JPEG or TIFF; 8- or 16-bit; gray, or colour converted to gray) whose names sort in
  time order, with rate_hz (frame k at k / rate_hz s) or a timestamps CSV (columns file,t_s);
- a video file (OpenCV's reader), with rate_hz or the file's own frame rate.
The camera: a TOML file (fx, fy, cx, cy px, width, height, optional OpenCV distortion) or the MJCF's chaser_cam.
Frames with distortion or non-square pixels are remapped once per frame to an ideal pinhole of the same size
(`camera_from_intrinsics`); the camera's mount on the chaser is the MJCF's.
"""

from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import InputError, check, load_toml
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.geometry import PinholeCamera, load_camera
from envisat_pose.pipelines.tracker import TRACKER_FILTER, TrackerConfig
from envisat_pose.status import STATUSES

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


@dataclass(frozen=True)
class TrackConfig:
    """One `envisat track` job. scenario: where the chaser's orbit and the target's dynamics come from (a
    generate folder's own scenario wins); orbit: the chaser's Keplerian orbit (datagen's OrbitConfig; default the
    scenario's); gravity_gradient: the target feels the gravity-gradient torque (default the scenario's);
    rate_hz: frame rate of an image folder or a video (0: a video's own rate); weights: detector weights;
    threads: torch CPU threads; jpeg_quality: the recording's images. filter, tracker: as `envisat run`."""

    scenario: str = "default"
    orbit: "OrbitConfig" = None
    gravity_gradient: bool = False
    rate_hz: float = 0.0
    weights: str = ""
    threads: int = 1
    jpeg_quality: int = 80
    filter: FilterConfig = field(default_factory=lambda: FilterConfig(**TRACKER_FILTER))
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    def validate(self, prefix: str = "") -> None:
        check(self.rate_hz >= 0, "rate_hz", self.rate_hz, "a frame rate in Hz (0: a video's own)")
        check(1 <= self.threads <= 256, "threads", self.threads, "1 to 256 threads")
        check(1 <= self.jpeg_quality <= 100, "jpeg_quality", self.jpeg_quality, "a JPEG quality in [1, 100]")


def stage_types() -> None:
    """Make the annotation "OrbitConfig" resolvable (a stage's type, imported when a job is configured)."""
    from envisat_pose.datagen.scenario import OrbitConfig

    globals()["OrbitConfig"] = OrbitConfig


# ---------------------------------------------------------------------------------------------------------
# The camera


def camera_from_intrinsics(path: str) -> tuple[PinholeCamera, tuple | None]:
    """(the ideal pinhole the tracker uses, remap) from a camera TOML file: fx, fy, cx, cy (px), width, height,
    optional distortion (OpenCV's k1, k2, p1, p2[, k3...]). remap is None when the frames are already ideal
    (fx == fy, no distortion), else (map1, map2) for cv2.remap to a pinhole with f = sqrt(fx fy) and the same
    principal point. InputError naming the file and the key otherwise."""
    import cv2

    data = load_toml(path)
    vals = {}
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        if key not in data:
            raise InputError(f"{path}: camera file has no {key!r} (expected fx, fy, cx, cy in px, width, height)")
        v = data[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise InputError(f"{path}: {key} = {v!r}: expected a number")
        vals[key] = float(v)
    for key in ("fx", "fy"):
        if vals[key] <= 0:
            raise InputError(f"{path}: {key} = {data[key]!r}: expected a positive focal length in px")
    for key in ("width", "height"):
        if vals[key] < 16 or vals[key] != int(vals[key]):
            raise InputError(f"{path}: {key} = {data[key]!r}: expected an image size of at least 16 px")
    w, h = int(vals["width"]), int(vals["height"])
    dist = data.get("distortion")
    if dist is not None:
        if not isinstance(dist, list) or len(dist) not in (4, 5, 8, 12, 14) \
                or not all(isinstance(d, (int, float)) and np.isfinite(d) for d in dist):
            raise InputError(f"{path}: distortion = {dist!r}: expected OpenCV's 4, 5, 8, 12 or 14 coefficients")
    unknown = sorted(set(data) - {"fx", "fy", "cx", "cy", "width", "height", "distortion"})
    if unknown:
        raise InputError(f"{path}: unknown camera keys {unknown} (expected fx, fy, cx, cy, width, height, distortion)")
    f = float(np.sqrt(vals["fx"] * vals["fy"]))
    mount = load_camera()
    cam = PinholeCamera(f, vals["cx"], vals["cy"], w, h, mount.R_K_from_C, mount.pos_C_m)
    if vals["fx"] == vals["fy"] and not (dist and any(dist)):
        return cam, None
    K_user = np.array([[vals["fx"], 0, vals["cx"]], [0, vals["fy"], vals["cy"]], [0, 0, 1.0]])
    maps = cv2.initUndistortRectifyMap(K_user, np.asarray(dist or [0, 0, 0, 0], float), None, cam.K, (w, h),
                                       cv2.CV_32FC1)
    return cam, maps


# ---------------------------------------------------------------------------------------------------------
# Frame sources


@dataclass
class FrameSource:
    """The frames of one input. kind: 'dataset', 'images' or 'video'; path; t_s (N,) s; names (N,) what each frame
    is called in messages (file, sample key, frame index); truth: None or {x (N, 12), corners_px (N, 8, 2),
    in_frame (N, 8)} from a dataset's labels; scenario: a dataset's own scenario (None otherwise)."""

    kind: str
    path: str
    t_s: np.ndarray
    names: list[str]
    truth: dict | None = None
    scenario: str | None = None
    files: list[str] = field(default_factory=list)

    def frames(self):
        """(index, gray uint8 image) in time order; InputError naming the frame when one cannot be read."""
        if self.kind == "images":
            for i, f in enumerate(self.files):
                yield i, read_gray(f)
        elif self.kind == "video":
            import cv2

            cap = cv2.VideoCapture(self.path)
            try:
                for i in range(len(self.t_s)):
                    ok, img = cap.read()
                    if not ok:
                        raise InputError(f"{self.path}: frame {i} cannot be read (expected {len(self.t_s)} frames)")
                    yield i, to_gray_u8(img, f"{self.path} frame {i}")
            finally:
                cap.release()
        else:
            from envisat_pose.datagen.dataset import iter_samples, sample_image

            for i, (key, label, members) in enumerate(iter_samples(self.path)):
                try:
                    yield i, sample_image(members, label)
                except Exception as err:  # a damaged PNG member
                    raise InputError(f"{self.path}: sample {key}: image cannot be read ({err})") from None


def to_gray_u8(img: np.ndarray, name: str) -> np.ndarray:
    """8- or 16-bit gray or colour (BGR/BGRA, OpenCV's order) -> (H, W) uint8 gray."""
    import cv2

    if img is None or img.size == 0:
        raise InputError(f"{name}: cannot be read as an image (expected PNG, JPEG or TIFF)")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = (img.astype(np.uint32) * 255 + 32767) // 65535
    elif img.dtype != np.uint8:
        raise InputError(f"{name}: pixels of type {img.dtype}: expected 8- or 16-bit")
    return np.ascontiguousarray(img.astype(np.uint8))


def read_gray(path: str) -> np.ndarray:
    """An image file as (H, W) uint8 gray; InputError naming the file when it is unreadable or truncated."""
    import cv2

    try:
        with open(path, "rb") as fh:
            data = np.frombuffer(fh.read(), np.uint8)
    except OSError as err:
        raise InputError(f"{path}: cannot be read ({err.strerror or err})") from None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is not None and path.lower().endswith((".jpg", ".jpeg")) and not data[-2:].tobytes() == b"\xff\xd9":
        img = None  # OpenCV decodes a truncated JPEG with a grey tail and a warning; it is not a whole frame
    return to_gray_u8(img, path)


def read_timestamps(path: str, files: list[str]) -> np.ndarray:
    """Frame times (N,) s from a CSV with columns file,t_s for the given image files (matched by file name);
    InputError naming the CSV when a file is missing from it or the times do not increase."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as err:
        raise InputError(f"--timestamps {path!r}: cannot be read ({err.strerror or err})") from None
    if not rows or not {"file", "t_s"} <= set(rows[0]):
        raise InputError(f"{path}: expected a CSV with a header line and columns file,t_s")
    times = {}
    for n, row in enumerate(rows, start=2):
        try:
            times[os.path.basename(row["file"].strip())] = float(row["t_s"])
        except (TypeError, ValueError):
            raise InputError(f"{path}: line {n}: t_s = {row.get('t_s')!r}: expected a time in s") from None
    t = []
    for f in files:
        name = os.path.basename(f)
        if name not in times:
            raise InputError(f"{path}: no time for image {name!r} (expected a row file,t_s for every image)")
        t.append(times[name])
    t = np.array(t)
    if not np.isfinite(t).all() or np.any(np.diff(t) <= 0):
        k = int(np.argmax(~(np.diff(t) > 0))) + 1 if len(t) > 1 else 0
        raise InputError(f"{path}: times must increase in the images' name order: {os.path.basename(files[k])} at "
                         f"t = {t[k]} s does not follow t = {t[k - 1] if k else float('nan')} s")
    return t


def open_source(src: str, rate_hz: float = 0.0, timestamps: str | None = None) -> FrameSource:
    """The frames of src (a generate folder, an image folder or a video file) with their times; InputError with
    one line naming the input and what was expected."""
    if os.path.isdir(src):
        if os.path.isfile(os.path.join(src, "manifest.json")):
            return dataset_source(src)
        files = sorted(os.path.join(src, f) for f in os.listdir(src) if f.lower().endswith(IMAGE_EXTENSIONS))
        if not files:
            raise InputError(f"--images {src!r}: no image files (expected PNG, JPEG or TIFF files, a generate "
                             "folder or a video)")
        if timestamps:
            t = read_timestamps(timestamps, files)
        elif rate_hz > 0:
            t = np.arange(len(files)) / rate_hz
        else:
            raise InputError(f"--images {src!r}: a folder of images needs --rate-hz R or --timestamps FILE.csv")
        return FrameSource("images", src, t, [os.path.basename(f) for f in files], files=files)
    if os.path.isfile(src):
        return video_source(src, rate_hz)
    raise InputError(f"--images {src!r}: no such file or folder")


def video_source(path: str, rate_hz: float) -> FrameSource:
    import cv2

    cap = cv2.VideoCapture(path)
    try:
        if not cap.isOpened():
            raise InputError(f"--images {path!r}: cannot be opened as a video (expected a video file OpenCV reads, "
                             "an image folder or a generate folder)")
        n = 0
        while cap.grab():
            n += 1
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
    if n == 0:
        raise InputError(f"--images {path!r}: the video has no readable frames")
    rate = rate_hz if rate_hz > 0 else fps
    if not rate > 0:
        raise InputError(f"--images {path!r}: the video has no frame rate: give --rate-hz")
    return FrameSource("video", path, np.arange(n) / rate, [f"frame {i}" for i in range(n)])


def dataset_source(path: str) -> FrameSource:
    """A sequence-mode generate folder: times, truth and scenario from the labels and the manifest."""
    from envisat_pose.datagen.dataset import iter_samples, load_manifest, verify_dataset

    manifest = load_manifest(path)
    cfg = manifest.get("config", {})
    if cfg.get("mode") != "sequence":
        raise InputError(f"--images {path!r}: a generate folder of mode {cfg.get('mode')!r}; expected one written "
                         "with --mode sequence (frames in time order)")
    problems = verify_dataset(path)
    if problems:
        raise InputError(f"--images {path!r}: {problems[0]} (`envisat dataset verify` lists all)")
    t, names, x, uv, inf = [], [], [], [], []
    for key, label, _ in iter_samples(path):
        t.append(float(label["scene"]["t_s"]))
        names.append(key)
        x.append(label["x"])
        uv.append(label["corners_px"])
        inf.append(np.asarray(label["in_frame"], bool) & np.asarray(label["visible"], bool))
    truth = {"x": np.array(x, float), "corners_px": np.array(uv, float), "in_frame": np.array(inf)}
    return FrameSource("dataset", path, np.array(t), names, truth=truth, scenario=cfg.get("scenario"))


def check_source(source: FrameSource, camera: PinholeCamera, progress: bool = False) -> None:
    """Read every frame once before any output: each must decode and have the camera's size. InputError naming
    the first frame that does not."""
    it = source.frames()
    if progress:
        from tqdm import tqdm

        it = tqdm(it, total=len(source.t_s), unit="frame", desc="checking frames", mininterval=0.5)
    want = (camera.height_px, camera.width_px)
    for i, img in it:
        if img.shape != want:
            where = source.files[i] if source.kind == "images" else f"{source.path}: {source.names[i]}"
            raise InputError(f"{where}: image is {img.shape[1]} x {img.shape[0]} px; expected {want[1]} x {want[0]} px "
                             "like the camera (all frames one size; --camera FILE.toml for another camera)")


# ---------------------------------------------------------------------------------------------------------
# The job


def output_paths(out_dir: str) -> dict[str, str]:
    names = {"est": "est.npz", "det": "det.npz", "plot": "errors.png", "config": "track.config.toml",
             "summary": "summary.json", "recording": "recording.rrd"}
    return {k: os.path.join(out_dir, v) for k, v in names.items()}


def track_frames(cfg: TrackConfig, source: FrameSource, camera: PinholeCamera, remap, out_dir: str,
                 sink: str | None = None, progress: bool = True) -> dict:
    """Run the Tracker over the source's frames; write est.npz, det.npz, track.config.toml, summary.json and
    the recording (streamed to sink, default out_dir/recording.rrd); with a truth also errors.png and the
    scores. Returns the summary."""
    import shutil

    import cv2
    import torch

    from envisat_pose.config import to_dict, to_toml
    from envisat_pose.analysis.recording import TrackRecorder
    from envisat_pose.io import atomic_write_text
    from envisat_pose.perception.detect import load_detector
    from envisat_pose.pipelines.closed_loop import (DET_KEYS, RunRows, chaser_function, est_row, run_rows,
                                                    score_run_files, store_estimate, write_run_files)
    from envisat_pose.pipelines.tracker import Tracker

    torch.set_num_threads(cfg.threads)
    paths = output_paths(out_dir)
    sink = sink or f"save:{os.path.abspath(paths['recording'])}"
    tracker = Tracker(camera, load_detector(cfg.weights), chaser_function(cfg.orbit), cfg.tracker, cfg.filter,
                      mu_m3_s2=cfg.orbit.mu_m3_s2, gravity_gradient=cfg.gravity_gradient)
    T = len(source.t_s)
    # the per-frame arrays go to files chunk by chunk (closed_loop.RunRows), est.npz/det.npz are streamed from them
    runs_dir = os.path.join(out_dir, "runs")
    run_dir = os.path.abspath(os.path.join(runs_dir, "run-0000"))
    rows = RunRows(run_dir, T)
    truth = source.truth
    recorder = TrackRecorder(sink, camera, with_truth=truth is not None, title=f"envisat track {source.path}")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, unit="frame", desc="tracking", mininterval=0.5)
    wall0 = time.perf_counter()
    try:
        for k, image in source.frames():
            if remap is not None:
                image = cv2.remap(image, remap[0], remap[1], cv2.INTER_LINEAR)
            est = tracker.step(float(source.t_s[k]), image)
            i, out = rows.row(k), rows.buf
            store_estimate(out, i, est)
            t0 = time.perf_counter()
            recorder.log_frame(k, est_row(out, i, float(source.t_s[k])), image, cfg.jpeg_quality,
                               x_true=None if truth is None else truth["x"][k],
                               corners_true_px=None if truth is None else truth["corners_px"][k],
                               in_frame=None if truth is None else truth["in_frame"][k])
            out["timing_s"][i, 3:] = (est.timing_s.get("detection", 0.0), est.timing_s.get("filtering", 0.0),
                                      time.perf_counter() - t0)
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(est.status, refresh=False)
    finally:
        if bar is not None:
            bar.close()
        recorder.close()
    sums = rows.close()
    wall_s = time.perf_counter() - wall0
    x_true = truth["x"] if truth is not None else np.full((T, 12), np.nan)
    config_json = json.dumps({"track": to_dict(cfg), "source": {"kind": source.kind, "path": source.path}},
                             sort_keys=True)
    det_cfg = json.dumps({"weights": cfg.weights, "source": source.path}, sort_keys=True)
    det_names = tuple(k for k in DET_KEYS if k != "skipped")
    scores = score_run_files(source.t_s, x_true, [run_dir], paths, config_json, det_cfg, score=truth is not None,
                             det_names=det_names)
    col = run_rows(run_dir, ["status", "nis", "nis_dof"], 0, T)  # three scalars a frame
    status = col["status"]
    write_run_files(paths, source.t_s, x_true, [run_dir], np.array([status[-1] != STATUSES.index("tracking")]),
                    config_json, source.names, det_cfg, det_names=det_names)
    atomic_write_text(paths["config"], "# envisat track: the full validated config of this job\n" + to_toml(to_dict(cfg)))
    tracking = np.flatnonzero(status == STATUSES.index("tracking"))
    timing = np.asarray(sums["timing_s"]) / T
    summary = {
        "source": {"kind": source.kind, "path": source.path, "frames": T},
        "weights": cfg.weights,
        "frames_by_status": {s: int((status == i).sum()) for i, s in enumerate(STATUSES)},
        "first_tracking_s": float(source.t_s[tracking[0]]) if tracking.size else None,
        "final_status": STATUSES[int(status[-1])],
        "mean_nis_per_dof": float(np.sum(col["nis"]) / max(int(np.sum(col["nis_dof"])), 1)),
        "timing_ms_per_frame": {"detection": float(1000 * timing[3]), "filtering": float(1000 * timing[4]),
                                "recording": float(1000 * timing[5])},
        "wall_s": wall_s,
    }
    if truth is not None:
        from envisat_pose.analysis.plots import plot_estimate
        from envisat_pose.pipelines.closed_loop import plot_inputs

        summary["scores"] = scores
        plot_estimate(*plot_inputs(source.t_s, x_true, [run_dir]), paths["plot"],
                      title=f"envisat track {os.path.basename(os.path.abspath(source.path))}")
    shutil.rmtree(runs_dir, ignore_errors=True)
    atomic_write_text(paths["summary"], json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return summary
