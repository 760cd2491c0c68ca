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
from envisat_pose.pipelines.tracker import STATUSES, TRACKER_FILTER, TrackerConfig
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
        check(self.image.resolution_px == cam.width_px == cam.height_px, "image.resolution_px",
              self.image.resolution_px, f"the camera's {cam.width_px} px (models/envisat.xml, camera chaser_cam): "
              "the filter's pixel model and the detector's training use it")


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


def closed_loop_task(cfg_json: str, run: int, truth_path: str, sink: str | None, progress: bool,
                     sim_s_per_frame: float) -> dict:
    """Closed loop `run` over the truth in truth_path; returns its arrays (record_arrays; plain data for the
    runner). sink: where run 0 streams its recording (analysis.recording.TrackRecorder), None for none."""
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
    camera = load_camera()
    renderer = shared_renderer(gcfg.resolution_px, gcfg.shadows,
                               gcfg.appearance.texture_set_size if gcfg.appearance_on else 0,
                               gcfg.appearance.texture_seed)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(run,)))
    prior = None
    if cfg.warm_start:
        prior = (draw_initial_estimate(truth.x[0], cfg.filter.P0, rng), cfg.filter.P0, float(truth.t_s[0]))
    tracker = Tracker(camera, load_detector(cfg.weights), chaser_function(orbit_config(truth.config)), cfg.tracker,
                      cfg.filter, mu_m3_s2=mu, gravity_gradient=gg, prior=prior)
    look_seed = sample_seed(cfg.seed, 0, 0)  # one look for the whole sequence: the same target in every run
    T = len(truth.t_s)
    out = record_arrays(T)
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
            x = truth.x[k]
            image = None
            t_render = t_camera = 0.0
            if not eclipse[k]:
                t0 = time.perf_counter()
                view = View(x[POS], mrp_to_dcm(x[MRP]).T, sun_C[k], unit(nadir_C[k]),
                            float(np.linalg.norm(nadir_C[k])), earth_backdrop=gcfg.earth_probability > 0)
                view, _ = with_look(gcfg, view, {}, look_seed)
                rendered = renderer.render(view)
                t_render = time.perf_counter() - t0
                t0 = time.perf_counter()
                frame_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(run, 1, k)))
                params = draw_corruption_params(gcfg, rendered, x, renderer.K[0, 0], renderer.target_boxes, frame_rng)
                image = apply_corruption(rendered.gray_u8, params)
                t_camera = time.perf_counter() - t0
            est = tracker.step(float(truth.t_s[k]), image)
            store_estimate(out, k, est)
            out["skipped"][k] = image is None
            t0 = time.perf_counter()
            if recorder is not None:
                recorder.log_frame(k, est_row(out, k, float(truth.t_s[k])), image, cfg.jpeg_quality, x_true=x,
                                   corners_true_px=truth.corners_px[k], in_frame=truth.in_frame[k] & truth.visible[k])
            out["timing_s"][k] = (sim_s_per_frame, t_render, t_camera, est.timing_s.get("detection", 0.0),
                                  est.timing_s.get("filtering", 0.0), time.perf_counter() - t0)
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(est.status, refresh=False)
    finally:
        if bar is not None:
            bar.close()
        if recorder is not None:
            recorder.close()
    return out


def est_row(out: dict, k: int, t_s: float) -> dict:
    """Row k of a run's arrays (at t_s, s) as the plain dict the recorder logs."""
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


