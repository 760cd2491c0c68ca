"""The closed loop of `envisat run`: MuJoCo truth -> rendered camera frames -> the space camera -> the Tracker.

Per run and frame k (t_k = k / rate_hz):
1. the truth at t_k is the MuJoCo truth simulation of `envisat simulate` (datagen.truth.simulate, run once before
   the loops: it refuses a trajectory that breaks the keep-out margin before any image is made);
2. in the Earth's shadow (the chaser's own orbit and the sun direction) there is no frame: the tracker predicts;
3. MuJoCo renders the chaser camera (datagen's SceneRenderer, the factory's sequence-mode view and look), and
   datagen's space camera corrupts it with the run's own noise;
4. the Tracker (pipelines/tracker.py) takes (t_k, image) and nothing else: it starts cold from the images unless
   `warm_start`, where it is handed the truth plus a draw from the filter's P0 (filter studies only).
The truth only scores (pipelines/scoring.py). Run r draws its camera noise (and a warm start) from
SeedSequence(seed, spawn_key=(r,)) and frame k's noise from spawn_key (r, 1, k); runs go through the core's runner.
Run 0 streams its recording frame by frame to the sink it is handed (analysis.recording.TrackRecorder).

Memory does not grow with the run's length: a run writes its per-frame arrays to runs/run-NNNN/<name>.npy in
chunks of CHUNK_FRAMES frames as it goes (RunRows, which also reduces the stage times and frame counts per chunk)
and returns only those reductions through the runner; the job then checks the contracts and scores chunk by
chunk (scoring.frame_errors: a few scalars per frame are kept), streams est.npz and det.npz from the files
(io.save_npz with StreamedArray members: the bytes of the whole arrays), draws errors.png from at most
PLOT_FRAMES frames, and removes runs/. What stays proportional to the frames: the truth's state and times, the
recorder's corners, a few scalars per frame (bench/memory.py measures it). The image is any square
image.resolution_px: the MJCF's chaser_cam read out at that size (the same field of view).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import check, from_dict, to_dict
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.pipelines.tracker import TRACKER_FILTER, TrackerConfig
from envisat_pose.status import ACQUIRING, LOST, STATUSES
from envisat_pose.state import MRP, POS

# per-frame stages timed: the MuJoCo truth (its share per frame), MuJoCo rendering, the space camera, the detector,
# the filter (with the cold start's fits), the recording (encoding and logging run 0's frame)
STAGES = ("simulation", "rendering", "camera", "detection", "filtering", "recording")
# a lit default: the sun 45 deg off the line of sight, behind the camera, from above the orbit plane at t = 0 (in
# C: radial, along-track, normal); in the default orbit the chaser enters the Earth's shadow at t = 1203 s
DEFAULT_SUN_C0 = (0.7, -0.7, 0.15)


def _image_defaults() -> "GenerateConfig":
    from envisat_pose.datagen.factory import GenerateConfig

    return GenerateConfig(mode="sequence", num_images=1, shard_size=1, write_mask=False, write_depth=False)


@dataclass(frozen=True)
class RunConfig:
    """One `envisat run` job. scenario: named truth; duration_s: simulated time; rate_hz: camera and filter rate;
    runs: closed loops on the same truth; workers: processes for them; seed: the truth's random attitude, every
    run's camera noise (and warm start); weights: detector weights file. warm_start: start each run's filter from
    the truth plus a draw from filter.p0_sigma (filter studies), instead of cold from the images. threads: torch
    CPU threads per run; jpeg_quality: run 0's images in the recording. image: the camera frames as the image
    factory's sequence mode makes them (its sequence fields are set from the ones above). filter: the UKF (the
    scenario's [filter] table under the file and the flags). tracker: pipelines.tracker.TrackerConfig."""

    scenario: str = "default"
    duration_s: float = 600.0
    rate_hz: float = 1.0
    runs: int = 1
    workers: int = 1
    seed: int = 0
    weights: str = ""
    warm_start: bool = False
    threads: int = 1
    jpeg_quality: int = 80
    image: "GenerateConfig" = field(default_factory=_image_defaults)
    filter: FilterConfig = field(default_factory=lambda: FilterConfig(**TRACKER_FILTER))
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    def validate(self, prefix: str = "") -> None:
        from envisat_pose.geometry import load_camera

        check(self.duration_s > 0, "duration_s", self.duration_s, "a positive duration in s")
        check(0.0 < self.rate_hz <= 10.0, "rate_hz", self.rate_hz, "a rate in (0, 10] Hz")
        check(self.duration_s * self.rate_hz <= 200_000, "duration_s", self.duration_s,
              "at most 200000 frames (duration_s x rate_hz)")
        check(1 <= self.runs <= 1000, "runs", self.runs, "1 to 1000 runs")
        check(1 <= self.workers <= 256, "workers", self.workers, "1 to 256 processes")
        check(0 <= self.seed < 2**63, "seed", self.seed, "a non-negative integer seed")
        check(1 <= self.threads <= 256, "threads", self.threads, "1 to 256 threads")
        check(1 <= self.jpeg_quality <= 100, "jpeg_quality", self.jpeg_quality, "a JPEG quality in [1, 100]")
        cam = load_camera()
        check(cam.width_px == cam.height_px and 16 <= self.image.resolution_px <= 4096, "image.resolution_px",
              self.image.resolution_px, "a square image side in [16, 4096] px (the MJCF's chaser_cam, "
              f"{cam.width_px} px, read out at that size: the same field of view)")


