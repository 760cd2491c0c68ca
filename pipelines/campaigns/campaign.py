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
    montecarlo.config.toml    the full validated config (`--config` reruns the campaign); a rate sweep's campaign
                              writes it as rate.config.toml (SWEEP_RATE_CONFIG: the sweep's own reruns it)

The same config and seed give the same bytes of blocks, campaign.npz and summary.json whatever the backend
(local pool, Dask) and worker count: blocks are merged in run-index order (`stats.SumsFolder`). Rerunning the
same command on DIR keeps the finished blocks whose sha256 matches the manifest; another config is refused.

A rate sweep (pipelines/campaigns/sweep.py) runs one such campaign per filter rate. `with_eclipse` adds a scenario's Earth's-shadow outages to a resolved config.
The app's verb (app/montecarlo.py) parses the flags, resolves the config and prints.

This module runs the campaign (run_campaign: the truth, the resumable job of blocks, the outputs); the parts, one
job each: its config (campaign_config.py: MonteCarloConfig, the truth's scenario, the rate check, eclipses), one
block (campaign_block.py: the runner's task, the chunked filter and its reduction) and the outputs
(campaign_outputs.py: merging, the PCRLB, summary.json, the figures, the recording). Their public names are
importable from here as before (`envisat_pose.pipelines.campaigns.campaign.run_campaign`, `MonteCarloConfig`, ...).
"""


from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import TYPE_CHECKING

from envisat_pose.config import check, config_arg, path_arg, rrd_arg, to_dict, to_toml
from envisat_pose.io import atomic_write_text, sha256_file
from envisat_pose.named_scenarios import table
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.campaigns.campaign_block import BLOCK_GLOB, block_name, block_task, load_campaign_truth
from envisat_pose.pipelines.campaigns.campaign_config import (
    MonteCarloConfig,
    check_filter_rate,
    truth_scenario,
    with_eclipse,
)
from envisat_pose.pipelines.campaigns.campaign_outputs import FIGURES, finish_campaign, write_recording
from envisat_pose.pipelines.campaigns.estimate import filter_keypoints_T_m
from envisat_pose.pipelines.campaigns.observability import warn_if_unfixed_start, warn_outages_outside
from envisat_pose.pools import BLAS_THREADS, RunnerConfig, thread_env, warn_runner
from envisat_pose.provenance import source_line
from envisat_pose.resumable import ResumableJob
from envisat_pose.target import load_target
from envisat_pose.written_target import with_target_sha256

# the entry points, and the parts' names the verb (app/montecarlo.py) and users import from here
__all__ = ["run_campaign", "campaign_job", "prepare_truth", "MANIFEST_FORMAT", "MonteCarloConfig", "with_eclipse",
           "check_filter_rate", "truth_scenario", "FIGURES", "write_recording", "read_timing"]

if TYPE_CHECKING:
    from envisat_pose.resumable import ResumableJob

MANIFEST_FORMAT = "envisat-pose montecarlo v1"
CONFIG_NAME = "montecarlo.config.toml"  # what `envisat montecarlo --config` reruns
SWEEP_RATE_CONFIG = "rate.config.toml"  # a rate sweep's campaign's config: the sweep's montecarlo.config.toml reruns it
# config fields added since v1 folders were written, with the value such a folder used (it resumes as it was)
ADDED_DEFAULTS = {"config.init_error_scale": 1.0}


def campaign_job(cfg: MonteCarloConfig, out_dir: str) -> ResumableJob:
    """The campaign in out_dir as the core's resumable job: one unit per block, the config as its identity, a
    block kept on resume only when its sha256 matches and it covers the runs the config gives it (the truth's
    sha256 goes in the header once the truth is known). A file named like a block that is none of the campaign's
    (beyond its last, copied in), or a block file in a folder without a manifest, is refused, not removed."""

    header = {"n_blocks": cfg.n_blocks}
    if cfg.target is not None:  # the file, however its path is written (compared by its sha256)
        header["target_sha256"] = load_target(cfg.target, "target").sha256
    return ResumableJob(out_dir, MANIFEST_FORMAT, "campaign", {"config": to_dict(cfg)}, "blocks", cfg.n_blocks,
                        block_name, header=header,
                        verify_unit=lambda e, path: cfg.block_range(e["index"]) == (e["run_start"], e["run_stop"]),
                        added_defaults=ADDED_DEFAULTS, own_entries=("truth.npz",),  # written before the manifest
                        compared_by={"config.target": "target_sha256"},
                        unit_glob=BLOCK_GLOB)  # a block beyond the last, or misnamed: refused, never removed


def prepare_truth(cfg: MonteCarloConfig, out_dir: str, manifest: dict | None, progress: bool) -> str:
    """DIR/truth.npz: kept when the manifest vouches for it, else simulated with MuJoCo. Returns its sha256."""
    path = os.path.join(out_dir, "truth.npz")
    if manifest and os.path.exists(path) and sha256_file(path) == manifest.get("truth_sha256"):
        return manifest["truth_sha256"]
    from envisat_pose.datagen.truth import simulate_truth

    simulate_truth(truth_scenario(cfg), progress=progress).save(path)
    return sha256_file(path)


@locks_output("rrd", "montecarlo", folder=False)
@locks_output("out_dir", "montecarlo")
def run_campaign(cfg: MonteCarloConfig, out_dir: str, runner: RunnerConfig | None = None,
                 progress: bool = False, rrd: str | None = None) -> dict:
    """Run (or finish) the campaign of cfg in out_dir (a str or pathlib.Path: rerun on it to resume) on runner
    (a core RunnerConfig: the local pool, Dask; None: one process) and write its outputs (module docstring); with
    rrd (a .rrd path) a Rerun recording of it there too (write_recording). Returns summary.json's dict.
    ConfigError or InputError (one line, naming the field or argument) before any work for a bad argument or a
    folder of another job. A scenario with a [sweep] table (rate-sweep) is one campaign per rate, as the verb runs
    it: pipelines.campaigns.sweep.run_sweep (ConfigError naming scenario)."""
    cfg = config_arg(cfg, MonteCarloConfig)
    check(not table(cfg.scenario, "sweep"), "scenario", cfg.scenario, "a scenario of one rate: this one is a rate "
          "sweep ([sweep] table), one campaign per rate: envisat_pose.pipelines.campaigns.sweep.run_sweep(cfg, "
          "sweep_for(cfg), out_dir, runner), as `envisat montecarlo` runs it")
    rrd = rrd_arg(rrd)
    if rrd is not None:
        check_out_file(rrd, "rrd")
    if runner is not None:
        warn_runner(config_arg(runner, RunnerConfig, "runner"), cfg.n_blocks)  # once, before the work
    summary = campaign_at_one_rate(cfg, out_dir, runner, progress)
    if rrd is not None:
        make_out_file_dir(rrd, "rrd")
        write_recording(cfg, out_dir, rrd)
    return summary


def with_blas_threads(runner: RunnerConfig) -> RunnerConfig:
    """runner with each worker's share of the usable cores for numpy's and scipy's linear algebra
    (pools.thread_env over BLAS_THREADS) where its env sets none of them: a block's filter is BLAS-bound, and N
    workers each taking every core oversubscribe them N times (the verb gave the share, run_campaign did not)."""
    env = {**thread_env(runner.workers, BLAS_THREADS), **runner.env}
    return runner if env == runner.env else dataclasses.replace(runner, env=env)


def campaign_at_one_rate(cfg: MonteCarloConfig, out_dir: str, runner: RunnerConfig | None = None,
                         progress: bool = False, in_sweep: bool = False) -> dict:
    """run_campaign's work, at cfg's one rate (a rate sweep's campaigns: pipelines.campaigns.sweep.run_sweep;
    in_sweep: one of them, its config written as SWEEP_RATE_CONFIG, which `--config` does not rerun alone)."""
    cfg = config_arg(cfg, MonteCarloConfig)
    out_dir = path_arg(out_dir, "out_dir")
    runner = with_blas_threads(config_arg(RunnerConfig() if runner is None else runner, RunnerConfig, "runner"))
    t_start = time.perf_counter()
    check_filter_rate(cfg, truth_scenario(cfg))
    job = campaign_job(cfg, out_dir)
    previous = job.open()
    truth_sha = prepare_truth(cfg, out_dir, previous, progress)
    job.header["truth_sha256"] = truth_sha
    tr = load_campaign_truth(out_dir, cfg.measurement, cfg.target)
    warn_if_unfixed_start(tr.t_s, filter_keypoints_T_m(tr.target), tr.base, cfg.measurement)
    warn_outages_outside(tr.t_s, cfg.measurement)
    # blocks filtered on another truth are redone
    done = job.resume(previous if previous and previous.get("truth_sha256") == truth_sha else None)
    head = (f"# envisat montecarlo: the validated config of this campaign at {cfg.measurement.rate_hz:g} Hz of a rate "
            f"sweep; `--config ../{CONFIG_NAME}` reruns the sweep\n" if in_sweep
            else "# envisat montecarlo: the full validated config of this campaign\n")
    atomic_write_text(os.path.join(out_dir, SWEEP_RATE_CONFIG if in_sweep else CONFIG_NAME), head + source_line()
                      + to_toml(with_target_sha256(to_dict(cfg), "montecarlo", job.header.get("target_sha256"))))
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


def read_timing(out_dir: str) -> dict | None:
    """DIR/timing.json's dict (wall times, blocks_run_now: how many blocks the last invocation ran, the rest
    kept from an earlier one); None where it is missing or unreadable."""
    try:
        with open(os.path.join(out_dir, "timing.json"), encoding="utf-8") as fh:
            timing = json.load(fh)
    except (OSError, ValueError):
        return None
    return timing if isinstance(timing, dict) else None


def _bar(cfg: MonteCarloConfig, done: dict, progress: bool):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=cfg.runs, initial=sum(e["run_stop"] - e["run_start"] for e in done.values()), unit="run",
                desc="montecarlo", mininterval=0.5)
