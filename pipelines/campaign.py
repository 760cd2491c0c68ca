"""The campaign pipeline of `envisat montecarlo`: a Monte Carlo campaign of the batched UKF over one MuJoCo
truth, in resumable blocks.

The truth is simulated once (MuJoCo) and saved as DIR/truth.npz. The runs are split into blocks of
`block_runs`; each block is one task of the core runner (`block_task`: plain data in, its manifest entry out)
that filters its runs with the pure `filter_step` in time chunks, so no covariance history is ever held: per
chunk, `analysis.stats.reduce_runs` turns it into sums over the block's runs, and per-run summaries are
accumulated. Memory is O(block_runs x steps) for the inputs and O(block_runs x CHUNK_STEPS) for covariances.
Run r draws from SeedSequence(seed, spawn_key=(r,)), so a block draws exactly what the campaign draws.

Files in DIR:
    truth.npz                 the truth (TruthTrajectory contract)
    blocks/block-NNNN.npz     one per block: CampaignSums arrays, per-run summaries, sample-run errors
    manifest.json             the config, the truth's sha256 and each finished block's sha256 and wall time
    campaign.npz              statistics over time (stats.CampaignStats), the PCRLB per block, per-run summaries,
                              the component errors of the first `sample_runs` runs
    summary.json              the reproducible scalars: RMSE per block after settle_s, share inside 3-sigma,
                              mean NEES with its 95 % band, NIS, PCRLB and RMSE/PCRLB per block, diverged runs
    timing.json               wall times (never part of anything byte-reproducible)
    envelopes.png, block_norms.png, nees_nis.png, rmse_vs_pcrlb.png
    montecarlo.config.toml    the full validated config

The same config and seed give the same bytes of blocks, campaign.npz and summary.json whatever the backend
(local pool, Dask) and worker count: blocks are merged in run-index order (`stats.SumsFolder`). Rerunning the
same command on DIR keeps the finished blocks whose sha256 matches the manifest; another config is refused.

A rate sweep (pipelines/sweep.py) runs one such campaign per filter rate. `with_eclipse` adds a scenario's Earth's-shadow outages to a resolved config.
The app's verb (app/montecarlo.py) parses the flags, resolves the config and prints.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import ConfigError, check, from_dict, to_dict, to_toml
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.filtering.montecarlo import MeasurementConfig
from envisat_pose.io import json_safe, sha256_file
from envisat_pose.state import BLOCKS, N_STATE

MANIFEST_FORMAT = "envisat-pose montecarlo v1"
CHUNK_STEPS = 200  # filter steps per reduction chunk: bounds the covariances held to R x 200 x 144 floats
FIGURES = ("envelopes.png", "block_norms.png", "nees_nis.png", "rmse_vs_pcrlb.png")
RUN_KEYS = ("rms_block", "final_block", "max_block", "inside_share", "nees_mean", "nis_per_dof", "diverged")


@dataclass(frozen=True)
class MonteCarloConfig:
    """One campaign. The results' bytes depend on every field (block_runs fixes the order of the sums).

    scenario: named truth scenario. duration_s: simulated time, s. runs: Monte Carlo runs. seed: root seed (the
    truth's initial attitude and run r's draws, SeedSequence(seed, spawn_key=(r,))). block_runs: runs per task.
    settle_s: the statistics of summary.json use the steps at or after t0 + settle_s (None: half the duration,
    at most 600 s). sample_runs: the first runs whose errors are kept for the figures' grey curves.
    """

    scenario: str = "default"
    duration_s: float = 1800.0
    runs: int = 100
    seed: int = 0
    block_runs: int = 125
    settle_s: float | None = None
    sample_runs: int = 20
    measurement: MeasurementConfig = field(default_factory=MeasurementConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)

    def validate(self, prefix: str = "") -> None:
        check(self.duration_s > 0, "duration_s", self.duration_s, "a positive duration in seconds")
        check(1 <= self.runs <= 1_000_000, "runs", self.runs, "a number of runs from 1 to 1000000")
        check(0 <= self.seed < 2**63, "seed", self.seed, "a non-negative integer seed")
        check(1 <= self.block_runs <= 10_000, "block_runs", self.block_runs, "an integer from 1 to 10000")
        check(self.settle_s is None or 0 <= self.settle_s < self.duration_s, "settle_s", self.settle_s,
              f"a time in [0, duration_s = {self.duration_s:g}) s")
        check(0 <= self.sample_runs <= 200, "sample_runs", self.sample_runs, "an integer from 0 to 200")

    @property
    def settle_time_s(self) -> float:
        return float(self.settle_s) if self.settle_s is not None else min(600.0, 0.5 * self.duration_s)

    @property
    def n_blocks(self) -> int:
        return -(-self.runs // self.block_runs)

    def block_range(self, b: int) -> tuple[int, int]:
        """Runs [start, stop) of block b."""
        return b * self.block_runs, min(self.runs, (b + 1) * self.block_runs)


def with_eclipse(cfg: MonteCarloConfig) -> MonteCarloConfig:
    """cfg with its scenario's Earth's-shadow windows (if it has an [eclipse] table) appended to the outages
    (pipelines.estimate.eclipse_outages)."""
    import dataclasses

    from envisat_pose.pipelines.estimate import eclipse_outages, with_outages

    windows = eclipse_outages(cfg.scenario, truth_scenario(cfg))
    return dataclasses.replace(cfg, measurement=with_outages(cfg.measurement, windows))


def write_recording(cfg: MonteCarloConfig, out_dir: str, path: str) -> None:
    """A Rerun recording at path (--rrd): the truth, run 0's estimate and 3-sigma ellipsoid (run 0 filtered
    again, keeping its means and covariances: it draws what the campaign drew), the sample runs' errors and the
    campaign's bands from campaign.npz."""
    from envisat_pose.analysis.recording import write_campaign_recording
    from envisat_pose.contracts import TruthTrajectory

    tr = load_campaign_truth(out_dir, cfg.measurement)
    x_hat, P = filter_run_history(tr, cfg, 0)
    with np.load(os.path.join(out_dir, "campaign.npz"), allow_pickle=False) as z:
        sample_err, filt, samp = z["sample_err"], z["filter_3sigma"], z["sample_3sigma"]
    write_campaign_recording(path, tr.t_s, tr.x_true, x_hat, P, sample_err, filt, samp if cfg.runs > 1 else None,
                             truth=TruthTrajectory.load(os.path.join(out_dir, "truth.npz")))


