"""The pipeline of `envisat estimate`: the batched UKF over R Monte Carlo runs of one MuJoCo truth, written as
est.npz (the Estimates contract) with its config next to it.

The truth comes from a truth file (written by `envisat simulate`, read as the core's TruthTrajectory contract
without importing the simulator) or is simulated for a named scenario by the MuJoCo truth simulator
(datagen.truth.simulate_truth). Measurements are synthesized from the truth's own arrays (MuJoCo's corner sites and
their projection through MuJoCo's camera), never from the filter's model; the filter's model takes the truth's
mu and gravity-gradient switch from its config (pipelines/tracking/onboard.py, `onboard_physics`) and its keypoints
and inertia from the truth's target file (config target.file, `truth_target`: any target). A named scenario with
an [eclipse] table adds the Earth's-shadow outages along its truth (`eclipse_outages`, `with_outages`; the campaigns use them too).
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass

import numpy as np

from envisat_pose.config import Config, ConfigError, InputError, check, config_arg, path_arg, rrd_arg, to_dict, to_toml
from envisat_pose.contracts import Estimates, TruthTrajectory
from envisat_pose.datagen.scenario import (
    eclipse_windows,
    scenario_config,
    scenario_dict,
    scenario_eclipse,
    scenario_of_truth,
)
from envisat_pose.filtering.estimator import (
    FilterConfig,
    chaser_states,
    diverged_against_truth,
    nees,
    run_filter,
    unjudged_runs,
)
from envisat_pose.filtering.filter_config import SIGMA_MIN
from envisat_pose.filtering.montecarlo import MeasurementConfig, filter_stride, make_run_inputs, truth_measurements
from envisat_pose.geometry import load_geometry
from envisat_pose.io import atomic_write_text, open_npz, sha256_file, staged_folder
from envisat_pose.named_scenarios import check_name
from envisat_pose.out_dirs import check_out_file, make_out_file_dirs, own_side_files
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.campaigns.observability import (
    warn_if_never_updated,
    warn_if_unfixed_start,
    warn_outages_outside,
)
from envisat_pose.pipelines.common.job_defaults import fill_from_scenario, layered_job
from envisat_pose.pipelines.tracking.onboard import onboard_physics
from envisat_pose.provenance import source_line
from envisat_pose.target import DEFAULT_TARGET, Target, is_default_file, load_target, resolve_target_path
from envisat_pose.target_assets import target_sha256

MAX_OUTPUT_BYTES = 8 * 2**30  # P alone is R * T * 144 * 8 bytes


@dataclass(frozen=True)
class EstimateConfig(Config):
    """One `envisat estimate` job, complete and validated when built: `EstimateConfig(scenario=NAME, runs=4)` is
    the config of `envisat estimate --scenario NAME --runs 4` (pipelines.jobs.resolve_job adds a config file and
    flags). scenario: the named scenario whose truth is simulated (None: a truth file's job, which takes the
    scenario the truth records where measurement and filter are the plain defaults, as the verb does:
    with_recorded_scenario; run_estimate takes it as its scenario when given neither a truth file nor a scenario);
    measurement and filter left None take the scenario's [measurement] and [filter] tables over the classes'
    defaults (job_defaults.fill_from_scenario; no scenario: the defaults); runs and the root seed. init_error_scale:
    each run's initial error is drawn from N(0, init_error_scale^2 P0) while the filter is told P0 (1: a consistent
    start; 3: a filter whose P0 is three times too tight).

    Run r draws its initial error and noise from SeedSequence(seed).spawn(runs)[r]; with a scenario the
    truth's random initial attitude comes from the same seed.
    """

    scenario: str | None = None
    measurement: MeasurementConfig | None = None
    filter: FilterConfig | None = None
    runs: int = 1
    seed: int = 0
    init_error_scale: float = 1.0

    def __post_init__(self) -> None:
        fill_from_scenario(self, "estimate", ESTIMATE_FALLBACKS)
        super().__post_init__()

    @classmethod
    def from_scenario(cls, name: str | None = None, config_path: str | None = None, overrides: dict | None = None,
                      **fields) -> "EstimateConfig":
        """Deprecated (goes in the next release): EstimateConfig(scenario=NAME, ...), or pipelines.jobs.resolve_job
        ("estimate", NAME, config_path, overrides, ...) for a config file and dotted flags; this is the latter."""
        warnings.warn("EstimateConfig.from_scenario is deprecated and goes in the next release: use "
                      "EstimateConfig(scenario=NAME, ...) (or pipelines.jobs.resolve_job for a config file)",
                      DeprecationWarning, stacklevel=2)
        return layered_job(cls, "estimate", name, config_path, overrides, fields)

    def validate(self, prefix: str = "") -> None:
        check(1 <= self.runs <= 100_000, "runs", self.runs, "a number of runs from 1 to 100000")
        check(0 <= self.seed < 2**63, "seed", self.seed, "a non-negative integer seed")
        check_init_error_scale(self.init_error_scale, self.filter.p0_sigma)


def check_init_error_scale(scale: float, p0_sigma=(1.0,)) -> None:
    """ConfigError unless the initial errors' scale (their sigma over P0's) is in (0, 100] and keeps P0's least
    sigma at or above SIGMA_MIN, the least the filter takes (the draw factors scale^2 P0: at 1e-300 it was 0, and
    its Cholesky factor a traceback)."""
    least = SIGMA_MIN / min(p0_sigma)
    check(least <= scale <= 100.0, "init_error_scale", scale, f"a scale in [{least:.3g}, 100] of P0's sigmas (1: "
          f"the filter's own P0; the least keeps its smallest sigma, {min(p0_sigma):g}, at {SIGMA_MIN:g} or more)")


# what an estimate takes where its scenario (or a truth file's job, without one) sets nothing
ESTIMATE_FALLBACKS = {"measurement": MeasurementConfig, "filter": FilterConfig}


# ---------------------------------------------------------------- what a job takes from its truth

def truth_target(config: dict, source: str) -> Target | None:
    """The target a truth was simulated with, for the filter: None for ENVISAT (the filter's own default model:
    its corners A-H, inertia and box face test, exactly its numbers before targets existed; asked of
    envisat_pose.target, which answers it without loading MuJoCo), else its config's target.file loaded
    (envisat_pose.target.load_target). InputError naming `source` in one line when the file cannot be loaded, or
    when the truth records the file's sha256 (target.sha256: its bytes and those of the files it names) and the
    file no longer matches it (an edited target would be estimated with another body than the truth's)."""
    record = config.get("target") or {}
    given = record.get("file", DEFAULT_TARGET)
    recorded = record.get("sha256")
    if recorded is not None:
        path = resolve_target_path(given)
        try:
            digest = target_sha256(path)
        except OSError as err:
            raise InputError(f"{source}: its target file {given!r} cannot be read ({err.strerror}; the path is "
                             "as simulate was given it: give the file with `target`)") from None
        if digest != recorded:
            raise InputError(f"{source}: its target file {given!r} changed since the truth was simulated (sha256 "
                             f"{digest[:12]}..., the truth recorded {str(recorded)[:12]}...)")
    if is_default_file(given):
        return None
    try:
        # its warnings name the truth that records the file (not the flag `target`, which the user did not give)
        return load_target(given, "target.file", named=f"the target file {given!r} of {source}")
    except ConfigError as err:
        raise InputError(f"{source}: its target file cannot be used ({err})") from None


def filter_keypoints_T_m(target: Target | None) -> np.ndarray:
    """(K, 3) m: the keypoints in T the filter measures (truth_target's None: ENVISAT's corners A-H)."""
    return load_geometry().corners_T_m if target is None else target.keypoints_T_m


def check_truth_keypoints(truth, target: Target | None, source: str) -> None:
    """InputError naming `source` unless the truth's arrays hold the filter's K keypoints (the target's; None:
    ENVISAT's corners A-H)."""
    K = int(truth.corners_C_m.shape[1])
    K_model = filter_keypoints_T_m(target).shape[0]
    if K != K_model:
        where = "ENVISAT's corners" if target is None else f"its target file {target.path!r}"
        raise InputError(f"{source}: the truth holds {K} keypoints; {where} number {K_model}")


def eclipse_outages(name: str, truth_cfg) -> tuple[tuple[float, float], ...]:
    """The Earth's-shadow windows [start, end) s of a named scenario's [eclipse] table along the truth of
    truth_cfg (a datagen ScenarioConfig); () for a scenario without one."""

    eclipse = scenario_eclipse(name)
    return eclipse_windows(truth_cfg, eclipse) if eclipse is not None else ()


def with_outages(mcfg, windows: tuple[tuple[float, float], ...]):
    """A MeasurementConfig with `windows` appended to its outages, but for those inside an outage it already has
    (unchanged when none is left). So a scenario's Earth's-shadow windows are added once: a job's written config
    holds them among its outages, and its rerun (`--config`) adds them no second time."""
    import dataclasses

    new = tuple((a, b) for a, b in windows if not any(s <= a and b <= e for s, e in mcfg.outages_s))
    if not new:
        return mcfg
    return dataclasses.replace(mcfg, outages_s=tuple(mcfg.outages_s) + new)


def load_truth(cfg: EstimateConfig, truth_path: str | None = None, scenario: str | None = None,
               duration_s: float | None = None, progress: bool = False, target: str | None = None):
    """The truth trajectory: read from truth_path, or simulated by MuJoCo for the named scenario (exactly one of
    them). Returns (truth, source) with source {"truth_file": path} or {"scenario": name} (and "target": its
    file, where one was given).

    A file that is not a truth trajectory (truncated, foreign, another contract) is one InputError line.
    With a scenario its duration applies unless duration_s is given; a truth file fixes the duration. target: a
    truth file's target file where the path it records is not found from here (relative to where simulate ran):
    its sha256 must be the one the truth recorded; the truth's config then names it. With a scenario: the
    spacecraft that flies it (its [target] file replaced), as `montecarlo --target`.
    """
    if truth_path:
        if duration_s is not None:
            raise InputError("duration_s applies to a `scenario` only; the truth file (`truth_path`) fixes the "
                             "duration")
        truth = TruthTrajectory.load(truth_path, "truth_path")  # its errors name the argument (the verb's --truth)
        if target is not None:
            truth = with_target_file(truth, target, truth_path)
        onboard_physics(truth, truth_path)  # its config must name the physics the filter needs
        check_truth_keypoints(truth, truth_target(truth.config, truth_path), truth_path)  # any target: its file
        return truth, {"truth_file": truth_path}
    from envisat_pose.datagen.truth import simulate_truth

    overrides: dict = {"seed": cfg.seed}
    if target is not None:  # the scenario flown by another spacecraft, as `montecarlo --target`
        overrides["target"] = {"file": target}
    if duration_s is not None:
        overrides["duration_s"] = duration_s
    if cfg.measurement.rate_hz > 1.0:
        overrides["dt_s"] = 1.0 / cfg.measurement.rate_hz
    scenario_dict(scenario)  # unknown names fail here with the list of known ones
    scfg = scenario_config(scenario, **overrides)
    source = {"scenario": scenario} if target is None else {"scenario": scenario, "target": target}
    return simulate_truth(scfg, progress=progress), source


def truth_origin(source: dict, truth) -> str:
    """The written config's comment naming the truth it filtered, which the config's fields do not hold: the truth
    file and its sha256, or the scenario simulated and for how long (the scenario's own duration otherwise), with
    the command that remakes the job."""
    if "truth_file" in source:
        path = source["truth_file"]
        return (f"# truth: {path} (sha256 {sha256_file(path)}); `envisat estimate --truth {path} --config "
                "THIS_FILE` remakes it\n")
    name, duration = source["scenario"], float(truth.config["duration_s"])
    target = f" --target {source['target']}" if source.get("target") else ""
    return (f"# truth: scenario {name!r} simulated for {duration:g} s from this seed; `envisat estimate --scenario "
            f"{name}{target} --duration-s {duration:g} --config THIS_FILE` remakes it\n")


def with_target_file(truth, target: str, source: str):
    """truth with its config's target.file set to `target`, the same file the truth recorded (its sha256);
    InputError naming `target` otherwise."""
    import dataclasses

    config = truth.config
    record = config.get("target") or {}
    path = resolve_target_path(target)
    if not os.path.isfile(path):
        raise InputError(f"target {target!r}: no such file; expected the target file of {source}")
    digest = target_sha256(path)
    if record.get("sha256") not in (None, digest):
        raise InputError(f"target {target!r}: not the target file of {source} (sha256 {digest[:12]}..., the truth "
                         f"recorded {str(record['sha256'])[:12]}... for {record.get('file')!r})")
    config["target"] = {**record, "file": target}
    return dataclasses.replace(truth, config_json=json.dumps(config, sort_keys=True))


def recorded_scenario(truth_path: str) -> str | None:
    """The named scenario a truth file records it was simulated from (datagen.scenario.truth_config_json), None
    where it records none, the name is no longer known, or the file does not read (load_truth says why)."""
    try:
        with open_npz(truth_path) as z:
            name = json.loads(str(z["config_json"])).get("scenario")
    except Exception:  # noqa: BLE001 - any unreadable file: load_truth reports it in one line
        return None
    try:
        check_name(name)
    except ConfigError:
        return None
    return name


def with_recorded_scenario(cfg: EstimateConfig, truth_path: str) -> EstimateConfig:
    """cfg as `envisat estimate --truth` builds it: a config of no scenario whose tables are the plain defaults
    takes the scenario the truth records (recorded_scenario: its [measurement] and [filter] tables, its name);
    cfg itself where it names a scenario, sets a table, or the truth records none."""
    recorded = recorded_scenario(truth_path)
    if cfg.scenario is not None or recorded is None:
        return cfg
    plain = EstimateConfig()
    if (cfg.measurement, cfg.filter) != (plain.measurement, plain.filter):
        return cfg
    return EstimateConfig(scenario=recorded, runs=cfg.runs, seed=cfg.seed, init_error_scale=cfg.init_error_scale)


def scenario_outages(cfg: EstimateConfig, scenario: str | None, truth) -> EstimateConfig:
    """With a named scenario whose file has an [eclipse] table: cfg with the Earth's-shadow windows along the
    simulated truth appended to its outages (eclipse_outages), but for those already among them (with_outages: a
    rerun of a written est.config.toml, which holds them, gets them once); cfg otherwise (no scenario: a truth
    file)."""
    if not scenario or scenario_eclipse(scenario) is None:  # the truth's config is read (MuJoCo: its target) only
        return cfg                                           # for a shadow to place
    import dataclasses

    windows = eclipse_outages(scenario, scenario_of_truth(truth.config))
    return dataclasses.replace(cfg, measurement=with_outages(cfg.measurement, windows))


# ---------------------------------------------------------------- the filter over R runs

def estimate_output_paths(out: str) -> tuple[str, str]:
    """est.npz -> (est.npz, est.config.toml)."""
    stem = out[:-4] if out.endswith(".npz") else out
    return out, stem + ".config.toml"


def estimate(truth, cfg: EstimateConfig, progress: bool = False) -> dict:
    """Filter cfg.runs runs of a truth trajectory; returns the arrays of est.npz (without config_json).

    Arrays: t_s (T,), x_true (R, T, 12), x_hat (R, T, 12), P (R, T, 12, 12), n_meas (R, T), nis (R, T), nis_dof (R, T),
    diverged (R,) (NIS window or NEES window against the truth), judged (R,) (whether the rule judged the run:
    False for one unflagged that ended before the monitors were armed, filtering.estimator.unjudged_runs).
    """

    mu_m3_s2, gravity_gradient = onboard_physics(truth)
    target = truth_target(truth.config, "the truth")
    check_truth_keypoints(truth, target, "the truth")

    sel = slice(0, None, truth_stride(truth, cfg))
    t_s, x_true = truth.t_s[sel], truth.x[sel]
    chaser = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad,
                           truth.chaser_thetadot_rad_s)[sel]
    R, T = cfg.runs, len(t_s)
    need = R * T * (144 + 30) * 8
    if need > MAX_OUTPUT_BYTES:
        raise ConfigError("runs", R, f"fewer runs or a shorter truth: {R} runs x {T} steps need "
                          f"{need / 2**30:.1f} GiB (limit {MAX_OUTPUT_BYTES / 2**30:.0f} GiB)")
    fcfg = cfg.filter
    kind = cfg.measurement.kind
    z_true, base = truth_measurements(kind, truth.corners_C_m[sel], truth.visible[sel], truth.corners_px[sel],
                                      truth.in_frame[sel])
    warn_if_unfixed_start(t_s, filter_keypoints_T_m(target), base, cfg.measurement)
    warn_outages_outside(t_s, cfg.measurement)
    inp = make_run_inputs(x_true[0], t_s, z_true, base, cfg.measurement, fcfg.P0, cfg.seed, R,
                          init_error_scale=cfg.init_error_scale)
    res = run_filter(inp.x0_hat, fcfg.P0, t_s, chaser, inp.z, inp.mask, inp.R_c, kind, fcfg, progress=progress,
                     mu_m3_s2=mu_m3_s2, gravity_gradient=gravity_gradient, target=target)
    diverged = diverged_against_truth(res.diverged, nees(x_true[None], res.x_hat, res.P, fcfg.sigma_chart), fcfg)
    if not np.any(res.n_meas):
        warn_if_never_updated(bool(np.any(inp.mask)))
    return {
        "t_s": t_s,
        "x_true": np.broadcast_to(x_true, (R, T, 12)).copy(),
        "x_hat": res.x_hat,
        "P": res.P,
        "n_meas": res.n_meas,
        "nis": res.nis,
        "nis_dof": res.dof,
        "diverged": diverged,
        "judged": ~unjudged_runs(diverged, T, fcfg),  # a short run's diverged False is "not judged"
    }


