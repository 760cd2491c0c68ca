"""The closed loop of `envisat run`: MuJoCo truth -> rendered camera frames -> the space camera -> the Tracker.

Per run and frame k (t_k = k / rate_hz):
1. the truth at t_k is the MuJoCo truth simulation of `envisat simulate` (datagen.truth.simulate_truth, run once before
   the loops: it refuses a trajectory that breaks the keep-out margin before any image is made);
2. in the Earth's shadow (the chaser's own orbit and the sun direction) there is no frame: the tracker predicts;
3. MuJoCo renders the chaser camera (datagen's SceneRenderer, the factory's sequence-mode view and appearance), and
   datagen's space camera corrupts it with the run's own noise (pipelines/runs/loop_frames.py; with render_window,
   the tracker's window alone), while the tracker steps the frame before (frame_loop.run_frames' overlap);
4. the Tracker (pipelines/tracking/tracker.py) takes (t_k, image) and nothing else: it starts cold from the images unless
   `warm_start`, where it is handed the truth plus a draw from the filter's P0 (filter studies only).
The truth only scores (pipelines/runs/scoring.py). Run r draws its camera noise (and a warm start) from
SeedSequence(seed, spawn_key=(r,)) and frame k's noise from spawn_key (r, 1, k); runs go through the core's runner.
Run 0 streams its recording frame by frame to the sink it is handed (analysis.recording.TrackRecorder). The frames
go through the per-frame loop `envisat track` shares (pipelines/runs/frame_loop.py: tracker, rows, recording, stage times).

Memory does not grow with the run's length: a run writes its per-frame arrays to runs/run-NNNN/<name>.npy in
chunks of CHUNK_FRAMES frames as it goes (RunRows, which also reduces the stage times and frame counts per chunk)
and returns only those reductions through the runner; the job then checks the contracts and scores chunk by
chunk (scoring.frame_errors: a few scalars per frame are kept), streams est.npz and det.npz from the files
(io.save_npz with StreamedArray members: the bytes of the whole arrays), draws errors.png from at most
PLOT_FRAMES frames (pipelines/runs/run_files.py), and removes runs/. What stays proportional to the frames: the truth's state and times, the
recorder's corners, a few scalars per frame (bench/memory.py measures it). The image is any square
image.resolution_px: the MJCF's chaser_cam read out at that size (the same field of view).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass

import numpy as np

from envisat_pose.analysis.sink_check import check_recording_path, check_sink
from envisat_pose.config import config_arg, derived, path_arg, to_dict, to_toml
from envisat_pose.contracts import TruthTrajectory
from envisat_pose.datagen.gl_check import check_gl_platform
from envisat_pose.datagen.scenario import scaled_start, scenario_config
from envisat_pose.datagen.truth import simulate_truth
from envisat_pose.datagen.views import sample_seed
from envisat_pose.filtering.estimator import filter_inertia_T_kg_m2
from envisat_pose.geometry import load_camera
from envisat_pose.io import atomic_write_text, sha256_file, staged_folder
from envisat_pose.out_dirs import made_out_dir, refuse_foreign_outputs
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.common.job_defaults import job_record, weights_name
from envisat_pose.pipelines.common.threads import compute_threads
from envisat_pose.pipelines.runs.frame_loop import run_frames
from envisat_pose.pipelines.runs.loop_frames import FrameMaker, PlanAhead, closed_loop_frames
from envisat_pose.pipelines.runs.outputs import mean_nis_per_dof, status_counts, status_summary
from envisat_pose.pipelines.runs.rows import STAGES, RunRows, timing_by_status
from envisat_pose.pipelines.runs.run_config import RUN_PROCESS_BYTES, RunConfig, run_config_from_json, sun_and_shadow
from envisat_pose.pipelines.runs.run_files import lost_runs, plot_inputs, run_rows, score_run_files, write_run_files
from envisat_pose.pipelines.runs.run_progress import FrameTally, runs_bar, tally_path
from envisat_pose.pipelines.runs.scoring import recording_errors
from envisat_pose.pipelines.tracking.build import tracker_detector
from envisat_pose.pipelines.tracking.camera_file import camera_record
from envisat_pose.pipelines.tracking.namings import target_namings
from envisat_pose.pipelines.tracking.onboard import chaser_function, onboard_physics, orbit_config
from envisat_pose.pipelines.tracking.tracker import Tracker
from envisat_pose.pools import RunnerConfig, run_tasks, thread_env, warn_oversubscribed
from envisat_pose.provenance import source_line
from envisat_pose.realtime import real_time_factor
from envisat_pose.state import draw_initial_estimate
from envisat_pose.target import load_target, other_target
from envisat_pose.written_target import with_target_sha256

# The config (pipelines/runs/run_config.py), the on-board physics and orbit (pipelines/tracking/onboard.py), the per-frame
# row store (pipelines/runs/rows.py) and the runs' files read back (pipelines/runs/run_files.py) have their own modules:
# import their names from there.


# ---------------------------------------------------------------------------------------------------------
# The truth


def run_truth(cfg: RunConfig, progress: bool = False):
    """The MuJoCo truth of the run on the frame grid (datagen.truth.simulate_truth, as `envisat simulate`), its
    start sized to the target as a generated sequence's (image.sequence.range_scale: 1 for ENVISAT)."""
    scale = cfg.image.sequence.range_scale
    scen = scenario_config(cfg.scenario, duration_s=cfg.duration_s, dt_s=1.0 / cfg.rate_hz, seed=cfg.seed,
                           target={"file": cfg.image.target}, **scaled_start(cfg.scenario, scale))
    return simulate_truth(scen, progress=progress)