def filter_run_history(tr: "CampaignTruth", cfg: MonteCarloConfig, run: int) -> tuple[np.ndarray, np.ndarray]:
    """Run `run` of the campaign filtered alone, as filter_block filters it: its means (T, 12) and covariances
    (T, 12, 12) after every step."""
    from envisat_pose.filtering.estimator import Measurement, filter_step, init_state, make_setup
    from envisat_pose.filtering.montecarlo import make_run_inputs

    fcfg = cfg.filter
    inp = make_run_inputs(tr.x_true[0], tr.t_s, tr.z_true, tr.base, cfg.measurement, fcfg.P0, cfg.seed, 1,
                          first_run=run)
    setup = make_setup(fcfg, cfg.measurement.kind, mu_m3_s2=tr.mu_m3_s2, gravity_gradient=tr.gravity_gradient)
    R_c = np.broadcast_to(inp.R_c, inp.z.shape[:-1] + inp.R_c.shape[-2:])
    state = init_state(inp.x0_hat, fcfg.P0, tr.t_s[0], tr.chaser[0], fcfg)
    T = len(tr.t_s)
    x_hat, P = np.empty((T, N_STATE)), np.empty((T, N_STATE, N_STATE))
    for k in range(T):
        state = filter_step(state, Measurement(tr.t_s[k], tr.chaser[k], inp.z[:, k], inp.mask[:, k], R_c[:, k]), setup)
        x_hat[k], P[k] = state.mean[0], state.cov[0]
    return x_hat, P


# ---------------------------------------------------------------- the campaign

def block_name(b: int) -> str:
    return os.path.join("blocks", f"block-{b:04d}.npz")