def run_closed_loop(cfg: RunConfig, out_dir: str, progress: bool = True, sink: str | None = None) -> dict:
    """The whole job into out_dir; returns the summary dict (also written as summary.json). sink: where run 0's
    recording goes (default: save to out_dir/recording.rrd; 'spawn' or 'connect:ADDR' for a live viewer)."""
    from envisat_pose.config import to_toml
    from envisat_pose.contracts import Detections, Estimates
    from envisat_pose.io import atomic_write_text, save_npz
    from envisat_pose.pipelines.scoring import score_runs
    from envisat_pose.runner import RunnerConfig, cpu_share, run_tasks

    os.makedirs(out_dir, exist_ok=True)
    paths = output_paths(out_dir)
    wall0 = time.perf_counter()
    truth = simulate_truth(cfg, progress=False)
    sim_s = time.perf_counter() - wall0
    truth.save(paths["truth"])
    T = len(truth.t_s)
    cfg_json = json.dumps(to_dict(cfg), sort_keys=True)
    workers = min(cfg.workers, cfg.runs)
    runner = RunnerConfig("local", workers, env={"LP_NUM_THREADS": str(cpu_share(workers))})
    if workers == 1:
        os.environ.setdefault("LP_NUM_THREADS", str(cpu_share(1)))
    sink = sink or f"save:{os.path.abspath(paths['recording'])}"
    tasks = [(cfg_json, r, os.path.abspath(paths["truth"]), sink if r == 0 else None, progress and cfg.runs == 1,
              sim_s / T) for r in range(cfg.runs)]
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
    x_true = np.broadcast_to(truth.x, (R, T, 12)).copy()
    x_hat = np.stack([r["x_hat"] for r in results])
    P = np.stack([r["P"] for r in results])
    status = np.stack([r["status"] for r in results])
    scores = score_runs(truth.t_s, x_true, x_hat, P, status, skipped=results[0]["skipped"])
    config_json = json.dumps({"run": to_dict(cfg), "truth_source": {"scenario": cfg.scenario},
                              "truth_config": truth.config}, sort_keys=True)
    est = Estimates(t_s=truth.t_s, x_true=x_true, x_hat=x_hat, P=P,
                    n_meas=np.stack([r["n_meas"] for r in results]), nis=np.stack([r["nis"] for r in results]),
                    nis_dof=np.stack([r["nis_dof"] for r in results]),
                    diverged=~np.array(scores["converged_runs"], bool), config_json=config_json)
    est.save(paths["est"])
    r0 = results[0]
    det = {k: r0[k] for k in ("corners_px", "cov_px", "confidence", "visible", "rejected", "alt_corners_px",
                              "alt_probability", "ambiguous", "crop_px", "roi_px", "converged", "skipped", "naming",
                              "status", "p_best", "n_hypotheses")}
    det["t_s"] = truth.t_s
    det["key"] = np.array([f"frame-{k:06d}" for k in range(T)])
    det_cfg = json.dumps({"weights": cfg.weights, "run": 0, "scenario": cfg.scenario, "seed": cfg.seed,
                          "roi": cfg.tracker.roi}, sort_keys=True)
    Detections.validated({**det, "config_json": det_cfg}, paths["det"])
    save_npz(paths["det"], {**det, "config_json": np.array(det_cfg)})
    atomic_write_text(paths["config"], "# envisat run: the full validated config of this run\n" + to_toml(to_dict(cfg)))
    from envisat_pose.analysis.plots import plot_estimate

    plot_estimate(truth.t_s, x_true, x_hat, P, paths["plot"],
                  title=f"closed loop, scenario {cfg.scenario!r}, {R} run(s), seed {cfg.seed}")
    timing = np.stack([r["timing_s"] for r in results])  # (R, T, stages)
    sim_time_s = float(truth.t_s[-1] - truth.t_s[0]) + 1.0 / cfg.rate_hz
    frames_sum = float(timing.sum(axis=-1).mean(axis=0).sum())  # one run's wall time in the stages
    summary = {
        "scenario": cfg.scenario, "runs": R, "frames": T, "duration_s": cfg.duration_s, "roi": cfg.tracker.roi,
        "weights": cfg.weights, "start": "warm" if cfg.warm_start else "cold",
        "scores": scores,
        "timing_ms_per_frame": {s: float(1000 * timing[..., i].mean()) for i, s in enumerate(STAGES)},
        "real_time_factor_one_run": sim_time_s / max(frames_sum, 1e-9),
        "real_time_factor_job": sim_time_s * R / max(loop_wall_s, 1e-9),
        "wall_s": {"truth_simulation": sim_s, "loops": loop_wall_s, "total": time.perf_counter() - wall0},
        "run0": {"frames_skipped_eclipse": int(r0["skipped"].sum()), "frames_roi": int(np.isfinite(r0["roi_px"][:, 0]).sum()),
                 "frames_ambiguous": int(r0["ambiguous"].sum()),
                 "frames_acquiring": int((r0["status"] == 0).sum()), "frames_lost": int((r0["status"] == 2).sum())},
        "recording_bytes": os.path.getsize(paths["recording"]) if os.path.isfile(paths["recording"]) else 0,
    }
    atomic_write_text(paths["summary"], json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return summary