# ---------------------------------------------------------------------------------------------------------
# One closed-loop run (a runner task)


def run_target(cfg: RunConfig):
    """The Tracker's target of a run: None for ENVISAT (its corner network), else the Target of image.target."""
    return None if other_target(cfg.image.target) is None else load_target(cfg.image.target)


def run_camera(resolution_px: int):
    """The MJCF's chaser_cam read out at resolution_px (square): the same field of view and mount."""

    cam = load_camera()
    return cam if resolution_px == cam.width_px else cam.scaled(resolution_px, resolution_px)


def rescale_px(uv: np.ndarray, src, dst) -> np.ndarray:
    """Pixels (..., 2) of camera src as camera dst (the same field of view, another size) sees them."""
    s = dst.f_px / src.f_px
    return (uv - [src.cu_px, src.cv_px]) * s + [dst.cu_px, dst.cv_px]


def closed_loop_task(cfg_json: str, run: int, truth_path: str, sink: str | None, progress: bool,
                     sim_s_per_frame: float, run_dir: str, tally: str | None = None) -> dict:
    """Closed loop `run` over the truth in truth_path; writes its per-frame arrays (record_arrays) to
    run_dir/<name>.npy chunk by chunk as it goes (RunRows) and returns only the run's reductions (plain data for
    the runner). sink: where run 0 streams its recording (analysis.recording.TrackRecorder), None for none.
    progress: this run's own per-frame bar; tally: a file where it counts its frames for the job's bar over
    every run (run_progress.FrameTally), None for none. The compute threads are the config's inside, the
    caller's again after (a run in the calling process)."""
    cfg = run_config_from_json(cfg_json)
    with compute_threads(cfg.threads, 1):
        return _closed_loop(cfg, run, truth_path, sink, progress, sim_s_per_frame, run_dir, tally)