def campaign_job(cfg: MonteCarloConfig, out_dir: str) -> "ResumableJob":
    """The campaign in out_dir as the core's resumable job: one unit per block, the config as its identity, a
    block kept on resume only when its sha256 matches and it covers the runs the config gives it (the truth's
    sha256 goes in the header once the truth is known)."""
    from envisat_pose.runner import ResumableJob

    return ResumableJob(out_dir, MANIFEST_FORMAT, "campaign", {"config": to_dict(cfg)}, "blocks", cfg.n_blocks,
                        block_name, header={"n_blocks": cfg.n_blocks},
                        verify_unit=lambda e, path: cfg.block_range(e["index"]) == (e["run_start"], e["run_stop"]))


def truth_scenario(cfg: MonteCarloConfig):
    """The validated ScenarioConfig of the campaign's truth (the filter's rate above 1 Hz refines its step)."""
    from envisat_pose.datagen.scenario import scenario_config

    overrides: dict = {"seed": cfg.seed, "duration_s": cfg.duration_s}
    if cfg.measurement.rate_hz > 1.0:
        overrides["dt_s"] = 1.0 / cfg.measurement.rate_hz
    return scenario_config(cfg.scenario, **overrides)


def check_filter_rate(cfg: MonteCarloConfig, scenario) -> None:
    """The filter's period must be a whole number of the truth's sample steps (before any work)."""
    from envisat_pose.filtering.montecarlo import filter_stride

    try:
        filter_stride(np.array([0.0, scenario.dt_s]), cfg.measurement.rate_hz)
    except ValueError as err:
        raise ConfigError("measurement.rate_hz", cfg.measurement.rate_hz, str(err)) from None


def prepare_truth(cfg: MonteCarloConfig, out_dir: str, manifest: dict | None, progress: bool) -> str:
    """DIR/truth.npz: kept when the manifest vouches for it, else simulated with MuJoCo. Returns its sha256."""
    path = os.path.join(out_dir, "truth.npz")
    if manifest and os.path.exists(path) and sha256_file(path) == manifest.get("truth_sha256"):
        return manifest["truth_sha256"]
    from envisat_pose.datagen.truth import simulate

    simulate(truth_scenario(cfg), progress=progress).save(path)
    return sha256_file(path)


def run_campaign(cfg: MonteCarloConfig, out_dir: str, runner, progress: bool = False) -> dict:
    """Run (or finish) the campaign of cfg in out_dir and write its outputs. Returns summary.json's dict."""
    from envisat_pose.io import atomic_write_text

    t_start = time.perf_counter()
    check_filter_rate(cfg, truth_scenario(cfg))
    job = campaign_job(cfg, out_dir)
    previous = job.open()
    truth_sha = prepare_truth(cfg, out_dir, previous, progress)
    job.header["truth_sha256"] = truth_sha
    # blocks filtered on another truth are redone
    done = job.resume(previous if previous and previous.get("truth_sha256") == truth_sha else None)
    atomic_write_text(os.path.join(out_dir, "montecarlo.config.toml"),
                      "# envisat montecarlo: the full validated config of this campaign\n" + to_toml(to_dict(cfg)))
    cfg_json, where = json.dumps(to_dict(cfg), sort_keys=True), os.path.abspath(out_dir)
    n_run_now = len(job.todo())
    bar = _bar(cfg, done, progress)
    try:
        job.run(block_task, lambda b: (where, cfg_json, b), runner,
                on_unit=None if bar is None else lambda e: bar.update(e["run_stop"] - e["run_start"]))
    finally:
        if bar is not None:
            bar.close()
    done = job.done
    summary = finish_campaign(cfg, out_dir)
    timing = {"wall_s_this_invocation": time.perf_counter() - t_start,
              "block_wall_s": {str(i): done[i]["wall_s"] for i in sorted(done)},
              "block_wall_s_sum": float(sum(e["wall_s"] for e in done.values())),
              "blocks_run_now": n_run_now, "backend": runner.backend, "workers": runner.workers,
              "run_steps": cfg.runs * summary["steps"]}
    atomic_write_text(os.path.join(out_dir, "timing.json"), json.dumps(timing, indent=1, sort_keys=True) + "\n")
    return summary


def _bar(cfg: MonteCarloConfig, done: dict, progress: bool):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=cfg.runs, initial=sum(e["run_stop"] - e["run_start"] for e in done.values()), unit="run",
                desc="montecarlo", mininterval=0.5)


# ---------------------------------------------------------------- one block (a runner task)

