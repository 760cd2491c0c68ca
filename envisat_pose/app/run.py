"""`envisat run`: the online closed loop. Truth (MuJoCo) -> camera frame (MuJoCo render + space camera) ->
corner detector -> UKF, one frame at a time, R runs on one truth.

Per run and frame k (t_k = k / rate_hz):
1. the truth at t_k is the MuJoCo truth simulation of `envisat simulate` (datagen.truth.simulate, run once
   before the loop: it also refuses a trajectory that breaks the keep-out margin before any image is made);
2. in the Earth's shadow (the chaser's own orbit and the sun direction: known on board) the frame is skipped:
   the filter only predicts (no zeros are fed);
3. MuJoCo renders the chaser camera (datagen's SceneRenderer, the image factory's sequence-mode view and look),
   and datagen's space camera corrupts it with the run's own noise (the factory's draw_corruption_params and
   apply_corruption);
4. the filter predicts to t_k (filtering.estimator.predict_to). Once it has converged (its prior position and
   attitude sigmas below loop.converged_pos_sigma_m and loop.converged_att_sigma_deg), the predicted corners,
   projected through the camera and grown by a margin and the prior's 3-sigma, are the detector's region of
   interest, and the predicted attitude its half-turn prior; before that, or when the ROI yields fewer than
   loop.roi_min_corners corners, the detector runs its coarse pass on the whole frame;
5. the detections become pixel measurements with R = the detector's calibrated covariance x loop.r_inflation
   (its errors are correlated from frame to frame; adaptive R may raise R further, never lower it), the
   chi-square gate rejects single wrong corners, the visibility check drops corners the prior says are hidden.
   A run whose gate rejects every corner for loop.reacquire_after_frames frames widens its covariance step by
   step until corners pass again (instead of the filter's one ungated update, which takes a wrong frame in). The half-turn: the detector's naming and its half-turn alternative (A<->C, B<->D, E<->G, F<->H) are
   both filtered from the same prior, and each scored by its innovation cost, NIS + gate bound x (corners
   rejected or dropped) (~ -2 log likelihood). The cheaper one is kept. Before convergence an ambiguous frame
   is used only when the prior decides it (cost difference > loop.decisive_cost, a likelihood ratio of
   ~1000 by default); otherwise both hypotheses stay open and the frame is not used (the filter predicts).
   After convergence the prior always decides.

A frame where the detector finds nothing is a predict-only step; a wrong corner is gated; no step can make the
filter NaN (filter_step rolls a non-finite update back). Runs differ in their initial estimate (drawn from P0,
as `envisat estimate` draws it) and their camera noise; run r draws both from SeedSequence(seed,
spawn_key=(r,)) (the image of frame k from spawn_key (r, 1, k)). Runs go through the core's runner.

RUN_DIR gets truth.npz, est.npz (Estimates), det.npz (run 0's Detections plus key, alt_corners_px,
alt_probability, ambiguous, and the loop's own per-frame columns), errors.png, run.config.toml (the full
validated config), summary.json (errors, timings, real-time factor) and recording.rrd (`envisat view RUN_DIR`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import InputError, check, deep_update, from_dict, load_toml, set_dotted, to_dict, to_toml
from envisat_pose.filtering.estimator import FilterConfig

# the half-turn about the long axis: A<->C, B<->D, E<->G, F<->H (perception's alt_corners_px naming)
HALF_TURN = np.array([2, 3, 0, 1, 6, 7, 4, 5])
# per-frame stages timed: the MuJoCo truth, MuJoCo rendering, the space camera (corruption), the detector, the
# filter (predictions and both half-turn hypotheses), JPEG encoding for the recording
STAGES = ("simulation", "rendering", "camera", "detection", "filtering", "recording")
# a lit default: the sun 45 deg off the line of sight, behind the camera, from above the orbit plane at t = 0
# (in C: radial, along-track, normal); in the default orbit the chaser enters the Earth's shadow at t = 1203 s
# (phase angle 46 deg at t = 0, 12 deg at 600 s): longer runs of the default scenario skip the frames in shadow
DEFAULT_SUN_C0 = (0.7, -0.7, 0.15)
# the filter's gate lockout (one ungated update after N all-rejected steps) is off in the loop: it re-acquires
# by inflating the covariance instead (LoopConfig.reacquire_*)
NO_LOCKOUT = 1_000_000
# the loop's filter settings under the scenario's [filter] table: the gate, adaptive R that only ever raises R
# above the detector's (inflated) covariance (lower bound 1: the covariance matching would otherwise undo
# LoopConfig.r_inflation), no lockout
LOOP_FILTER = {"adaptive_r": True, "adaptive_r_bounds": (1.0, 100.0), "gate_lockout_steps": NO_LOCKOUT}


def default_weights_path() -> str:
    """The shipped detector weights, models/detector.safetensors (package data of envisat_pose.models, found
    with importlib.resources by perception.weights.shipped_weights_path). InputError (WeightsError) naming the
    path when the file is absent."""
    from envisat_pose.perception.weights import shipped_weights_path

    return shipped_weights_path()


@dataclass(frozen=True)
class LoopConfig:
    """How the loop uses the detector and the filter.

    roi: use the filter's predicted corners as the detector's region of interest once converged.
    roi_margin: ROI side over the predicted corners' extent (then + 6 x the prior's pixel sigma).
    roi_min_side_px: least ROI side. roi_min_corners: fewer corners found in the ROI -> the coarse pass again.
    converged_pos_sigma_m / converged_att_sigma_deg: the filter counts as converged when its prior's largest
    position sigma (m) and attitude sigma (deg, rotation angle) are below these.
    decisive_cost: before convergence an ambiguous frame is used only when the two half-turn hypotheses'
    innovation costs differ by more than this (2 ln 1000: a likelihood ratio of 1000).
    compare_half_turn: score the half-turn alternative on every frame that has one (the detector's unflagged
    wrong namings are mostly half-turns), not only on the frames it flags as ambiguous.
    prior_attitude: give the detector the predicted attitude (once converged) to settle the half-turn.
    reacquire_after_frames / reacquire_inflation: after this many consecutive frames in which the gate rejected
    every detected corner, the covariance is multiplied by reacquire_inflation before each further frame until
    a corner passes again (the gate widens step by step; the filter's own lockout, which would take one frame
    ungated, is set off for the loop: a weak detector can give ten wrong frames in a row).
    r_inflation: the detector's covariance times this is the filter's R. Its errors are correlated from frame
    to frame (the same corner seen from nearly the same pose): a filter that takes them as independent averages
    them too long and becomes over-confident (measured: NEES ~10x its 12 dof with the calibrated covariance).
    threads: torch CPU threads per run. jpeg_quality: of the images in the recording (run 0 only).
    """

    roi: bool = True
    roi_margin: float = 1.4
    roi_min_side_px: int = 64
    roi_min_corners: int = 4
    converged_pos_sigma_m: float = 0.2
    converged_att_sigma_deg: float = 2.0
    decisive_cost: float = 13.8
    compare_half_turn: bool = True
    prior_attitude: bool = True
    reacquire_after_frames: int = 5
    reacquire_inflation: float = 2.0
    r_inflation: float = 4.0
    threads: int = 1
    jpeg_quality: int = 80

    def validate(self, prefix: str = "loop") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.roi_margin >= 1.0, f"{p}roi_margin", self.roi_margin, "a factor >= 1")
        check(16 <= self.roi_min_side_px <= 4096, f"{p}roi_min_side_px", self.roi_min_side_px, "a side in [16, 4096] px")
        check(1 <= self.roi_min_corners <= 8, f"{p}roi_min_corners", self.roi_min_corners, "1 to 8 corners")
        check(self.converged_pos_sigma_m > 0, f"{p}converged_pos_sigma_m", self.converged_pos_sigma_m, "a positive sigma in m")
        check(self.converged_att_sigma_deg > 0, f"{p}converged_att_sigma_deg", self.converged_att_sigma_deg,
              "a positive sigma in deg")
        check(self.decisive_cost >= 0, f"{p}decisive_cost", self.decisive_cost, "a non-negative cost")
        check(self.reacquire_after_frames >= 1, f"{p}reacquire_after_frames", self.reacquire_after_frames,
              "at least 1 frame")
        check(self.reacquire_inflation >= 1.0, f"{p}reacquire_inflation", self.reacquire_inflation, "a factor >= 1")
        check(self.r_inflation >= 1.0, f"{p}r_inflation", self.r_inflation, "a factor >= 1")
        check(1 <= self.threads <= 256, f"{p}threads", self.threads, "1 to 256 threads")
        check(1 <= self.jpeg_quality <= 100, f"{p}jpeg_quality", self.jpeg_quality, "a JPEG quality in [1, 100]")


def _image_defaults() -> "GenerateConfig":
    from envisat_pose.datagen.factory import GenerateConfig

    return GenerateConfig(mode="sequence", num_images=1, shard_size=1, write_mask=False, write_depth=False)


@dataclass(frozen=True)
class RunConfig:
    """One `envisat run` job. scenario: named truth; duration_s: simulated time (the CLI starts from the
    scenario's); rate_hz: camera and filter rate;
    runs: closed loops on the same truth; workers: processes for them; seed: the truth's random attitude, every
    run's initial error and camera noise; weights: detector weights file. image: the camera frames, as the image
    factory's sequence mode makes them (datagen.factory.GenerateConfig: corruption, appearance, lighting, sun_dir
    in N; its mode, scenario, seed, num_images and frame_dt_s are set from the fields above; sun_dir None: the
    scenario's [eclipse] sun, else DEFAULT_SUN_C0 at t = 0). filter: the UKF (the scenario's [filter] table
    under the file and the flags; adaptive R on). loop: LoopConfig."""

    scenario: str = "default"
    duration_s: float = 600.0
    rate_hz: float = 1.0
    runs: int = 1
    workers: int = 1
    seed: int = 0
    weights: str = ""
    image: "GenerateConfig" = field(default_factory=_image_defaults)
    filter: FilterConfig = field(default_factory=lambda: FilterConfig(**LOOP_FILTER))
    loop: LoopConfig = field(default_factory=LoopConfig)

    def validate(self, prefix: str = "") -> None:
        from envisat_pose.geometry import load_camera

        check(self.duration_s > 0, "duration_s", self.duration_s, "a positive duration in s")
        check(0.0 < self.rate_hz <= 10.0, "rate_hz", self.rate_hz, "a rate in (0, 10] Hz")
        check(self.duration_s * self.rate_hz <= 200_000, "duration_s", self.duration_s,
              "at most 200000 frames (duration_s x rate_hz)")
        check(1 <= self.runs <= 1000, "runs", self.runs, "1 to 1000 runs")
        check(1 <= self.workers <= 256, "workers", self.workers, "1 to 256 processes")
        check(0 <= self.seed < 2**63, "seed", self.seed, "a non-negative integer seed")
        cam = load_camera()
        check(self.image.resolution_px == cam.width_px == cam.height_px, "image.resolution_px",
              self.image.resolution_px, f"the camera's {cam.width_px} px (models/envisat.xml, camera chaser_cam): "
              "the filter's pixel model and the detector's training use it")


def _stage_types() -> None:
    """Make the annotation "GenerateConfig" resolvable (typing.get_type_hints reads this module's globals): the
    image factory's config is a stage's type, imported when a run is configured, not when the CLI starts."""
    from envisat_pose.datagen.factory import GenerateConfig

    globals()["GenerateConfig"] = GenerateConfig


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="the online closed loop: MuJoCo truth -> rendered camera frames -> corner detector -> UKF",
        description="Run the closed loop on a named scenario: the MuJoCo truth advances, MuJoCo renders the chaser "
        "camera with the space-camera model at the filter rate, the corner detector names the corners (in the "
        "filter's predicted region of interest once it has converged) and the UKF takes them as pixel "
        "measurements with the detector's covariance. Writes est.npz, det.npz, truth.npz, errors.png, "
        "run.config.toml, summary.json and recording.rrd into --out (`envisat view RUN_DIR`).",
    )
    add_run_arguments(p)
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="output folder (created; files are replaced)")
    p.set_defaults(func=run_cli)


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="default", help="named scenario (`envisat scenarios` lists them)")
    p.add_argument("--duration-s", type=float, help="simulated time, s (default: the scenario's)")
    p.add_argument("--config", metavar="FILE.toml", help="run config (sections image, filter, loop; top-level keys)")
    p.add_argument("--weights", metavar="W.safetensors",
                   help="detector weights (default: the shipped models/detector.safetensors)")
    p.add_argument("--runs", type=int, help="closed loops on the same truth (initial error, camera noise; default 1)")
    p.add_argument("--workers", type=int, help="processes for --runs (default: min(runs, CPU cores))")
    p.add_argument("--seed", type=int, help="root seed (default 0)")
    p.add_argument("--no-roi", action="store_true", help="always run the detector's coarse pass (no region of interest)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def resolve_config(args: argparse.Namespace) -> RunConfig:
    """Defaults, then the scenario's [filter] table, then --config, then the flags; validated before any work."""
    from envisat_pose.app.scenarios import job_defaults

    _stage_types()
    defaults = job_defaults(args.scenario)  # unknown names fail here with the known ones
    data: dict = {"scenario": args.scenario, "filter": {**LOOP_FILTER, **defaults.get("filter", {})}}
    if "duration_s" in defaults:  # the scenario's duration unless the file or --duration-s say otherwise
        data["duration_s"] = defaults["duration_s"]
    if "rate_hz" in defaults.get("measurement", {}):  # the camera runs at the scenario's measurement rate
        data["rate_hz"] = defaults["measurement"]["rate_hz"]
    if args.config:
        data = deep_update(data, load_toml(args.config))
    flags = {
        "scenario": args.scenario,  # the flag names the truth whose [filter] table is above
        "duration_s": args.duration_s,
        "runs": args.runs,
        "seed": args.seed,
        "weights": args.weights,
        "workers": args.workers,
        "loop.roi": False if args.no_roi else None,
    }
    for key, value in flags.items():
        if value is not None:
            data = set_dotted(data, key, value)
    if "workers" not in data:  # default: one process per run, at most one per core
        runs = data.get("runs", 1)
        data["workers"] = max(1, min(runs if isinstance(runs, int) else 1, os.cpu_count() or 1))
    if not data.get("weights"):
        data["weights"] = default_weights_path()
    cfg = from_dict(RunConfig, data)
    if not os.path.isfile(cfg.weights):
        raise InputError(f"--weights {cfg.weights!r}: no such file")
    return finish_config(cfg)


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
    _stage_types()
    return from_dict(RunConfig, json.loads(text))


# ---------------------------------------------------------------------------------------------------------
# The truth and what the chaser knows of its own orbit


def simulate_truth(cfg: RunConfig, progress: bool = False):
    """The MuJoCo truth of the run on the frame grid (datagen.truth.simulate, as `envisat simulate`)."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate

    scen = scenario_config(cfg.scenario, duration_s=cfg.duration_s, dt_s=1.0 / cfg.rate_hz, seed=cfg.seed)
    return simulate(scen, progress=progress)


def sun_and_shadow(cfg: RunConfig, truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: sun_dir_C (N, 3) unit, eclipse (N,) bool (the chaser in the Earth's cylindrical shadow),
    nadir_C (N, 3) the Earth's centre from the chaser, m."""
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import ScenarioConfig, in_earth_shadow

    scen = from_dict(ScenarioConfig, truth.config)
    orb = chaser_orbit(scen.orbit, truth.t_s)
    sun_N = np.asarray(cfg.image.sun_dir, dtype=float)
    sun_N = sun_N / np.linalg.norm(sun_N)
    sun_C = np.einsum("nji,j->ni", orb.R_N_from_C, sun_N)
    eclipse = in_earth_shadow(orb.r_N_m, sun_N)
    nadir_C = np.zeros((len(truth.t_s), 3))
    nadir_C[:, 0] = -orb.r_m
    return sun_C, eclipse, nadir_C


# ---------------------------------------------------------------------------------------------------------
# One frame of the loop


@dataclass
class FrameInput:
    """What the loop has at frame k: t_s, the chaser's orbit (4,), the camera image (H, W) uint8 or None in
    eclipse (skipped)."""

    t_s: float
    chaser: np.ndarray
    image: np.ndarray | None


@dataclass
class FrameRecord:
    """What one frame did: the detection (camera px), the region of interest, whether the coarse pass had to
    run after the ROI, which naming the filter took (0 the detector's, 1 the half-turn, -1 none), skipped
    (eclipse), converged (the prior), the time of detection and filtering, s."""

    detection: object | None
    roi_px: np.ndarray | None
    coarse_fallback: bool
    hypothesis: int
    skipped: bool
    converged: bool
    costs: tuple[float, float]
    detect_s: float = 0.0
    filter_s: float = 0.0


def prior_sigmas(cov: np.ndarray) -> tuple[float, float]:
    """(largest position sigma, m; largest attitude sigma, deg) of one run's covariance (12, 12). The MRP
    sigma is a rotation angle of 4 sigma_p rad (small angles)."""
    pos = float(np.sqrt(np.max(np.linalg.eigvalsh(cov[0:3, 0:3]))))
    att = float(np.degrees(4.0 * np.sqrt(np.max(np.linalg.eigvalsh(cov[6:9, 6:9])))))
    return pos, att


def predicted_roi(mean: np.ndarray, cov: np.ndarray, camera, lcfg: LoopConfig) -> np.ndarray | None:
    """The detector's region of interest (x0, y0, side) px from a prior (12,), (12, 12): the 8 predicted corners
    through the camera, their extent x roi_margin plus 6 x the prior's position sigma in pixels; None when no
    predicted corner is in the image."""
    from envisat_pose.filtering.measurements import measure

    uv = measure(mean[None], "pixels", camera)[0]  # (8, 2)
    w, h = camera.width_px, camera.height_px
    inside = np.isfinite(uv).all(-1) & (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) \
        & (uv[:, 1] < h - 0.5)
    if not inside.any():
        return None
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    pos_sigma_m, _ = prior_sigmas(cov)
    sigma_px = camera.f_px * pos_sigma_m / max(float(np.linalg.norm(mean[0:3])), 1.0)
    side = max(float(np.max(hi - lo)) * lcfg.roi_margin + 6.0 * sigma_px, float(lcfg.roi_min_side_px))
    side = int(np.ceil(min(side, 2.0 * max(w, h))))
    x0, y0 = np.round((lo + hi) / 2 - side / 2).astype(int)
    return np.array([x0, y0, side], dtype=np.int64)


def half_turn_measurement(fd) -> tuple[np.ndarray, np.ndarray] | None:
    """The half-turn naming of a detection as (corners_px (8, 2), cov_px (8, 2, 2)), None when it names nothing.
    Its corners are the detector's candidates renamed A<->C, B<->D, E<->G, F<->H: a corner takes the covariance of
    the candidate it is (the detector's corner HALF_TURN[i]), else the median covariance of the frame."""
    alt = np.asarray(fd.alt_corners_px, dtype=float)
    ok = np.isfinite(alt).all(-1)
    if not ok.any():
        return None
    cov = np.asarray(fd.cov_px, dtype=float)
    cov_ok = np.isfinite(cov).all((-1, -2))
    fallback = np.median(cov[cov_ok], axis=0) if cov_ok.any() else np.eye(2) * 4.0
    src = HALF_TURN
    same = cov_ok[src] & np.all(np.abs(np.asarray(fd.corners_px)[src] - alt) < 1e-6, axis=-1)
    alt_cov = np.where(same[:, None, None], cov[src], fallback)
    return np.where(ok[:, None], alt, np.nan), np.where(ok[:, None, None], alt_cov, np.nan)


def innovation_cost(state, setup) -> float:
    """~ -2 log likelihood of a hypothesis after its filter step (one run): its NIS plus the gate's bound for
    every corner the gate rejected or the visibility check dropped."""
    thr = setup.gate_threshold if setup.gate_threshold is not None else 23.0
    return float(state.nis[0] + thr * (state.rejected[0] + state.dropped[0]))


def loop_step(state, frame: FrameInput, detector, setup, lcfg: LoopConfig):
    """One frame of the closed loop for one run: returns (new FilterState, FrameRecord).

    `detector` is anything with perception's `detect(image_u8, K, roi_px=, prior_R_cam_from_target=)` returning
    a FrameDetection. Eclipse (image None) and frames without a usable detection are predict-only steps."""
    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.filtering.estimator import Measurement, filter_step, predict_to

    t0 = time.perf_counter()
    camera = setup.camera
    if state.locked[0] >= lcfg.reacquire_after_frames:  # lost: widen the gate step by step
        state = dataclasses.replace(state, cov=state.cov * lcfg.reacquire_inflation)
    prior = predict_to(state, frame.t_s, setup)
    empty = Measurement(frame.t_s, frame.chaser, np.full((1, 8, 2), np.nan), np.zeros((1, 8), bool),
                        np.broadcast_to(np.eye(2), (1, 8, 2, 2)))
    pos_sig, att_sig = prior_sigmas(prior[1][0])
    converged = bool(pos_sig < lcfg.converged_pos_sigma_m and att_sig < lcfg.converged_att_sigma_deg)
    t_filter = time.perf_counter() - t0
    if frame.image is None:
        t1 = time.perf_counter()
        new = filter_step(state, empty, setup, prior=prior)
        return new, FrameRecord(None, None, False, -1, True, converged, (np.nan, np.nan),
                                filter_s=t_filter + time.perf_counter() - t1)
    # detection: in the predicted region of interest once converged, else (or if it finds too little) coarse
    t1 = time.perf_counter()
    roi = predicted_roi(prior[0][0], prior[1][0], camera, lcfg) if (lcfg.roi and converged) else None
    R_prior = None
    if converged and lcfg.prior_attitude:
        R_prior = camera.R_K_from_C @ mrp_to_dcm(prior[0][0, 6:9]).T  # R_K_from_T = R_K_from_C Gamma^T
    fd = detector.detect(frame.image, camera.K, roi_px=roi, prior_R_cam_from_target=R_prior)
    fallback = False
    if roi is not None and int(np.sum(fd.visible)) < lcfg.roi_min_corners:
        fd = detector.detect(frame.image, camera.K, roi_px=None, prior_R_cam_from_target=R_prior)
        fallback = True
    t_detect = time.perf_counter() - t1
    # the filter: the detector's naming and its half-turn, scored on the same prior
    t2 = time.perf_counter()
    z = np.asarray(fd.corners_px, dtype=float)
    found = np.asarray(fd.visible, dtype=bool) & np.isfinite(z).all(-1) \
        & np.isfinite(np.asarray(fd.cov_px, dtype=float)).all((-1, -2))
    hyps = []  # (label: 0 the detector's naming, 1 its half-turn; corners; covariances)
    if found.any():
        hyps.append((0, np.where(found[:, None], z, np.nan), np.where(found[:, None, None], fd.cov_px, np.nan)))
    alt = half_turn_measurement(fd) if (bool(fd.ambiguous) or lcfg.compare_half_turn) else None
    if alt is not None:
        hyps.append((1, *alt))
    costs = [np.nan, np.nan]
    choice, new = -1, None
    if hyps:
        steps = {}
        for label, zc, cc in hyps:
            mask = np.isfinite(zc).all(-1)
            cov = np.where(mask[:, None, None], cc, np.eye(2))
            cov = 0.5 * (cov + np.swapaxes(cov, -1, -2)) * lcfg.r_inflation
            steps[label] = filter_step(state, Measurement(frame.t_s, frame.chaser, np.nan_to_num(zc)[None],
                                                          mask[None], cov[None]), setup, prior=prior)
            costs[label] = innovation_cost(steps[label], setup)
        best = min(steps, key=lambda label: costs[label])
        # before convergence an ambiguous frame commits only when the prior decides it clearly
        undecided = len(steps) == 2 and bool(fd.ambiguous) and not converged \
            and abs(costs[1] - costs[0]) < lcfg.decisive_cost
        if not undecided:
            choice, new = best, steps[best]
    if new is None:
        new = filter_step(state, empty, setup, prior=prior)
    t_filter += time.perf_counter() - t2
    return new, FrameRecord(fd, roi, fallback, choice, False, converged, (float(costs[0]), float(costs[1])),
                            detect_s=t_detect, filter_s=t_filter)


# ---------------------------------------------------------------------------------------------------------
# One closed-loop run (a runner task)


def closed_loop_task(cfg_json: str, run: int, truth_path: str, keep_images: bool, progress: bool,
                     sim_s_per_frame: float) -> dict:
    """Run closed loop `run` over the truth in truth_path; returns its arrays (plain data for the runner).

    Keys: x_hat (T, 12), P (T, 12, 12), n_meas, nis, nis_dof, rejected (T,), diverged, repaired; the detections
    corners_px (T, 8, 2), cov_px (T, 8, 2, 2), confidence (T, 8), visible (T, 8), alt_corners_px,
    alt_probability (T,), ambiguous (T,), crop_px (T, 3); the loop's roi_px (T, 3) (NaN without), roi_used,
    coarse_fallback, skipped, converged (T,) bool, hypothesis (T,) int, cost (T, 2); timing_s (T, 6) s per STAGES;
    jpeg: list of T bytes (b'' for a skipped frame) when keep_images."""
    import cv2

    from envisat_pose.contracts import TruthTrajectory
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.datagen.factory import draw_corruption_params, sample_seed, unit, with_look
    from envisat_pose.datagen.render import View, shared_renderer
    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.filtering.estimator import chaser_states, init_state, make_setup
    from envisat_pose.geometry import load_camera
    from envisat_pose.perception.detect import load_detector
    import torch

    cfg = config_from_json(cfg_json)
    lcfg, gcfg = cfg.loop, cfg.image
    torch.set_num_threads(lcfg.threads)
    cv2.setNumThreads(1)
    truth = TruthTrajectory.load(truth_path)
    from envisat_pose.app.estimate import truth_model

    mu, gg = truth_model(truth, truth_path)
    sun_C, eclipse, nadir_C = sun_and_shadow(cfg, truth)
    chaser = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad,
                           truth.chaser_thetadot_rad_s)
    camera = load_camera()
    setup = make_setup(cfg.filter, "pixels", camera, mu_m3_s2=mu, gravity_gradient=gg)
    renderer = shared_renderer(gcfg.resolution_px, gcfg.shadows,
                               gcfg.appearance.texture_set_size if gcfg.appearance_on else 0,
                               gcfg.appearance.texture_seed)
    detector = load_detector(cfg.weights)
    rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(run,)))
    P0 = cfg.filter.P0
    x0_hat = truth.x[0] + np.linalg.cholesky(P0) @ rng.standard_normal(12)  # as make_run_inputs draws it
    state = init_state(x0_hat[None], P0, truth.t_s[0], chaser[0], cfg.filter)
    look_seed = sample_seed(cfg.seed, 0, 0)  # one look for the whole sequence: the same target in every run
    T = len(truth.t_s)
    out = {k: np.zeros((T,), dtype=np.int64) for k in ("n_meas", "nis_dof", "rejected", "hypothesis")}
    out.update({"x_hat": np.empty((T, 12)), "P": np.empty((T, 12, 12)), "nis": np.zeros(T),
                "corners_px": np.full((T, 8, 2), np.nan), "cov_px": np.full((T, 8, 2, 2), np.nan),
                "confidence": np.zeros((T, 8)), "visible": np.zeros((T, 8), bool),
                "alt_corners_px": np.full((T, 8, 2), np.nan), "alt_probability": np.zeros(T),
                "ambiguous": np.zeros(T, bool), "crop_px": np.zeros((T, 3)), "roi_px": np.full((T, 3), np.nan),
                "roi_used": np.zeros(T, bool), "coarse_fallback": np.zeros(T, bool), "skipped": np.zeros(T, bool),
                "converged": np.zeros(T, bool), "cost": np.full((T, 2), np.nan),
                "timing_s": np.zeros((T, len(STAGES)))})
    jpegs: list[bytes] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, unit="frame", desc=f"closed loop (run {run})", mininterval=0.5)
    for k in range(T):
        x = truth.x[k]
        image = None
        t_render = t_camera = 0.0
        if not eclipse[k]:
            t0 = time.perf_counter()
            view = View(x[0:3], mrp_to_dcm(x[6:9]).T, sun_C[k], unit(nadir_C[k]), float(np.linalg.norm(nadir_C[k])),
                        earth_backdrop=gcfg.earth_probability > 0)
            view, _ = with_look(gcfg, view, {}, look_seed)
            rendered = renderer.render(view)
            t_render = time.perf_counter() - t0
            t0 = time.perf_counter()
            frame_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(run, 1, k)))
            params = draw_corruption_params(gcfg, rendered, x, renderer.K[0, 0], renderer.target_boxes, frame_rng)
            image = apply_corruption(rendered.gray_u8, params)
            t_camera = time.perf_counter() - t0
        state, rec = loop_step(state, FrameInput(float(truth.t_s[k]), chaser[k], image), detector, setup, lcfg)
        t0 = time.perf_counter()
        if keep_images:
            ok, buf = (False, None) if image is None else cv2.imencode(
                ".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, lcfg.jpeg_quality])
            jpegs.append(buf.tobytes() if ok else b"")
        _store(out, k, state, rec)
        out["timing_s"][k] = (sim_s_per_frame, t_render, t_camera, rec.detect_s, rec.filter_s, time.perf_counter() - t0)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    out["diverged"] = bool(state.diverged[0])
    out["repaired"] = int(state.repaired[0])
    out["x0_hat"] = x0_hat
    if keep_images:
        out["jpeg"] = jpegs
    return out


def _store(out: dict, k: int, state, rec: FrameRecord) -> None:
    out["x_hat"][k], out["P"][k] = state.mean[0], state.cov[0]
    out["n_meas"][k], out["nis"][k], out["nis_dof"][k] = state.n_meas[0], state.nis[0], state.dof[0]
    out["rejected"][k] = state.rejected[0]
    out["hypothesis"][k] = rec.hypothesis
    out["skipped"][k], out["converged"][k], out["coarse_fallback"][k] = rec.skipped, rec.converged, rec.coarse_fallback
    out["cost"][k] = rec.costs
    if rec.roi_px is not None:
        out["roi_px"][k], out["roi_used"][k] = rec.roi_px, True
    fd = rec.detection
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


# ---------------------------------------------------------------------------------------------------------
# The job: truth, runs, outputs


def run_closed_loop(cfg: RunConfig, out_dir: str, progress: bool = True) -> dict:
    """The whole job into out_dir; returns the summary dict (also written as summary.json)."""
    from envisat_pose.contracts import Detections, Estimates
    from envisat_pose.filtering.estimator import nees_divergence
    from envisat_pose.io import atomic_write_text, save_npz
    from envisat_pose.runner import RunnerConfig, cpu_share, run_tasks

    os.makedirs(out_dir, exist_ok=True)
    paths = output_paths(out_dir)
    wall0 = time.perf_counter()
    t0 = time.perf_counter()
    truth = simulate_truth(cfg, progress=False)
    sim_s = time.perf_counter() - t0
    truth.save(paths["truth"])
    T = len(truth.t_s)
    cfg_json = json.dumps(to_dict(cfg), sort_keys=True)
    workers = min(cfg.workers, cfg.runs)
    runner = RunnerConfig("local", workers, env={"LP_NUM_THREADS": str(cpu_share(workers))})
    if workers == 1:
        os.environ.setdefault("LP_NUM_THREADS", str(cpu_share(1)))
    tasks = [(cfg_json, r, os.path.abspath(paths["truth"]), r == 0, progress and cfg.runs == 1, sim_s / T)
             for r in range(cfg.runs)]
    results: list[dict | None] = [None] * cfg.runs
    bar = None
    if progress and cfg.runs > 1:
        from tqdm import tqdm

        bar = tqdm(total=cfg.runs, unit="run", desc=f"closed loop ({workers} workers)")
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
    diverged = np.array([r["diverged"] for r in results]) | nees_divergence(truth.x[None], x_hat, P, cfg.filter)
    config_json = json.dumps({"run": to_dict(cfg), "truth_source": {"scenario": cfg.scenario},
                              "truth_config": truth.config}, sort_keys=True)
    est = Estimates(t_s=truth.t_s, x_true=x_true, x_hat=x_hat, P=P,
                    n_meas=np.stack([r["n_meas"] for r in results]), nis=np.stack([r["nis"] for r in results]),
                    nis_dof=np.stack([r["nis_dof"] for r in results]), diverged=diverged, config_json=config_json)
    est.save(paths["est"])
    r0 = results[0]
    det = {k: r0[k] for k in ("corners_px", "cov_px", "confidence", "visible", "alt_corners_px", "alt_probability",
                              "ambiguous", "crop_px", "roi_px", "roi_used", "coarse_fallback", "skipped",
                              "converged", "hypothesis", "cost")}
    det["t_s"] = truth.t_s
    det["key"] = np.array([f"frame-{k:06d}" for k in range(T)])
    det_cfg = json.dumps({"weights": cfg.weights, "run": 0, "scenario": cfg.scenario, "seed": cfg.seed,
                          "roi": cfg.loop.roi}, sort_keys=True)
    Detections.validated({**det, "config_json": det_cfg}, paths["det"])
    save_npz(paths["det"], {**det, "config_json": np.array(det_cfg)})
    atomic_write_text(paths["config"], "# envisat run: the full validated config of this run\n" + to_toml(to_dict(cfg)))
    from envisat_pose.analysis.plots import plot_estimate

    plot_estimate(truth.t_s, x_true, x_hat, P, paths["plot"],
                  title=f"closed loop, scenario {cfg.scenario!r}, {R} run(s), seed {cfg.seed}")
    t_rec = time.perf_counter()
    from envisat_pose.analysis.recording import write_closed_loop_recording

    write_closed_loop_recording(paths["recording"], est, truth, r0["jpeg"], r0["corners_px"], r0["visible"],
                                r0["roi_px"])
    rec_s = time.perf_counter() - t_rec
    summary = make_summary(cfg, truth, est, results, sim_s, loop_wall_s, time.perf_counter() - wall0,
                           os.path.getsize(paths["recording"]), rec_s)
    atomic_write_text(paths["summary"], json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return summary


def output_paths(out_dir: str) -> dict[str, str]:
    names = {"truth": "truth.npz", "est": "est.npz", "det": "det.npz", "plot": "errors.png",
             "config": "run.config.toml", "summary": "summary.json", "recording": "recording.rrd"}
    return {k: os.path.join(out_dir, v) for k, v in names.items()}


def error_table(t_s: np.ndarray, x_true: np.ndarray, x_hat: np.ndarray, after_s: float) -> dict:
    """Errors of R runs (R, T, 12) after after_s: RMS and final position (m), attitude (deg), rate (deg/s)."""
    from envisat_pose.attitude import mrp_error_angle_rad

    late = t_s >= after_s
    if not late.any():
        late = np.ones_like(t_s, dtype=bool)
    pos = np.linalg.norm(x_hat[..., 0:3] - x_true[..., 0:3], axis=-1)
    ang = np.degrees(mrp_error_angle_rad(x_hat[..., 6:9], x_true[..., 6:9]))
    rate = np.degrees(np.linalg.norm(x_hat[..., 9:12] - x_true[..., 9:12], axis=-1))
    vel = np.linalg.norm(x_hat[..., 3:6] - x_true[..., 3:6], axis=-1)

    def stats(e):
        return {"rms_after": float(np.sqrt(np.mean(e[:, late] ** 2))), "final": float(np.sqrt(np.mean(e[:, -1] ** 2))),
                "max_after": float(np.max(e[:, late]))}

    return {"after_s": float(t_s[late][0]), "position_m": stats(pos), "velocity_m_s": stats(vel),
            "attitude_deg": stats(ang), "rate_deg_s": stats(rate)}


def make_summary(cfg: RunConfig, truth, est, results: list[dict], sim_s: float, loop_wall_s: float,
                 total_wall_s: float, rrd_bytes: int, rec_s: float) -> dict:
    T = len(truth.t_s)
    timing = np.stack([r["timing_s"] for r in results])  # (R, T, stages)
    per_frame_ms = {s: float(1000 * timing[..., i].mean()) for i, s in enumerate(STAGES)}
    r0 = results[0]
    frames_sum = float(timing.sum(axis=-1).mean(axis=0).sum())  # one run's wall time in the stages
    sim_time_s = float(truth.t_s[-1] - truth.t_s[0]) + 1.0 / cfg.rate_hz
    return {
        "scenario": cfg.scenario, "runs": cfg.runs, "frames": T, "duration_s": cfg.duration_s,
        "roi": cfg.loop.roi, "weights": cfg.weights,
        "errors": error_table(truth.t_s, est.x_true, est.x_hat, min(300.0, truth.t_s[-1] / 2)),
        "diverged_runs": int(est.diverged.sum()),
        "timing_ms_per_frame": per_frame_ms,
        "real_time_factor_one_run": sim_time_s / max(frames_sum, 1e-9),
        "real_time_factor_job": sim_time_s * cfg.runs / max(loop_wall_s, 1e-9),
        "wall_s": {"truth_simulation": sim_s, "loops": loop_wall_s, "recording": rec_s, "total": total_wall_s},
        "run0": {"frames_skipped_eclipse": int(r0["skipped"].sum()), "frames_roi": int(r0["roi_used"].sum()),
                 "frames_coarse_fallback": int(r0["coarse_fallback"].sum()),
                 "frames_ambiguous": int(r0["ambiguous"].sum()),
                 "frames_half_turn_taken": int((r0["hypothesis"] == 1).sum()),
                 "frames_not_used": int(((r0["hypothesis"] < 0) & ~r0["skipped"]).sum()),
                 "frames_without_detection": int(((r0["visible"].sum(-1) == 0) & ~r0["skipped"]).sum()),
                 "first_converged_s": float(truth.t_s[np.argmax(r0["converged"])]) if r0["converged"].any() else None},
        "recording_bytes": rrd_bytes,
    }


def print_table(summary: dict) -> None:
    e = summary["errors"]
    rows = (("position", "m", e["position_m"]), ("velocity", "m/s", e["velocity_m_s"]),
            ("attitude", "deg", e["attitude_deg"]), ("rate", "deg/s", e["rate_deg_s"]))
    print(f"errors over {summary['runs']} run(s) (RMS over runs), from t = {e['after_s']:.0f} s:")
    print(f"  {'':10s} {'unit':6s} {'RMS after':>12s} {'max after':>12s} {'final':>12s}")
    for name, unit, s in rows:
        print(f"  {name:10s} {unit:6s} {s['rms_after']:12.5f} {s['max_after']:12.5f} {s['final']:12.5f}")
    t = summary["timing_ms_per_frame"]
    print("per frame (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items())
          + f"; real-time factor {summary['real_time_factor_one_run']:.1f}x (one run), "
          f"diverged runs {summary['diverged_runs']}/{summary['runs']}")


def run_cli(args: argparse.Namespace) -> int:
    from envisat_pose.datagen.factory import make_out_dir, prepare_out_dir

    cfg = resolve_config(args)
    prepare_out_dir(args.out)
    make_out_dir(args.out)
    summary = run_closed_loop(cfg, args.out, progress=not args.quiet)
    print_table(summary)
    print(f"wrote {args.out}: est.npz, det.npz, truth.npz, errors.png, run.config.toml, summary.json, "
          f"recording.rrd ({summary['recording_bytes'] / 2**20:.1f} MiB; `envisat view {args.out}`)")
    return 0