def stage_types() -> None:
    """Make the annotation "GenerateConfig" resolvable (typing.get_type_hints reads this module's globals): the
    image factory's config is a stage's type, imported when a run is configured, not when the CLI starts."""
    from envisat_pose.datagen.factory import GenerateConfig

    globals()["GenerateConfig"] = GenerateConfig


def finish_config(cfg: RunConfig) -> RunConfig:
    """The image config's sequence fields from the run's (mode, scenario, seed, frames, frame period) and the sun
    made explicit (the scenario's [eclipse] sun, else DEFAULT_SUN_C0 at t = 0 turned into N)."""
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import scenario_config, scenario_eclipse

    n = n_frames(cfg)
    sun = cfg.image.sun_dir
    if sun is None:
        ecl = scenario_eclipse(cfg.scenario)
        if ecl is not None:
            sun = tuple(float(v) for v in ecl.sun_dir_N)
        else:
            orb = chaser_orbit(scenario_config(cfg.scenario).orbit, np.array([0.0]))
            s_C = np.asarray(DEFAULT_SUN_C0) / np.linalg.norm(DEFAULT_SUN_C0)
            sun = tuple(round(float(v), 9) for v in orb.R_N_from_C[0] @ s_C)
    image = dataclasses.replace(cfg.image, mode="sequence", scenario=cfg.scenario, seed=cfg.seed, num_images=n,
                                shard_size=n, frame_dt_s=1.0 / cfg.rate_hz, sun_dir=sun)
    return dataclasses.replace(cfg, image=image)


def n_frames(cfg: RunConfig) -> int:
    return int(np.floor(cfg.duration_s * cfg.rate_hz + 1e-9)) + 1


def config_from_json(text: str) -> RunConfig:
    stage_types()
    return from_dict(RunConfig, json.loads(text))


# ---------------------------------------------------------------------------------------------------------
# The truth, and what the chaser knows of its own orbit


def simulate_truth(cfg: RunConfig, progress: bool = False):
    """The MuJoCo truth of the run on the frame grid (datagen.truth.simulate, as `envisat simulate`)."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate

    scen = scenario_config(cfg.scenario, duration_s=cfg.duration_s, dt_s=1.0 / cfg.rate_hz, seed=cfg.seed)
    return simulate(scen, progress=progress)


def orbit_config(truth_config: dict):
    """The chaser's Keplerian orbit (datagen's OrbitConfig) of a truth's config."""
    from envisat_pose.datagen.scenario import ScenarioConfig

    return from_dict(ScenarioConfig, truth_config).orbit