@dataclass(frozen=True)
class CampaignTruth:
    """The truth on the filter's grid: t_s (T,), x_true (T, 12), chaser (T, 4), z_true (T, 8, m), base (T, 8)
    measurable corners (outages not yet removed), and the filter's model constants mu_m3_s2, gravity_gradient."""

    t_s: np.ndarray
    x_true: np.ndarray
    chaser: np.ndarray
    z_true: np.ndarray
    base: np.ndarray
    mu_m3_s2: float
    gravity_gradient: bool


def load_campaign_truth(out_dir: str, mcfg: MeasurementConfig) -> CampaignTruth:
    """DIR/truth.npz sampled at the filter's rate, with its noise-free measurements."""
    from envisat_pose.contracts import TruthTrajectory
    from envisat_pose.filtering.estimator import chaser_states
    from envisat_pose.filtering.montecarlo import filter_stride, truth_measurements
    from envisat_pose.pipelines.onboard import onboard_physics

    path = os.path.join(out_dir, "truth.npz")
    truth = TruthTrajectory.load(path)
    mu, gg = onboard_physics(truth, path)
    sel = slice(0, None, filter_stride(truth.t_s, mcfg.rate_hz))
    chaser = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad,
                           truth.chaser_thetadot_rad_s)[sel]
    z_true, base = truth_measurements(mcfg.kind, truth.corners_C_m[sel], truth.visible[sel], truth.corners_px[sel],
                                      truth.in_frame[sel])
    return CampaignTruth(truth.t_s[sel], truth.x[sel], chaser, z_true, base, mu, gg)


def block_task(out_dir: str, cfg_json: str, b: int) -> dict:
    """Runner task: filter and reduce block b of the campaign in out_dir, write blocks/block-NNNN.npz
    atomically, return its manifest entry {index, run_start, run_stop, file, sha256, wall_s}."""
    from envisat_pose.io import save_npz

    t0 = time.perf_counter()
    cfg = from_dict(MonteCarloConfig, json.loads(cfg_json))
    a, z = cfg.block_range(b)
    arrays = filter_block(load_campaign_truth(out_dir, cfg.measurement), cfg, a, z)
    path = os.path.join(out_dir, block_name(b))
    save_npz(path, arrays)
    return {"index": b, "run_start": a, "run_stop": z, "file": block_name(b), "sha256": sha256_file(path),
            "wall_s": time.perf_counter() - t0}


def filter_block(tr: CampaignTruth, cfg: MonteCarloConfig, run_start: int, run_stop: int) -> dict:
    """Filter runs [run_start, run_stop) and reduce them chunk by chunk. Returns the block file's arrays:
    CampaignSums.to_arrays() (over all T steps), run_<key> per-run summaries (stats.RunSummary fields over the
    settled steps), sample_err (S, T, 12) and sample_norms (S, T, 4) of the block's runs below sample_runs."""
    from envisat_pose.analysis.stats import RunAccumulator, block_error_norms, component_errors
    from envisat_pose.filtering.estimator import Measurement, filter_step, init_state, make_setup
    from envisat_pose.filtering.montecarlo import make_run_inputs
    from envisat_pose.state import nees_window_diverged

    fcfg, n = cfg.filter, run_stop - run_start
    inp = make_run_inputs(tr.x_true[0], tr.t_s, tr.z_true, tr.base, cfg.measurement, fcfg.P0, cfg.seed, n,
                          first_run=run_start)
    setup = make_setup(fcfg, cfg.measurement.kind, mu_m3_s2=tr.mu_m3_s2, gravity_gradient=tr.gravity_gradient)
    R_c = np.broadcast_to(inp.R_c, inp.z.shape[:-1] + inp.R_c.shape[-2:])
    state = init_state(inp.x0_hat, fcfg.P0, tr.t_s[0], tr.chaser[0], fcfg)
    T, n_sample = len(tr.t_s), max(0, min(run_stop, cfg.sample_runs) - run_start)
    acc = RunAccumulator(n, settled_mask(tr.t_s, cfg.settle_time_s))
    sums, nees_rt = [], np.empty((n, T))
    sample_err, sample_norms = np.empty((n_sample, T, N_STATE)), np.empty((n_sample, T, 4))
    for k0 in range(0, T, CHUNK_STEPS):
        ks = range(k0, min(T, k0 + CHUNK_STEPS))
        x_hat, P = np.empty((n, len(ks), N_STATE)), np.empty((n, len(ks), N_STATE, N_STATE))
        nis, dof = np.empty((n, len(ks))), np.empty((n, len(ks)), dtype=np.int64)
        for j, k in enumerate(ks):
            state = filter_step(state, Measurement(tr.t_s[k], tr.chaser[k], inp.z[:, k], inp.mask[:, k], R_c[:, k]),
                                setup)
            x_hat[:, j], P[:, j], nis[:, j], dof[:, j] = state.mean, state.cov, state.nis, state.dof
        x_true = np.broadcast_to(tr.x_true[k0:k0 + len(ks)], x_hat.shape)
        sums.append(_reduce_chunk(x_true, x_hat, P, nis, dof))
        nees_rt[:, ks.start:ks.stop] = acc.add(ks, x_true, x_hat, P, nis, dof)
        if n_sample:
            sample_err[:, ks.start:ks.stop] = component_errors(x_true[:n_sample], x_hat[:n_sample])
            sample_norms[:, ks.start:ks.stop] = block_error_norms(x_true[:n_sample], x_hat[:n_sample])
    diverged = state.diverged | nees_window_diverged(nees_rt, fcfg.divergence_window, fcfg.divergence_settle_steps,
                                                     fcfg.nees_divergence_factor)
    out = _join_chunks(sums, run_start, run_stop, diverged)
    out.update({f"run_{k}": v for k, v in vars(acc.result(x_true[:, -1], x_hat[:, -1], diverged)).items()})
    out.update(sample_err=sample_err, sample_norms=sample_norms)
    return out


