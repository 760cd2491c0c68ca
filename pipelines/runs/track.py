"""`envisat track`: the Tracker over a user's own frames (no truth needed; labels, where a dataset has them, score).

Inputs (pipelines/runs/frames.py: `open_source`), every frame read once before any output is written (`scan_source`):
- a folder written by `envisat generate --mode sequence` (manifest.json and shards) of the job's target: frame
  times from the labels' scene, the chaser's orbit from its scenario, the labels' truth for scoring (a dataset of
  another target than the job's is refused: frames.require_source_target);
- a folder of image files (PNG, JPEG, TIFF, BMP, PGM/PPM or WebP; 8-bit, or 10- to 16-bit data in 16-bit files; gray, or colour
  converted to gray; hidden files ignored) in natural name order, with rate_hz (frame k at k / rate_hz s) or a
  timestamps CSV (columns file,t_s);
- a video file (OpenCV's reader), with rate_hz or the file's own frame rate.
The camera (pipelines/tracking/camera_file.py): a TOML file (fx, fy, cx, cy px, width, height, optional OpenCV
distortion) or the MJCF's chaser_cam (a user's frames of another size than its 1024 px need a camera file).
Frames with distortion or non-square pixels are remapped once per frame to an ideal pinhole of the same size; the
camera's mount on the chaser is the MJCF's.
The target (`target`, its MJCF file): ENVISAT by default, with its corner detector (the shipped weights unless
others are given); another target's frames are tracked by its own keypoint detector (`envisat train --target`,
then `envisat calibrate --target`), whose weights must be given (pipelines/tracking/build.tracker_detector).

Outputs are written into a hidden folder inside out_dir and moved into place when complete (io.staged_folder):
an error or an interrupt leaves out_dir as it was; a finished run removes an earlier run's outputs it did not
write (errors.png of a scored run, say). An out_dir on, inside or around the frames' folder, or holding files of
the outputs' names but no track.config.toml written by track (a user's own summary.json), is refused first.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from envisat_pose.analysis.sink_check import check_recording_path, check_sink
from envisat_pose.config import Config, as_path_or_object, check, config_arg, path_arg, to_toml
from envisat_pose.datagen.scenario import OrbitConfig
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.geometry import PinholeCamera
from envisat_pose.io import atomic_write_text, sha256_file, staged_folder
from envisat_pose.out_dirs import check_out_dir, made_out_dir, refuse_foreign_outputs, refuse_overlap
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.common.job_defaults import (
    fill_from_scenario,
    job_record,
    job_weights,
    layered_job,
    scenario_table,
    weights_name,
)
from envisat_pose.pipelines.common.threads import compute_threads
from envisat_pose.pipelines.runs.frame_loop import BEFORE_TRACKER, FrameInput, run_frames
from envisat_pose.pipelines.runs.frame_names import spacing_caution
from envisat_pose.pipelines.runs.frames import FrameSource, open_source, require_source_target, scan_source
from envisat_pose.pipelines.runs.outputs import status_summary
from envisat_pose.pipelines.runs.rows import DET_KEYS, STAGES, RunRows
from envisat_pose.pipelines.runs.run_files import lost_runs, plot_inputs, run_rows, score_run_files, write_run_files
from envisat_pose.pipelines.runs.scoring import recording_errors
from envisat_pose.pipelines.tracking.build import tracker_detector
from envisat_pose.pipelines.tracking.camera_file import camera_from_intrinsics, camera_record, default_camera
from envisat_pose.pipelines.tracking.integrity import check_min_target_px
from envisat_pose.pipelines.tracking.onboard import chaser_function
from envisat_pose.pipelines.tracking.tracker import TRACKER_FILTER, Tracker, TrackerConfig
from envisat_pose.pipelines.tracking.tracker_bounds import MAX_PREDICTION_S, MIN_FRAME_DT_S
from envisat_pose.provenance import source_line
from envisat_pose.realtime import real_time_factor
from envisat_pose.status import legend
from envisat_pose.target import DEFAULT_TARGET, load_target, other_target
from envisat_pose.written_target import with_target_sha256

if TYPE_CHECKING:  # the stage's type for annotations (track_stage_types resolves it at run time)
    from envisat_pose.datagen.scenario import OrbitConfig


@dataclass(frozen=True)
class TrackConfig(Config):
    """One `envisat track` job, complete and validated when built: `TrackConfig(scenario=NAME, rate_hz=2.0)` is
    the job of `envisat track --scenario NAME --rate-hz 2` (pipelines.jobs.resolve_job adds a config file and
    flags). scenario: where the chaser's orbit, the target's dynamics and the filter's tuning come from (a
    generate folder's own scenario wins in the verb); orbit: the chaser's Keplerian orbit (datagen's
    OrbitConfig); gravity_gradient: the target feels the gravity-gradient torque; filter: the UKF (the scenario's
    [filter] table over TRACKER_FILTER). Those three left None take the scenario's
    (job_defaults.fill_from_scenario); orbit or filter given as a dict sets its keys over the scenario's, as a
    config file's table does (a config given is taken whole).
    rate_hz: frame rate of an image folder or a video (0: a video's own
    rate); target: the tracked spacecraft's MJCF file (envisat_pose/target.py; ENVISAT's by default); weights:
    detector weights ("": ENVISAT's shipped ones; the file must exist and be the target's detector: another
    target's keypoint detector is required for it); bf16: ENVISAT's corner detector in bfloat16 (as `envisat
    run`); threads: torch CPU threads; jpeg_quality: the recording's images. tracker: as `envisat run`."""

    scenario: str = "default"
    orbit: "OrbitConfig | None" = None
    gravity_gradient: bool | None = None
    rate_hz: float = 0.0
    target: str = DEFAULT_TARGET
    weights: str = ""
    bf16: bool = False
    threads: int = 1
    jpeg_quality: int = 80
    filter: FilterConfig | None = None
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    table_bases: ClassVar[dict] = {"orbit": scenario_table("track", "orbit"),
                                   "filter": scenario_table("track", "filter")}

    def __post_init__(self) -> None:
        track_stage_types()
        fill_from_scenario(self, "track", TRACK_FALLBACKS)
        super().__post_init__()  # the target file first: its weights are asked of it
        object.__setattr__(self, "weights", job_weights(self.weights, self.target))  # never ENVISAT's for another

    @classmethod
    def from_scenario(cls, name: str = "default", config_path: str | None = None, overrides: dict | None = None,
                      **fields) -> "TrackConfig":
        """Deprecated (goes in the next release): TrackConfig(scenario=NAME, ...), or pipelines.jobs.resolve_job
        ("track", NAME, config_path, overrides, ...) for a config file and dotted flags; this is the latter."""
        warnings.warn("TrackConfig.from_scenario is deprecated and goes in the next release: use "
                      "TrackConfig(scenario=NAME, ...) (or pipelines.jobs.resolve_job for a config file)",
                      DeprecationWarning, stacklevel=2)
        track_stage_types()
        return layered_job(cls, "track", name, config_path, overrides, fields)

    def validate(self, prefix: str = "") -> None:
        lo, hi = 1.0 / MAX_PREDICTION_S, 1.0 / MIN_FRAME_DT_S  # frames 1e6 s apart at most, 1e-4 s at least
        check(self.rate_hz == 0 or lo <= self.rate_hz <= hi, "rate_hz", self.rate_hz, f"a frame rate in [{lo:g}, "
              f"{hi:g}] Hz (frames at most as far apart as a track is predicted over, at least the filter's least "
              "step), or 0: a video's own")
        check(1 <= self.threads <= 256, "threads", self.threads, "1 to 256 threads")
        check(1 <= self.jpeg_quality <= 100, "jpeg_quality", self.jpeg_quality, "a JPEG quality in [1, 100]")
        load_target(self.target, f"{prefix}.target" if prefix else "target")  # one line for a bad file (cached)


# what a scenario sets of a track job when it has no such table (every named scenario has an orbit)
TRACK_FALLBACKS = {"orbit": lambda: OrbitConfig(), "gravity_gradient": lambda: False,
                   "filter": lambda: FilterConfig(**TRACKER_FILTER)}


def track_stage_types() -> None:
    """Make the annotation "OrbitConfig" resolvable (a stage's type, imported when a job is configured)."""

    globals()["OrbitConfig"] = OrbitConfig


# ---------------------------------------------------------------------------------------------------------
# The job

OUTPUTS = {"est": "est.npz", "det": "det.npz", "plot": "errors.png", "config": "track.config.toml",
           "summary": "summary.json", "recording": "recording.rrd"}


def track_output_paths(out_dir: str) -> dict[str, str]:
    return {k: os.path.join(out_dir, v) for k, v in OUTPUTS.items()}


def prepare_frames(cfg: TrackConfig, source: FrameSource | str, camera: PinholeCamera | str | None = None,
                   remap=None, progress: bool = False) -> tuple:
    """A user's frames made ready for a job over them (track_frames, adapt): the source opened (a path at
    cfg.rate_hz; a generate folder must be of cfg.target: frames.require_source_target), the camera read (a TOML
    file: its remap too) or the MJCF's (camera_file.default_camera), every frame scanned once
    (frames.scan_source: one size, decodable, at least the cold start's frames; frames too far apart for it warned
    of: frame_names.spacing_caution); a min_target_px the camera's focal length never lets a box span refused
    (integrity.check_min_target_px). Returns (cfg, source, camera, remap, pixels); cfg as given (complete when
    built: its weights named)."""
    if isinstance(source, str):
        source = open_source(source, cfg.rate_hz)
    require_source_target(source, cfg.target)
    if source.scenario and source.scenario != cfg.scenario:  # the verb takes the folder's unless --scenario is typed
        warnings.warn(f"{source.path}: frames of scenario {source.scenario!r}, tracked with the orbit, dynamics and "
                      f"filter of scenario {cfg.scenario!r} (TrackConfig(scenario={source.scenario!r}) takes the "
                      "frames' own, as `envisat track` does without --scenario)")
    if isinstance(camera, str):
        camera, remap = camera_from_intrinsics(camera)
    if camera is not None:  # before the frames are read
        check_min_target_px(cfg.tracker.integrity.min_target_px, camera.f_px, "tracker.integrity.min_target_px")
    pixels = scan_source(source, None if camera is None else (camera.width_px, camera.height_px),
                         min_frames=cfg.tracker.acquire.frames, progress=progress)
    if camera is None:
        camera = default_camera(source.path, source.size_px, generated=source.kind == "dataset")
        check_min_target_px(cfg.tracker.integrity.min_target_px, camera.f_px, "tracker.integrity.min_target_px")
    caution = spacing_caution(source.path, source.t_s, cfg.tracker.acquire.frames, cfg.tracker.acquire.max_gap_s)
    if caution:  # once the frames and the camera pass: a refusal stays one line
        warnings.warn(caution, stacklevel=2)
    return cfg, source, camera, remap, pixels


@locks_output("out_dir", "track")
def track_frames(cfg: TrackConfig, source: FrameSource | str, camera: PinholeCamera | str | None = None, remap=None,
                 out_dir: str = "track-out", sink: str | None = None, progress: bool = False) -> dict:
    """Run the Tracker over the source's frames (a FrameSource, or a path open_source opens at cfg.rate_hz);
    write est.npz, det.npz, track.config.toml, summary.json and the recording (out_dir/recording.rrd, or
    streamed to sink: 'spawn' or 'connect:URL'); with a truth also errors.png and the scores. camera: a
    PinholeCamera (remap: its cv2.remap maps, or None), a camera TOML file (camera_file.camera_from_intrinsics), or
    None for the MJCF's chaser_cam (camera_file.default_camera: a generated folder's at its size, a user's frames
    at the camera's own size only, others refused); cfg: TrackConfig(scenario=NAME, ...) (or
    pipelines.jobs.resolve_job("track", ...), the job `envisat track` runs); the Tracker's target is cfg.target's
    (a generate folder of another target refused), its detector cfg.weights' (build.tracker_detector: another
    target's calibrated keypoint detector). Every frame is read once and the detector loaded before any output
    (frames.scan_source: one size, decodable, at least the cold start's frames); every output is staged and moved
    into out_dir when complete (io.staged_folder). Returns the summary (its source's `pixels`: what the scan found
    of the pixels; `target`: the target's record)."""

    cfg, out_dir = config_arg(cfg, TrackConfig), path_arg(out_dir, "out_dir")
    source, camera = as_path_or_object(source), as_path_or_object(camera)
    check_out_dir(out_dir, field="out_dir")
    refuse_overlap(out_dir, source if isinstance(source, str) else getattr(source, "path", None))
    refuse_foreign_outputs(out_dir, OUTPUTS.values(), OUTPUTS["config"], "track")  # a user's summary.json stays
    if sink is not None:
        check_sink(sink)  # a viewer that is not there refused before any frame is read
    else:
        check_recording_path(out_dir, "out_dir")  # the recording goes there
    camera_file, default = (camera if isinstance(camera, str) else None), camera is None
    cfg, source, camera, remap, pixels = prepare_frames(cfg, source, camera, remap, progress)
    used = camera_record(camera, camera_file, remap is not None, default)  # a PinholeCamera given: not the default
    # the detector before any output: another target's weights without their calibration are refused here
    detector = tracker_detector(cfg.weights, target=cfg.target, bf16=cfg.bf16)
    with made_out_dir(out_dir), staged_folder(out_dir, OUTPUTS.values()) as stage, compute_threads(cfg.threads):
        return _track(cfg, source, camera, remap, stage, sink, progress, pixels, detector, used)


def _track(cfg: TrackConfig, source: FrameSource, camera: PinholeCamera, remap, out_dir: str, sink: str | None,
           progress: bool, pixels: str, detector, used: dict) -> dict:
    import shutil
    from dataclasses import asdict

    from envisat_pose.analysis.recording import TrackRecorder

    paths = track_output_paths(out_dir)
    sink = sink or f"save:{os.path.abspath(paths['recording'])}"
    target = load_target(cfg.target)
    tracker = Tracker(camera, detector, chaser_function(cfg.orbit), cfg.tracker, asdict(cfg.filter),
                      mu_m3_s2=cfg.orbit.mu_m3_s2, gravity_gradient=cfg.gravity_gradient,
                      target=None if other_target(cfg.target) is None else target)
    T = len(source.t_s)
    # the per-frame arrays go to files chunk by chunk (rows.RunRows), est.npz/det.npz are streamed from them
    runs_dir = os.path.join(out_dir, "runs")
    run_dir = os.path.abspath(os.path.join(runs_dir, "run-0000"))
    rows = RunRows(run_dir, T, K=tracker.K)
    truth = source.truth
    recorder = TrackRecorder(sink, camera, with_truth=truth is not None, title=f"envisat track {target.name}: {source.path}",
                             target=target, error_in_chart=recording_errors(tracker.fcfg.sigma_chart))

    wall0 = time.perf_counter()
    sums = run_frames(tracker, frame_inputs(source, remap), rows, recorder, cfg.jpeg_quality,
                      "tracking" if progress else None, overlap=True)  # the next frame read beside the tracker
    wall_s = time.perf_counter() - wall0
    x_true = truth["x"] if truth is not None else np.full((T, 12), np.nan)
    record = target.record(cfg.target)  # the file as given, its name, sha256 and keypoints
    config_json = json.dumps({"track": job_record(cfg), "target": record,
                              "source": {"kind": source.kind, "path": source.path, "bit_depth": source.bit_depth,
                                         "skipped_damaged_shards": source.skipped}, "camera": used}, sort_keys=True)
    det_cfg = json.dumps({"weights": weights_name(cfg.weights), "source": source.path, "target": record},
                         sort_keys=True)
    det_names = tuple(k for k in DET_KEYS if k != "skipped")
    scores = score_run_files(source.t_s, x_true, [run_dir], paths, config_json, det_cfg, score=truth is not None,
                             det_names=det_names, equivalent=tracker.namings.equivalent,
                             dark=None if truth is None else truth.get("eclipse"), chart=tracker.fcfg.sigma_chart)
    col = run_rows(run_dir, ["status", "nis", "nis_dof"], 0, T)  # three scalars a frame
    write_run_files(paths, source.t_s, x_true, [run_dir], lost_runs([run_dir], T), config_json, source.names,
                    det_cfg, det_names=det_names)
    atomic_write_text(paths["config"], "# envisat track: the full validated config of this job\n" + source_line()
                      + to_toml(with_target_sha256(job_record(cfg), "track", record["sha256"])))
    summary = track_summary(source, cfg.weights, pixels, col, np.asarray(sums["timing_s"]) / T, wall_s)
    summary["target"], summary["camera"] = record, used
    summary["last_cold_start_refusal"] = tracker.last_refusal  # why a frame's cold start started nothing (None)
    if truth is not None:
        from envisat_pose.analysis.plots import plot_estimate

        summary["scores"] = scores
        plot_estimate(*plot_inputs(source.t_s, x_true, [run_dir]), paths["plot"],
                      title=f"envisat track {target.name}: {os.path.basename(os.path.abspath(source.path))}")
    shutil.rmtree(runs_dir, ignore_errors=True)
    atomic_write_text(paths["summary"], json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return summary


def track_summary(source: FrameSource, weights: str, pixels: str, col: dict, timing_s: np.ndarray,
                  wall_s: float) -> dict:
    """summary.json of a track (without its scores): the source, the frames by status, the first tracking time,
    the mean NIS per degree of freedom, the stages' time per frame (ms; the frames are read, not made: no
    simulation, rendering or camera) and the real-time factor. col: the run's status, nis and nis_dof per frame
    (T,); timing_s: (len(STAGES),) s per frame."""

    T = len(source.t_s)
    return {
        "source": {"kind": source.kind, "path": source.path, "frames": T, "bit_depth": source.bit_depth,
                   "size_px": list(source.size_px), "pixels": pixels, "skipped_damaged_shards": source.skipped},
        "weights": weights_name(weights), "weights_sha256": sha256_file(weights),
        **status_summary(source.t_s, col),
        # the stages timed here: the frames are read, not made (no simulation, rendering or camera)
        "timing_ms_per_frame": {s: float(1000 * timing_s[i]) for i, s in enumerate(STAGES) if s not in BEFORE_TRACKER},
        "real_time_factor": real_time_factor(source.t_s, wall_s),
        "wall_s": wall_s,
        "status_legend": legend(),
    }


def frame_inputs(source: FrameSource, remap):
    """The source's frames as the frame loop's FrameInputs (remapped to the ideal pinhole where the camera has
    one: remap, cv2.remap's maps), with their truth where the source has one."""
    import cv2

    truth = source.truth
    for k, image in source.frames():
        if remap is not None:
            image = cv2.remap(image, remap[0], remap[1], cv2.INTER_LINEAR)
        if truth is None:
            yield FrameInput(k, float(source.t_s[k]), image)
        else:
            yield FrameInput(k, float(source.t_s[k]), image, x_true=truth["x"][k],
                             corners_true_px=truth["corners_px"][k], in_frame=truth["in_frame"][k])