def truth_stride(truth, cfg: EstimateConfig) -> int:
    """The truth samples a filter step spans (filtering.montecarlo.filter_stride); ConfigError naming
    measurement.rate_hz where its period is not a whole number of them, or is longer than the truth (one filter
    step: the first update alone, which a summary "after t = 0 s" did not tell)."""
    rate = cfg.measurement.rate_hz
    try:
        stride = filter_stride(truth.t_s, rate)
    except ValueError as err:
        raise ConfigError("measurement.rate_hz", rate, str(err)) from None
    span_s = float(truth.t_s[-1] - truth.t_s[0])
    check(len(truth.t_s) > stride, "measurement.rate_hz", rate,
          f"a rate whose period 1/rate_hz = {1.0 / rate:g} s fits in the truth's {span_s:g} s (2 filter steps at "
          "least)")
    return stride


@locks_output("rrd", "estimate", folder=False)
@locks_output("out", "estimate", folder=False)
def run_estimate(cfg: EstimateConfig, out: str, truth_path: str | None = None, scenario: str | None = None,
                 duration_s: float | None = None, plot: bool = False, rrd: str | None = None,
                 progress: bool = False, target: str | None = None) -> dict:
    """The whole job: load or simulate the truth (load_truth; given neither truth_path nor scenario,
    cfg.scenario's), add a scenario's eclipse outages, filter cfg.runs runs (estimate), write out (Estimates)
    and its config (output_paths), and with plot the errors' PNG next to out, with rrd a Rerun recording
    (target: a truth file's target file where the path it records is not found from here: load_truth). The
    paths (str or pathlib.Path; out ending in .npz, rrd in .rrd) are checked before any work, InputError naming
    the argument; the folders are made once the truth is read (a refused truth writes nothing).

    Returns {"config": the EstimateConfig run (outages added), "arrays": est.npz's arrays, "est": out,
    "config_toml": its path, "plot": the PNG's path or None, "rrd": rrd}.
    """
    cfg = config_arg(cfg, EstimateConfig)
    out, rrd = path_arg(out, "out"), rrd_arg(rrd)
    truth_path = path_arg(truth_path, "truth_path", optional=True)
    if truth_path and scenario:  # the verb's --truth and --scenario exclude each other as well
        raise InputError("truth_path and scenario: give one of them (a truth file, or a named scenario to simulate)")
    if not out.endswith(".npz"):
        raise InputError(f"out {out!r}: expected a path ending in .npz")
    for path, field in [(p, "out") for p in estimate_output_paths(out)] + ([(rrd, "rrd")] if rrd else []):
        check_out_file(path, field)
    out, cfg_path = estimate_output_paths(out)
    stale = own_side_files(out, cfg_path, out[:-4] + ".png", "estimate", plot)  # a user's est.png: not replaced
    if not truth_path and not scenario:
        scenario = cfg.scenario
        if scenario is None:
            raise InputError("truth_path or scenario: give one (a truth file, or a named scenario to simulate, "
                             "as `scenario` or EstimateConfig(scenario=NAME))")
    if truth_path and not scenario:
        cfg = with_recorded_scenario(cfg, truth_path)
    truth, source = load_truth(cfg, truth_path, scenario, duration_s, progress, path_arg(target, "target",
                                                                                          optional=True))
    cfg = scenario_outages(cfg, scenario or cfg.scenario, truth)  # a truth file of cfg's scenario: its shadow too
    if len(truth.t_s) < 2:
        raise InputError("the truth trajectory has fewer than 2 samples")
    cfg.measurement.check_keypoints(int(truth.corners_C_m.shape[1]))  # max_markers <= the target's K
    truth_stride(truth, cfg)  # a rate off the truth's grid: refused before any folder is made
    make_out_file_dirs({out: "out", cfg_path: "out", **({rrd: "rrd"} if rrd else {})})
    arrays = estimate(truth, cfg, progress=progress)
    config_json = json.dumps({"estimate": to_dict(cfg), "truth_source": source, "truth_config": truth.config},
                             sort_keys=True)
    est = Estimates(**arrays, config_json=config_json)
    png = out[:-4] + ".png" if plot else None
    # written into a staging folder beside out and moved into place together: an interrupt leaves an earlier
    # run's est.npz, est.config.toml and est.png as they were, never a new est.npz beside an old est.png (a
    # rerun without plot removes the earlier PNG: it shows other estimates; a user's PNG of that name stays)
    with staged_folder(os.path.dirname(os.path.abspath(out)), stale) as stage:
        est.save(os.path.join(stage, os.path.basename(out)))
        atomic_write_text(os.path.join(stage, os.path.basename(cfg_path)),
                          "# envisat estimate: the full validated config of this job\n" + source_line()
                          + truth_origin(source, truth)
                          + to_toml(to_dict(cfg)))
        if plot:
            from envisat_pose.analysis.plots import plot_estimate

            plot_estimate(arrays["t_s"], arrays["x_true"], arrays["x_hat"], arrays["P"],
                          os.path.join(stage, os.path.basename(png)),
                          title=f"{(truth_target(truth.config, 'the truth') or load_target(DEFAULT_TARGET)).name}: "
                                f"UKF errors, {cfg.measurement.kind}, {cfg.runs} runs, seed {cfg.seed}", job="estimate")
        if rrd:
            from envisat_pose.analysis.recording import write_estimates_recording

            write_estimates_recording(rrd, est, truth, target=truth_target(truth.config, "the truth"),
                                      nees_rt=nees(est.x_true, est.x_hat, est.P, cfg.filter.sigma_chart))
    return {"config": cfg, "arrays": arrays, "est": out, "config_toml": cfg_path, "plot": png, "rrd": rrd}