def _reduce_chunk(x_true, x_hat, P, nis, dof):
    from envisat_pose.analysis.stats import reduce_runs

    return reduce_runs(x_true, x_hat, P, nis, dof, np.zeros(x_hat.shape[0], dtype=bool))


def _join_chunks(sums: list, run_start: int, run_stop: int, diverged: np.ndarray) -> dict:
    """CampaignSums arrays of consecutive time chunks of the same runs, joined along time."""
    from envisat_pose.analysis.stats import CampaignSums

    joined = CampaignSums(run_start, run_stop, run_stop - run_start,
                          **{k: np.concatenate([getattr(s, k) for s in sums]) for k in CampaignSums.ARRAYS},
                          n_diverged=int(np.count_nonzero(diverged)))
    return joined.to_arrays()


def settled_mask(t_s: np.ndarray, settle_s: float) -> np.ndarray:
    """(T,) bool: the steps at or after t_s[0] + settle_s (stats.settled)."""
    from envisat_pose.analysis.stats import settled

    return settled(np.asarray(t_s), settle_s)


# ---------------------------------------------------------------- merging, bound, outputs

def load_block(path: str) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def merge_blocks(cfg: MonteCarloConfig, out_dir: str):
    """Fold the block files in run-index order. Returns (CampaignSums, per-run dict, sample_err, sample_norms)."""
    from envisat_pose.analysis.stats import CampaignSums, SumsFolder

    folder, runs, s_err, s_norm = SumsFolder(), {k: [] for k in RUN_KEYS}, [], []
    for b in range(cfg.n_blocks):
        d = load_block(os.path.join(out_dir, block_name(b)))
        folder.add(CampaignSums.from_arrays(d))
        for k in RUN_KEYS:
            runs[k].append(d[f"run_{k}"])
        s_err.append(d["sample_err"])
        s_norm.append(d["sample_norms"])
    return (folder.result(), {k: np.concatenate(v) for k, v in runs.items()}, np.concatenate(s_err),
            np.concatenate(s_norm))