def chaser_function(orbit):
    """chaser_at(t_s) -> (4,) the chaser's polar orbit (r_m, rdot_m_s, theta_rad, thetadot_rad_s) from its
    Keplerian elements: what the chaser knows of itself on board."""
    from envisat_pose.datagen.orbit import chaser_orbit

    def chaser_at(t_s: float) -> np.ndarray:
        o = chaser_orbit(orbit, np.array([float(t_s)]))
        return np.array([o.r_m[0], o.rdot_m_s[0], o.theta_rad[0], o.thetadot_rad_s[0]])

    return chaser_at


def sun_and_shadow(cfg: RunConfig, truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: sun_dir_C (N, 3) unit, eclipse (N,) bool (the chaser in the Earth's cylindrical shadow),
    nadir_C (N, 3) the Earth's centre from the chaser, m."""
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import in_earth_shadow

    orb = chaser_orbit(orbit_config(truth.config), truth.t_s)
    sun_N = np.asarray(cfg.image.sun_dir, dtype=float)
    sun_N = sun_N / np.linalg.norm(sun_N)
    sun_C = np.einsum("nji,j->ni", orb.R_N_from_C, sun_N)
    eclipse = in_earth_shadow(orb.r_N_m, sun_N)
    nadir_C = np.zeros((len(truth.t_s), 3))
    nadir_C[:, 0] = -orb.r_m
    return sun_C, eclipse, nadir_C


# ---------------------------------------------------------------------------------------------------------
# One closed-loop run (a runner task)


def record_arrays(T: int) -> dict:
    """The per-frame arrays a run keeps (one row per frame)."""
    out = {k: np.zeros((T,), dtype=np.int64) for k in ("n_meas", "nis_dof", "naming", "status", "n_hypotheses")}
    out.update({"x_hat": np.empty((T, 12)), "P": np.empty((T, 12, 12)), "nis": np.zeros(T),
                "p_best": np.zeros(T), "corners_px": np.full((T, 8, 2), np.nan),
                "cov_px": np.full((T, 8, 2, 2), np.nan), "confidence": np.zeros((T, 8)),
                "visible": np.zeros((T, 8), bool), "rejected": np.zeros((T, 8), bool),
                "alt_corners_px": np.full((T, 8, 2), np.nan), "alt_probability": np.zeros(T),
                "ambiguous": np.zeros(T, bool), "crop_px": np.zeros((T, 3)), "roi_px": np.full((T, 3), np.nan),
                "converged": np.zeros(T, bool), "skipped": np.zeros(T, bool), "timing_s": np.zeros((T, len(STAGES)))})
    return out


def store_estimate(out: dict, k: int, est) -> None:
    """Row k of record_arrays from a TrackEstimate. While acquiring before any pose the state is NaN: it is kept
    as zeros with a NaN-free wide covariance so the Estimates contract (finite) holds; status says which."""
    from envisat_pose.pipelines.tracker import ACQUIRING_SIGMA

    if np.isfinite(est.x_hat).all():
        out["x_hat"][k], out["P"][k] = est.x_hat, est.P
    else:
        out["x_hat"][k], out["P"][k] = 0.0, np.diag(np.repeat(np.square(ACQUIRING_SIGMA), 3)) * 1e4
    out["status"][k] = STATUSES.index(est.status)
    out["n_hypotheses"][k] = len(est.probabilities)
    out["p_best"][k] = float(np.max(est.probabilities)) if len(est.probabilities) else 0.0
    out["nis"][k], out["nis_dof"][k] = est.nis, est.nis_dof
    out["n_meas"][k] = int((est.measured & ~est.rejected).sum())
    out["naming"][k] = est.naming
    out["rejected"][k] = est.rejected
    out["converged"][k] = est.converged
    if est.roi_px is not None:
        out["roi_px"][k] = est.roi_px
    fd = est.detection
    if fd is not None:
        vis = np.asarray(fd.visible, bool) & np.isfinite(fd.corners_px).all(-1) & np.isfinite(fd.cov_px).all((-1, -2))
        out["visible"][k] = vis
        out["corners_px"][k] = np.where(vis[:, None], fd.corners_px, np.nan)
        out["cov_px"][k] = np.where(vis[:, None, None], fd.cov_px, np.nan)
        out["confidence"][k] = np.where(vis, np.clip(np.nan_to_num(fd.confidence), 0.0, 1.0), 0.0)
        out["alt_corners_px"][k] = fd.alt_corners_px
        out["alt_probability"][k] = float(fd.alt_probability)
        out["ambiguous"][k] = bool(fd.ambiguous)
        out["crop_px"][k] = fd.crop_px


# rows a run holds before writing them out: ~2 kB a frame, so ~2 MB per run whatever the run's length
CHUNK_FRAMES = 1000
# columns of a run's arrays that go to det.npz (run 0) and est.npz (every run)
DET_KEYS = ("corners_px", "cov_px", "confidence", "visible", "rejected", "alt_corners_px", "alt_probability",
            "ambiguous", "crop_px", "roi_px", "converged", "skipped", "naming", "status", "p_best", "n_hypotheses")
EST_KEYS = ("x_hat", "P", "n_meas", "nis", "nis_dof")


class RunRows:
    """A run's per-frame arrays (record_arrays) streamed to run_dir/<name>.npy, `chunk` frames at a time, with
    the run's reductions (stage time sums, frame counts) taken per chunk: the run holds one chunk, never the run.
    Frames come in order: row(k) is frame k's row in `buf` (the chunk before it written out when full)."""

    def __init__(self, run_dir: str, T: int, chunk: int = CHUNK_FRAMES):
        from envisat_pose.io import NpyRowWriter

        os.makedirs(run_dir, exist_ok=True)
        self.T, self.chunk, self.start, self.n = T, min(chunk, T), 0, 0
        self.buf = record_arrays(self.chunk)
        self.writers = {k: NpyRowWriter(os.path.join(run_dir, f"{k}.npy"), T, a.shape[1:], a.dtype)
                        for k, a in self.buf.items()}
        self.sums = {"timing_s": np.zeros(len(STAGES)), "frames_skipped_eclipse": 0, "frames_roi": 0,
                     "frames_ambiguous": 0, "frames_acquiring": 0, "frames_lost": 0}

    def row(self, k: int) -> int:
        if k != self.start + self.n:
            raise ValueError(f"frame {k} out of order (expected {self.start + self.n})")
        if self.n == self.chunk:
            self.flush()
        self.n += 1
        return self.n - 1

    def flush(self) -> None:
        b = {k: a[:self.n] for k, a in self.buf.items()}
        for k, w in self.writers.items():
            w.write(b[k])
        s = self.sums
        s["timing_s"] += b["timing_s"].sum(axis=0)
        s["frames_skipped_eclipse"] += int(b["skipped"].sum())
        s["frames_roi"] += int(np.isfinite(b["roi_px"][:, 0]).sum())
        s["frames_ambiguous"] += int(b["ambiguous"].sum())
        s["frames_acquiring"] += int((b["status"] == ACQUIRING).sum())
        s["frames_lost"] += int((b["status"] == LOST).sum())
        self.start, self.n = self.start + self.n, 0
        self.buf = record_arrays(self.chunk)  # fresh defaults (NaN where a frame has no detection)

    def close(self) -> dict:
        """Write the last rows and check every frame was written; returns the run's reductions (plain data)."""
        if self.n:
            self.flush()
        for w in self.writers.values():
            w.close()
        return {**self.sums, "timing_s": self.sums["timing_s"].tolist(), "frames": self.T}


def run_camera(resolution_px: int):
    """The MJCF's chaser_cam read out at resolution_px (square): the same field of view and mount."""
    from envisat_pose.geometry import load_camera

    cam = load_camera()
    return cam if resolution_px == cam.width_px else cam.scaled(resolution_px, resolution_px)


def rescale_px(uv: np.ndarray, src, dst) -> np.ndarray:
    """Pixels (..., 2) of camera src as camera dst (the same field of view, another size) sees them."""
    s = dst.f_px / src.f_px
    return (uv - [src.cu_px, src.cv_px]) * s + [dst.cu_px, dst.cv_px]


def closed_loop_task(cfg_json: str, run: int, truth_path: str, sink: str | None, progress: bool,
                     sim_s_per_frame: float, run_dir: str) -> dict:
    """Closed loop `run` over the truth in truth_path; writes its per-frame arrays (record_arrays) to
    run_dir/<name>.npy chunk by chunk as it goes (RunRows) and returns only the run's reductions (plain data for
    the runner). sink: where run 0 streams its recording (analysis.recording.TrackRecorder), None for none."""
    import cv2
    import torch

    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.contracts import TruthTrajectory
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.datagen.factory import draw_corruption_params, sample_seed, unit, with_look
    from envisat_pose.datagen.render import View, shared_renderer
    from envisat_pose.geometry import load_camera
    from envisat_pose.perception.detect import load_detector
    from envisat_pose.pipelines.tracker import Tracker
    from envisat_pose.state import draw_initial_estimate

    cfg = config_from_json(cfg_json)
    gcfg = cfg.image
    torch.set_num_threads(cfg.threads)
    cv2.setNumThreads(1)
    truth = TruthTrajectory.load(truth_path)
    mu, gg = truth_dynamics(truth)
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
                               gcfg.appearance.texture_seed)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(run,)))
    prior = None
    if cfg.warm_start:
        prior = (draw_initial_estimate(x_truth[0], cfg.filter.P0, rng), cfg.filter.P0, float(t_s[0]))
    tracker = Tracker(camera, load_detector(cfg.weights), chaser_function(orbit), cfg.tracker,
                      cfg.filter, mu_m3_s2=mu, gravity_gradient=gg, prior=prior)
    look_seed = sample_seed(cfg.seed, 0, 0)  # one look for the whole sequence: the same target in every run
    T = len(t_s)
    rows = RunRows(run_dir, T)
    recorder = None
    if sink:
        from envisat_pose.analysis.recording import TrackRecorder

        recorder = TrackRecorder(sink, camera, with_truth=True, title=f"envisat run {cfg.scenario}, run {run}")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, unit="frame", desc=f"closed loop (run {run})", mininterval=0.5)
    try:
        for k in range(T):
            x = x_truth[k]
            image = None
            t_render = t_camera = 0.0
            if not eclipse[k]:
                t0 = time.perf_counter()
                view = View(x[POS], mrp_to_dcm(x[MRP]).T, sun_C[k], unit(nadir_C[k]),
                            float(np.linalg.norm(nadir_C[k])), earth_backdrop=gcfg.earth_probability > 0)
                view, _ = with_look(gcfg, view, {}, look_seed)
                rendered = renderer.render(view, labels=False)  # the image and the pose: no depth or mask
                t_render = time.perf_counter() - t0
                t0 = time.perf_counter()
                frame_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(run, 1, k)))
                params = draw_corruption_params(gcfg, rendered, x, renderer.K[0, 0], renderer.target_boxes, frame_rng)
                image = apply_corruption(rendered.gray_u8, params)
                t_camera = time.perf_counter() - t0
            est = tracker.step(float(t_s[k]), image)
            i, out = rows.row(k), rows.buf
            store_estimate(out, i, est)
            out["skipped"][i] = image is None
            t0 = time.perf_counter()
            if recorder is not None:
                recorder.log_frame(k, est_row(out, i, float(t_s[k])), image, cfg.jpeg_quality, x_true=x,
                                   corners_true_px=truth_uv[k], in_frame=truth_seen[k])
            out["timing_s"][i] = (sim_s_per_frame, t_render, t_camera, est.timing_s.get("detection", 0.0),
                                  est.timing_s.get("filtering", 0.0), time.perf_counter() - t0)
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(est.status, refresh=False)
    finally:
        if bar is not None:
            bar.close()
        if recorder is not None:
            recorder.close()
    return rows.close()