def _closed_loop(cfg: RunConfig, run: int, truth_path: str, sink: str | None, progress: bool,
                 sim_s_per_frame: float, run_dir: str, tally: str | None) -> dict:
    from envisat_pose.datagen.render_cache import shared_renderer

    gcfg = cfg.image
    truth = TruthTrajectory.load(truth_path)
    mu, gg = onboard_physics(truth, truth_path)
    sun_C, eclipse, nadir_C = sun_and_shadow(cfg, truth)
    camera = run_camera(gcfg.resolution_px)
    # the truth's corners are projected at the MJCF camera's size; the recorder shows them at the frames' size
    truth_uv = truth.corners_px if camera.width_px == load_camera().width_px else \
        rescale_px(truth.corners_px, load_camera(), camera)
    truth_seen = truth.in_frame & truth.visible
    t_s, x_truth, orbit = truth.t_s, truth.x, orbit_config(truth.config)
    del truth  # what the loop reads of it is above; the rest (corners in C, the chaser's orbit) is not held
    renderer = shared_renderer(gcfg.resolution_px, gcfg.shadows,
                               gcfg.appearance.texture_set_size if gcfg.appearance_on else 0,
                               gcfg.appearance.texture_seed, target=gcfg.target)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(run,)))
    prior = None
    if cfg.warm_start:
        prior = (draw_initial_estimate(x_truth[0], cfg.filter.P0, rng), cfg.filter.P0, float(t_s[0]))
    detector = tracker_detector(cfg.weights, target=gcfg.target, bf16=cfg.bf16)
    tracker = Tracker(camera, detector, chaser_function(orbit), cfg.tracker,
                      dataclasses.asdict(cfg.filter), mu_m3_s2=mu, gravity_gradient=gg, prior=prior,
                      target=run_target(cfg))  # exact
    appearance_seed = sample_seed(cfg.seed, 0, 0)  # one appearance for the whole sequence: the same target in every run
    rows = RunRows(run_dir, len(t_s), K=tracker.K)
    recorder = None
    if sink:
        from envisat_pose.analysis.recording import TrackRecorder

        target = load_target(gcfg.target)
        recorder = TrackRecorder(sink, camera, with_truth=True, title=f"envisat run {target.name}, {cfg.scenario}, "
                                 f"run {run}", target=target, error_in_chart=recording_errors(tracker.fcfg.sigma_chart))

    maker = FrameMaker(renderer, gcfg, cfg.seed, run, appearance_seed, sun_C, nadir_C)
    plan_ahead = PlanAhead(tracker, t_s) if cfg.render_window else None
    frames = closed_loop_frames(maker, t_s, x_truth, eclipse, sim_s_per_frame, plan_ahead, cfg.full_frame_every,
                                truth=None if recorder is None else (truth_uv, truth_seen))  # the truth: recording
    # the next frame made while the tracker steps this one
    res = run_frames(tracker if plan_ahead is None else plan_ahead, frames, rows, recorder, cfg.jpeg_quality,
                     f"closed loop (run {run})" if progress else None, overlap=True,
                     tally=None if tally is None else FrameTally(tally))
    return res | maker.counts | {"last_cold_start_refusal": tracker.last_refusal}


# ---------------------------------------------------------------------------------------------------------
# The job: truth, runs, outputs


# what summary.json's run0 keeps of run 0's reductions (beside its status_summary)
RUN0_KEYS = ("frames_skipped_eclipse", "frames_roi", "frames_ambiguous", "frames_acquiring", "frames_lost",
             "frames_windowed", "frames_window_remade", "last_cold_start_refusal")


def run_output_paths(out_dir: str) -> dict[str, str]:
    names = {"truth": "truth.npz", "est": "est.npz", "det": "det.npz", "plot": "errors.png",
             "config": "run.config.toml", "summary": "summary.json", "recording": "recording.rrd"}
    return {k: os.path.join(out_dir, v) for k, v in names.items()}


@dataclass(frozen=True)
class TruthBrief:
    """What the job keeps of its truth after saving it: t_s (T,) s, x (T, 12), config (dict)."""

    t_s: np.ndarray
    x: np.ndarray
    config: dict