def campaign_pcrlb(cfg: MonteCarloConfig, tr: CampaignTruth) -> np.ndarray:
    """PCRLB per block (T, 4) along the truth, with the corners the truth lets the filter measure at each step
    (visible, in frame for pixels, outside outages, at most max_markers; random failures are not modelled), the
    filter's P0, the measurement noise of the config and the truth's process noise (none). Statistics' units."""
    from envisat_pose.analysis.pcrlb import block_bounds, pcrlb_along_truth
    from envisat_pose.filtering.dynamics import load_inertia_T_kg_m2, propagate
    from envisat_pose.filtering.measurements import limit_markers, measure, outage_mask
    from envisat_pose.geometry import load_camera

    mcfg, J_T, camera = cfg.measurement, load_inertia_T_kg_m2(), load_camera()
    dt_s = 1.0 / mcfg.rate_hz
    measured = limit_markers(tr.base & ~outage_mask(tr.t_s, mcfg.outages_s)[:, None], mcfg.max_markers)

    def fx(X):
        return propagate(X, tr.chaser[:-1, None, :], dt_s, J_T, tr.mu_m3_s2, gravity_gradient=tr.gravity_gradient)

    def hx(X):
        return measure(X, mcfg.kind, camera)

    B = pcrlb_along_truth(fx, hx, tr.x_true, measured, mcfg.corner_cov, cfg.filter.P0, np.zeros((N_STATE, N_STATE)))
    return block_bounds(B, tr.x_true)


def finish_campaign(cfg: MonteCarloConfig, out_dir: str) -> dict:
    """Merge the blocks, compute the PCRLB, write campaign.npz, summary.json and the figures."""
    from envisat_pose.analysis.pcrlb import efficiency
    from envisat_pose.analysis.stats import campaign_summary, finalize
    from envisat_pose.io import atomic_write_text, save_npz

    sums, runs, sample_err, sample_norms = merge_blocks(cfg, out_dir)
    tr = load_campaign_truth(out_dir, cfg.measurement)
    stats = finalize(sums)
    bound = campaign_pcrlb(cfg, tr)
    settle = cfg.settle_time_s
    arrays = {k: np.asarray(v) for k, v in vars(stats).items()}
    arrays.update(t_s=tr.t_s, pcrlb_block=bound, sample_err=sample_err, sample_norms=sample_norms,
                  **{f"run_{k}": v for k, v in runs.items()})
    save_npz(os.path.join(out_dir, "campaign.npz"), arrays)
    summary = campaign_summary(sums, tr.t_s, settle)
    k = settled_mask(tr.t_s, settle)
    summary.update(
        scenario=cfg.scenario, runs=cfg.runs, seed=cfg.seed, steps=len(tr.t_s), duration_s=cfg.duration_s,
        measurement=to_dict(cfg.measurement),
        pcrlb_rms={b: float(np.sqrt(np.mean(bound[k, i] ** 2))) for i, b in enumerate(BLOCKS)},
        rmse_over_pcrlb=dict(zip(BLOCKS, (float(v) for v in efficiency(stats.rmse_block, bound, tr.t_s, settle)))),
        diverged_runs=[int(i) for i in np.flatnonzero(runs["diverged"])],
    )
    atomic_write_text(os.path.join(out_dir, "summary.json"), json.dumps(json_safe(summary), indent=1, sort_keys=True)
                      + "\n")
    write_figures(cfg, out_dir, tr.t_s, stats, bound, sample_err, sample_norms)
    return summary


def write_figures(cfg: MonteCarloConfig, out_dir: str, t_s, stats, bound, sample_err, sample_norms) -> None:
    from envisat_pose.analysis.campaign_figures import (plot_block_norms, plot_error_envelopes, plot_nees_nis,
                                                        plot_rmse_vs_bound)

    m = cfg.measurement
    noise = f"{m.sigma_m:g} m" if m.kind == "markers3d" else f"{m.sigma_px:g} px"
    title = f"{cfg.scenario}: {cfg.runs} runs, {m.kind} at {noise}, {m.rate_hz:g} Hz, seed {cfg.seed}"
    err = sample_err if len(sample_err) else None
    norms = sample_norms if len(sample_norms) else None
    path = os.path.join
    plot_error_envelopes(t_s, err, stats.filter_3sigma, stats.sample_3sigma, path(out_dir, FIGURES[0]), title=title)
    plot_block_norms(t_s, norms, stats.rmse_block, stats.filter_3sigma_block, path(out_dir, FIGURES[1]), title=title)
    plot_nees_nis(t_s, stats.nees_mean, stats.nees_bounds, stats.nis_mean, stats.nis_bounds,
                  path(out_dir, FIGURES[2]), title=title)
    plot_rmse_vs_bound(t_s, stats.rmse_block, bound, path(out_dir, FIGURES[3]), title=title,
                       filter_3sigma_block=stats.filter_3sigma_block)