def est_row(out: dict, k: int, t_s: float) -> dict:
    """Row k of a run's arrays (record_arrays or a RunRows chunk; at t_s, s) as the plain dict the recorder logs."""
    return {"t_s": t_s} | {name: out[name][k] for name in ("x_hat", "P", "status", "p_best", "n_hypotheses", "nis", "nis_dof",
                                             "corners_px", "visible", "rejected", "roi_px")}


def truth_dynamics(truth) -> tuple[float, bool]:
    """(mu, m^3/s^2; gravity-gradient torque on) of the truth's config: the filter models what the truth applies."""
    from envisat_pose.datagen.scenario import ScenarioConfig

    scen = from_dict(ScenarioConfig, truth.config)
    return float(scen.orbit.mu_m3_s2), bool(scen.target.gravity_gradient)


# ---------------------------------------------------------------------------------------------------------
# The job: truth, runs, outputs


def output_paths(out_dir: str) -> dict[str, str]:
    names = {"truth": "truth.npz", "est": "est.npz", "det": "det.npz", "plot": "errors.png",
             "config": "run.config.toml", "summary": "summary.json", "recording": "recording.rrd"}
    return {k: os.path.join(out_dir, v) for k, v in names.items()}


@dataclass(frozen=True)
class TruthBrief:
    """What the job keeps of its truth after saving it: t_s (T,) s, x (T, 12), config (dict)."""

    t_s: np.ndarray
    x: np.ndarray
    config: dict