@locks_output("out_dir", "run")
def run_closed_loop(cfg: RunConfig, out_dir: str, progress: bool = False, sink: str | None = None) -> dict:
    """The whole job into out_dir (created, parents too); returns the summary dict (also written as
    summary.json). sink: where run 0's recording goes (None: save to out_dir/recording.rrd; 'spawn' or
    'connect:ADDR' for a live viewer).

    Every output is written into a hidden folder inside out_dir and moved into place when the job completes
    (io.staged_folder): an error or an interrupt leaves out_dir as it was (an earlier run's outputs intact); a
    folder holding files of the outputs' names but no run.config.toml written by `envisat run` (a user's own
    summary.json) is refused first (out_dirs.refuse_foreign_outputs).
    Memory does not grow with the run's per-frame arrays: each run writes them to runs/run-NNNN/ (in the staged
    folder) chunk by chunk; est.npz and det.npz are streamed from those files (then removed) and the scores read
    them chunk by chunk (what stays whole: the truth, and a few scalars per frame: the errors the scores need
    and the status)."""

    cfg, out_dir = config_arg(cfg, RunConfig), path_arg(out_dir, "out_dir")
    check_gl_platform()  # MuJoCo renders every frame: a platform that cannot is one line, before the folder is made
    if sink is not None:
        check_sink(sink)  # before the folder is made
    else:
        check_recording_path(out_dir, "out_dir")  # the recording goes there
    if not derived(cfg.workers):  # a count given (the default is sized to the machine: RunConfig)
        warn_oversubscribed(cfg.workers, bytes_each=RUN_PROCESS_BYTES)  # RunConfig: no more than the runs
    names = [os.path.basename(p) for p in run_output_paths(out_dir).values()]
    refuse_foreign_outputs(out_dir, names, "run.config.toml", "run")  # a user's summary.json is not replaced
    with made_out_dir(out_dir), staged_folder(out_dir, names) as stage:
        return _run_closed_loop(cfg, stage, progress, sink)


def saved_bytes(sink: str) -> int:
    """The size of the file a 'save:PATH' sink wrote (the run folder's recording.rrd or the caller's PATH); 0 for a
    live viewer's sink, which writes none."""
    kind, _, path = sink.partition(":")
    return os.path.getsize(path) if kind == "save" and os.path.isfile(path) else 0


def _run_closed_loop(cfg: RunConfig, out_dir: str, progress: bool, sink: str | None) -> dict:
    import shutil

    paths = run_output_paths(out_dir)
    wall0 = time.perf_counter()
    truth = run_truth(cfg, progress=False)
    sim_s = time.perf_counter() - wall0
    truth.save(paths["truth"])
    truth = TruthBrief(truth.t_s, truth.x, truth.config)  # the rest of the truth is in truth.npz, not held
    T = len(truth.t_s)
    cfg_json = json.dumps(to_dict(cfg), sort_keys=True)
    workers = cfg.workers  # at most one per run (RunConfig)
    runner = RunnerConfig("local", workers, env=thread_env(workers))  # one worker: run_tasks sets it here
    sink = sink or f"save:{os.path.abspath(paths['recording'])}"
    runs_dir = os.path.join(out_dir, "runs")
    run_dirs = [os.path.abspath(os.path.join(runs_dir, f"run-{r:04d}")) for r in range(cfg.runs)]
    # several runs: one bar over every run's frames, each run counting its own into a file the job reads
    tallies = [tally_path(d) for d in run_dirs] if progress and cfg.runs > 1 else None
    tasks = [(cfg_json, r, os.path.abspath(paths["truth"]), sink if r == 0 else None, progress and cfg.runs == 1,
              sim_s / T, run_dirs[r], None if tallies is None else tallies[r]) for r in range(cfg.runs)]
    results: list[dict | None] = [None] * cfg.runs
    t0 = time.perf_counter()
    with runs_bar(tallies, T, f"closed loop ({workers} workers)") as finished:
        for i, res in run_tasks(closed_loop_task, tasks, runner):
            results[i] = res
            finished(i)
    loop_wall_s = time.perf_counter() - t0
    R = cfg.runs
    # the frames' camera: det.npz's pixels are its; truth.npz's corners_px are the MJCF chaser_cam's (its contract)
    used = camera_record(run_camera(cfg.image.resolution_px), None, False)
    # the target as `envisat track` records it in both files (ENVISAT's too): the file as given, name, sha256, keypoints
    record = load_target(cfg.image.target).record(cfg.image.target)
    config_json = json.dumps({"run": job_record(cfg), "truth_source": {"scenario": cfg.scenario},
                              "truth_config": truth.config, "camera": used, "target": record}, sort_keys=True)
    det_cfg = json.dumps({"weights": weights_name(cfg.weights), "run": 0, "scenario": cfg.scenario, "seed": cfg.seed,
                          "roi": cfg.tracker.roi.enabled, "camera": used, "target": record}, sort_keys=True)
    target = run_target(cfg)
    equivalent = None if target is None else target_namings(target, filter_inertia_T_kg_m2(target)).equivalent
    scores = score_run_files(truth.t_s, truth.x, run_dirs, paths, config_json, det_cfg, equivalent=equivalent,
                             chart=cfg.filter.sigma_chart)  # the runs' trackers' chart (tracker_filter keeps it)
    write_run_files(paths, truth.t_s, truth.x, run_dirs, lost_runs(run_dirs, T), config_json,
                    [f"frame-{k:06d}" for k in range(T)], det_cfg,
                    extra={"settled": np.array(scores["settled_runs"], bool)})
    atomic_write_text(paths["config"], "# envisat run: the full validated config of this run\n" + source_line()
                      + to_toml(with_target_sha256(job_record(cfg), "run", truth.config["target"]["sha256"])))
    from envisat_pose.analysis.plots import plot_estimate

    plot_estimate(*plot_inputs(truth.t_s, truth.x, run_dirs), paths["plot"],
                  title=f"closed loop of {load_target(cfg.image.target).name}, scenario {cfg.scenario!r}, {R} run(s), "
                        f"seed {cfg.seed}")
    cols = [run_rows(d, ["status", "nis", "nis_dof"], 0, T) for d in run_dirs]  # three scalars a frame
    shutil.rmtree(runs_dir, ignore_errors=True)
    timing_sum = np.sum([r["timing_s"] for r in results], axis=0)  # (stages,) over runs and frames
    sim_time_s = float(truth.t_s[-1] - truth.t_s[0]) + 1.0 / cfg.rate_hz
    # one run's wall time: its loop's (the stages overlap where frames are made beside the tracker) and its share
    # of the truth's simulation
    run_wall_s = float(np.mean([r["loop_wall_s"] for r in results])) + sim_s
    r0 = results[0]
    summary = {
        "scenario": cfg.scenario, "target": load_target(cfg.image.target).record(cfg.image.target), "runs": R, "frames": T, "duration_s": cfg.duration_s, "roi": cfg.tracker.roi.enabled,
        "weights": weights_name(cfg.weights), "weights_sha256": sha256_file(cfg.weights),
        "start": "warm" if cfg.warm_start else "cold",
        "resolution_px": cfg.image.resolution_px,
        "scores": scores,
        "timing_ms_per_frame": {s: float(1000 * timing_sum[i] / (R * T)) for i, s in enumerate(STAGES)},
        "timing_ms_per_frame_by_status": timing_by_status(results),
        "real_time_factor_one_run": real_time_factor(truth.t_s, run_wall_s, 1.0 / cfg.rate_hz),
        "real_time_factor_job": sim_time_s * R / max(loop_wall_s, 1e-9),
        "wall_s": {"truth_simulation": sim_s, "loops": loop_wall_s, "total": time.perf_counter() - wall0},
        "run0": {k: r0[k] for k in RUN0_KEYS} | status_summary(truth.t_s, cols[0]),
        # without the truth, as `envisat track` says it: every run's frames by status and their mean NIS
        "frames_by_status": status_counts(np.concatenate([c["status"] for c in cols])),
        "mean_nis_per_dof": mean_nis_per_dof(*(np.concatenate([c[k] for c in cols]) for k in ("nis", "nis_dof"))),
        "recording_bytes": saved_bytes(sink),
    }
    atomic_write_text(paths["summary"], json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return summary