def run_closed_loop(cfg: RunConfig, out_dir: str, progress: bool = True, sink: str | None = None) -> dict:
    """The whole job into out_dir; returns the summary dict (also written as summary.json). sink: where run 0's
    recording goes (default: save to out_dir/recording.rrd; 'spawn' or 'connect:ADDR' for a live viewer).

    Memory does not grow with the run's per-frame arrays: each run writes them to out_dir/runs/run-NNNN/ chunk by
    chunk; est.npz and det.npz are streamed from those files (then removed) and the scores read them chunk by
    chunk (what stays whole: the truth, and a few scalars per frame: the errors the scores need and the status)."""
    import shutil

    from envisat_pose.config import to_toml
    from envisat_pose.io import atomic_write_text
    from envisat_pose.runner import RunnerConfig, cpu_share, run_tasks

    os.makedirs(out_dir, exist_ok=True)
    paths = output_paths(out_dir)
    wall0 = time.perf_counter()
    truth = simulate_truth(cfg, progress=False)
    sim_s = time.perf_counter() - wall0
    truth.save(paths["truth"])
    truth = TruthBrief(truth.t_s, truth.x, truth.config)  # the rest of the truth is in truth.npz, not held
    T = len(truth.t_s)
    cfg_json = json.dumps(to_dict(cfg), sort_keys=True)
    workers = min(cfg.workers, cfg.runs)
    runner = RunnerConfig("local", workers, env={"LP_NUM_THREADS": str(cpu_share(workers))})
    if workers == 1:
        os.environ.setdefault("LP_NUM_THREADS", str(cpu_share(1)))
    sink = sink or f"save:{os.path.abspath(paths['recording'])}"
    runs_dir = os.path.join(out_dir, "runs")
    run_dirs = [os.path.abspath(os.path.join(runs_dir, f"run-{r:04d}")) for r in range(cfg.runs)]
    tasks = [(cfg_json, r, os.path.abspath(paths["truth"]), sink if r == 0 else None, progress and cfg.runs == 1,
              sim_s / T, run_dirs[r]) for r in range(cfg.runs)]
    results: list[dict | None] = [None] * cfg.runs
    bar = None
    if progress and cfg.runs > 1:
        from tqdm import tqdm

        bar = tqdm(total=cfg.runs, unit="run", desc=f"closed loop ({workers} workers)")
    t0 = time.perf_counter()
    for i, res in run_tasks(closed_loop_task, tasks, runner):
        results[i] = res
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    loop_wall_s = time.perf_counter() - t0
    R = cfg.runs
    config_json = json.dumps({"run": to_dict(cfg), "truth_source": {"scenario": cfg.scenario},
                              "truth_config": truth.config}, sort_keys=True)
    det_cfg = json.dumps({"weights": cfg.weights, "run": 0, "scenario": cfg.scenario, "seed": cfg.seed,
                          "roi": cfg.tracker.roi}, sort_keys=True)
    scores = score_run_files(truth.t_s, truth.x, run_dirs, paths, config_json, det_cfg)
    write_run_files(paths, truth.t_s, truth.x, run_dirs, ~np.array(scores["settled_runs"], bool), config_json,
                    [f"frame-{k:06d}" for k in range(T)], det_cfg)
    atomic_write_text(paths["config"], "# envisat run: the full validated config of this run\n" + to_toml(to_dict(cfg)))
    from envisat_pose.analysis.plots import plot_estimate

    plot_estimate(*plot_inputs(truth.t_s, truth.x, run_dirs), paths["plot"],
                  title=f"closed loop, scenario {cfg.scenario!r}, {R} run(s), seed {cfg.seed}")
    shutil.rmtree(runs_dir, ignore_errors=True)
    timing_sum = np.sum([r["timing_s"] for r in results], axis=0)  # (stages,) over runs and frames
    sim_time_s = float(truth.t_s[-1] - truth.t_s[0]) + 1.0 / cfg.rate_hz
    frames_sum = float(timing_sum.sum()) / R  # one run's wall time in the stages
    r0 = results[0]
    summary = {
        "scenario": cfg.scenario, "runs": R, "frames": T, "duration_s": cfg.duration_s, "roi": cfg.tracker.roi,
        "weights": cfg.weights, "start": "warm" if cfg.warm_start else "cold",
        "resolution_px": cfg.image.resolution_px,
        "scores": scores,
        "timing_ms_per_frame": {s: float(1000 * timing_sum[i] / (R * T)) for i, s in enumerate(STAGES)},
        "real_time_factor_one_run": sim_time_s / max(frames_sum, 1e-9),
        "real_time_factor_job": sim_time_s * R / max(loop_wall_s, 1e-9),
        "wall_s": {"truth_simulation": sim_s, "loops": loop_wall_s, "total": time.perf_counter() - wall0},
        "run0": {k: r0[k] for k in ("frames_skipped_eclipse", "frames_roi", "frames_ambiguous", "frames_acquiring",
                                    "frames_lost")},
        "recording_bytes": os.path.getsize(paths["recording"]) if os.path.isfile(paths["recording"]) else 0,
    }
    atomic_write_text(paths["summary"], json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return summary


# ---------------------------------------------------------------------------------------------------------
# Reading the runs' files back, chunk by chunk (run_closed_loop and `envisat track`)

# the most frames errors.png draws per series: beyond it every k-th frame (a 13-inch figure at 100 dpi shows
# ~400 px per panel; drawing every frame of a long run would hold every run's covariances at once)
PLOT_FRAMES = 7200


def run_rows(run_dir: str, names, start: int, stop: int) -> dict:
    """Frames [start, stop) of a run's arrays `names` (RunRows' files), read from the files."""
    from envisat_pose.io import read_npy_rows

    return {k: read_npy_rows(os.path.join(run_dir, f"{k}.npy"), start, stop) for k in names}


def run_array(run_dirs: list[str], name: str, T: int):
    """The runs' array `name` stacked over runs, (R, T, ...), as an io.StreamedArray read chunk by chunk."""
    from envisat_pose.io import StreamedArray, npy_info, read_npy_rows

    shape, dtype, _ = npy_info(os.path.join(run_dirs[0], f"{name}.npy"))

    def chunks():
        for d in run_dirs:
            for a in range(0, T, CHUNK_FRAMES):
                yield read_npy_rows(os.path.join(d, f"{name}.npy"), a, a + CHUNK_FRAMES)

    return StreamedArray((len(run_dirs),) + tuple(shape), dtype, chunks)


def score_run_files(t_s: np.ndarray, x_true: np.ndarray, run_dirs: list[str], paths: dict, config_json: str,
                    det_cfg: str, score: bool = True, det_names=DET_KEYS) -> dict | None:
    """scoring.score_runs of the runs in run_dirs against x_true (T, 12), reading x_hat and P chunk by chunk;
    each chunk is also checked as est.npz's and (run 0) det.npz's contracts check them on save (score False: only
    the checks, for x_true all NaN, no truth; returns None). Keeps only per-frame scalars (the errors, status)
    and the second half's estimates for the error summary."""
    from envisat_pose.contracts import Detections, Estimates
    from envisat_pose.pipelines.scoring import frame_errors, score_frames, summary_after_s
    from envisat_pose.state import error_summary

    T = len(t_s)
    errors, status = [], []
    for r, d in enumerate(run_dirs):
        parts, st = [], []
        for a in range(0, T, CHUNK_FRAMES):
            b = min(a + CHUNK_FRAMES, T)
            c = run_rows(d, set(EST_KEYS + ("status",) + (det_names if r == 0 else ())), a, b)
            Estimates.validated({"t_s": t_s[a:b], "x_true": x_true[None, a:b], "diverged": np.zeros(1, bool),
                                 "config_json": config_json} | {k: c[k][None] for k in EST_KEYS}, paths["est"])
            if r == 0:
                Detections.validated({"t_s": t_s[a:b], "config_json": det_cfg} | {k: c[k] for k in det_names},
                                     paths["det"])
            if not score:
                continue
            parts.append(frame_errors(x_true[a:b], c["x_hat"], c["P"]))
            st.append(c["status"])
        if score:
            errors.append({k: np.concatenate([p[k] for p in parts]) for k in parts[0]})
            status.append(np.concatenate(st))
    if not score:
        return None
    errors = {k: np.stack([e[k] for e in errors]) for k in errors[0]}
    after_s = summary_after_s(t_s)
    first = int(np.argmax(t_s >= after_s))
    x_late = np.stack([run_rows(d, ["x_hat"], first, T)["x_hat"] for d in run_dirs])
    summary = error_summary(t_s[first:], x_true[first:], x_late, after_s)
    skipped = run_rows(run_dirs[0], ["skipped"], 0, T)["skipped"]
    return score_frames(t_s, errors, np.stack(status), skipped, summary)


def write_run_files(paths: dict, t_s: np.ndarray, x_true: np.ndarray, run_dirs: list[str], diverged: np.ndarray,
                    config_json: str, keys: list[str], det_cfg: str, det_names=DET_KEYS) -> None:
    """est.npz (every run) and det.npz (run 0) streamed from the runs' files (their contracts checked chunk by
    chunk in score_run_files): the same bytes as Estimates.save / save_npz of the whole arrays."""
    from envisat_pose.io import StreamedArray, save_npz

    T, R = len(t_s), len(run_dirs)
    est = {k: run_array(run_dirs, k, T) for k in EST_KEYS}
    est["x_true"] = StreamedArray((R, T, 12), np.float64, lambda: (x_true for _ in range(R)))
    save_npz(paths["est"], est | {"t_s": t_s, "diverged": np.asarray(diverged, bool),
                                  "config_json": np.array(config_json)})
    det = {k: run_array(run_dirs[:1], k, T) for k in det_names}
    det = {k: StreamedArray(a.shape[1:], a.dtype, a.chunks) for k, a in det.items()}
    key_dtype = np.dtype(f"<U{max(max(map(len, keys), default=1), 1)}")  # as numpy.array(keys) makes it
    det["key"] = StreamedArray((T,), key_dtype, lambda: (np.array(keys[a:a + CHUNK_FRAMES], key_dtype)
                                                         for a in range(0, T, CHUNK_FRAMES)))
    save_npz(paths["det"], det | {"t_s": t_s, "config_json": np.array(det_cfg)})


def plot_inputs(t_s: np.ndarray, x_true: np.ndarray, run_dirs: list[str]) -> tuple:
    """What plots.plot_estimate draws (t_s, x_true, x_hat, P) at most PLOT_FRAMES frames (every k-th), read from
    the runs' files: P as its mean over runs (the figure's filter sigma is that mean's diagonal) on the diagonal,
    one run, so the figure holds one covariance series whatever the number of runs."""
    T = len(t_s)
    step = -(-T // PLOT_FRAMES)
    idx = np.arange(0, T, step)
    x_hat, p_sum = [], 0.0
    for d in run_dirs:
        xs, ps = [], []
        for a in range(0, T, CHUNK_FRAMES):
            c = run_rows(d, ["x_hat", "P"], a, a + CHUNK_FRAMES)
            take = slice((-a) % step, None, step)
            xs.append(c["x_hat"][take])
            ps.append(np.diagonal(c["P"][take], axis1=-2, axis2=-1))
        x_hat.append(np.concatenate(xs))
        p_sum = p_sum + np.concatenate(ps)
    P = np.zeros((1, len(idx), 12, 12))
    P[0][:, np.arange(12), np.arange(12)] = p_sum / len(run_dirs)
    return t_s[idx], np.repeat(x_true[idx][None], len(run_dirs), axis=0), np.stack(x_hat), P
