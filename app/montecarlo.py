"""`envisat montecarlo`: the verb over the campaign pipeline (pipelines/campaigns/campaign.py): a Monte Carlo
campaign of the batched UKF over one MuJoCo truth in resumable blocks, or a rate sweep of such campaigns. Here:
the flags, the config's resolution (the campaign's, the sweep's, the runner's) and the printed lines (their text:
pipelines/campaigns/lines.py); what the campaign writes into DIR is described in the pipeline.
"""

from __future__ import annotations

import argparse
import os
import time

from envisat_pose.app.common import MEASUREMENT_FLAGS, add_common, check_rrd_output, init_error_line
from envisat_pose.app.flag_rules import check_noise_flags, job_scenario
from envisat_pose.config import InputError, check
from envisat_pose.pipelines.campaigns.campaign import FIGURES, MonteCarloConfig, read_timing, run_campaign
from envisat_pose.pipelines.campaigns.campaign_config import runs_words
from envisat_pose.pipelines.campaigns.lines import resume_note, summary_line, sweep_line, sweep_resume_note
from envisat_pose.pipelines.campaigns.sweep import SWEEP_FIGURE, run_sweep, sweep_for
from envisat_pose.pipelines.jobs import resolve_job
from envisat_pose.pools import RunnerConfig

FLAGS = {**{k: "--" + k.replace("_", "-") for k in "scenario runs target duration_s block_runs settle_s "
                                                   "init_error_scale workers".split()}, **MEASUREMENT_FLAGS,
         "rrd": "--rrd"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("montecarlo",
        help="Monte Carlo campaign of the UKF on one simulated truth: statistics, PCRLB, figures, summary.json",
        description="Simulate the scenario's truth once, filter N Monte Carlo runs in blocks (parallel, resumable) "
        "and write DIR/campaign.npz, summary.json, timing.json, the figures and montecarlo.config.toml.",
    )
    p.add_argument("--scenario", metavar="NAME",
                   help="named truth scenario (`envisat scenarios` lists them) or a scenario file NAME.toml; its "
                   "duration, [measurement] and [filter] tables are the defaults under --config and the flags "
                   "(default: the --config file's `scenario`, as montecarlo.config.toml records it)")
    p.add_argument("--runs", type=int, help="number of Monte Carlo runs (default 100)")
    p.add_argument("--target", metavar="FILE.xml", help="the target's MJCF file (default: the scenario's, ENVISAT): "
                   "the truth tumbles with its inertia, the filter measures its keypoints")
    add_common(p, out="campaign folder (rerun on it to resume)", config="campaign config (tables measurement, "
               "filter; runs, seed...)", seed="root seed (default 0)", flag_names=FLAGS)
    p.add_argument("--duration-s", type=float, help="simulated time, s (default: the scenario's, 1800 for "
                   "default, 3600 for eclipse)")
    p.add_argument("--rate-hz", type=float, help="filter/measurement rate, Hz (default: the scenario's; 1 for default)")
    p.add_argument("--measurements", choices=["markers3d", "pixels", "pixels+range"],
                   help="what is measured of each visible keypoint (default: the scenario's; markers3d for default)")
    p.add_argument("--sigma-m", type=float,
                   help="3D keypoint noise per axis, m (default: the scenario's; 0.02 for default)")
    p.add_argument("--sigma-px", type=float, help="pixel noise per axis, px (default: the scenario's; 1 for default)")
    p.add_argument("--max-markers", type=int, help="use at most N keypoints per step, the first visible in the "
                   "target's order (A..H for ENVISAT; default all)")
    p.add_argument("--rates-hz", type=float, nargs="+", metavar="HZ",
                   help="a rate sweep: one campaign per filter rate (default: the --config file's [sweep] "
                   "rates_hz, as a sweep's montecarlo.config.toml records it, else the scenario's)")
    p.add_argument("--init-error-scale", type=float, metavar="S",
                   help="draw each run's initial error from (S x P0's sigmas)^2 while the filter is told P0: a filter "
                   "started with the wrong uncertainty (default 1)")
    p.add_argument("--block-runs", type=int, help="runs per block (one task; default 125)")
    p.add_argument("--settle-s", type=float, help="statistics after this time, s (default half, at most 600 s)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--backend", choices=["local", "dask"], default="local", help="process pool or Dask")
    p.add_argument("--scheduler", metavar="ADDRESS", help="with --backend dask: an existing scheduler")
    p.add_argument("--rrd", metavar="FILE.rrd",
                   help="also write a Rerun recording: truth, run 0's estimate with its 3-sigma ellipsoid, the kept "
                   "sample runs' errors with the campaign's +-3 sigma bands (`envisat view FILE`)")
    p.set_defaults(func=run_montecarlo, resumable=True)


def resolve_config(args: argparse.Namespace) -> MonteCarloConfig:
    """The scenario's campaign (pipelines.jobs.resolve_job: its duration, [measurement] and [filter] tables and
    [eclipse] outages), then the file, then the flags; validated before any work."""
    flags = {
        "runs": args.runs, "seed": args.seed, "duration_s": args.duration_s, "target": args.target,
        "block_runs": args.block_runs, "settle_s": args.settle_s, "init_error_scale": args.init_error_scale,
        "measurement.kind": args.measurements, "measurement.sigma_m": args.sigma_m,
        "measurement.sigma_px": args.sigma_px, "measurement.max_markers": args.max_markers,
        "measurement.rate_hz": args.rate_hz}
    return resolve_job("montecarlo", job_scenario(args.scenario, args.config, required=True), args.config, flags)


def runner_config(args: argparse.Namespace):
    """The core runner's settings (run_campaign gives each worker its BLAS thread share)."""

    check(args.workers >= 1, "workers", args.workers, "at least 1 worker")
    check(args.scheduler is None or args.backend == "dask", "scheduler", args.scheduler,
          "an address only with --backend dask")
    runner = RunnerConfig(args.backend, args.workers, args.scheduler)
    runner.validate()
    return runner


def run_montecarlo(args: argparse.Namespace) -> int:
    cfg = resolve_config(args)
    check_noise_flags(args, cfg.measurement.kind)
    runner = runner_config(args)
    sweep = sweep_for(cfg, args.rates_hz, rate_given=args.rate_hz is not None, config_path=args.config)
    if args.rrd:
        if sweep is not None:
            raise InputError("--rrd records one campaign, not a rate sweep")
        check_rrd_output(args.rrd)
    t0 = time.perf_counter()
    if sweep is not None:
        result = run_sweep(cfg, sweep, args.out, runner, progress=not args.quiet)
        resumed = sweep_resume_note(result["rates_hz"], cfg.n_blocks,  # each rate's campaign's timing.json
                                    [read_timing(os.path.join(args.out, f)) for f in result["campaigns"]])
        print(f"wrote {args.out}: {len(sweep.rates_hz)} campaigns of {runs_words(cfg.runs)}, sweep.json, "
              f"{SWEEP_FIGURE} ({time.perf_counter() - t0:.1f} s{resumed})")
        print(sweep_line(result))
        return 0
    summary = run_campaign(cfg, args.out, runner, progress=not args.quiet, rrd=args.rrd)
    resumed = resume_note(cfg.n_blocks, read_timing(args.out))
    print(f"wrote {args.out}: {runs_words(cfg.runs)} x {summary['steps']} steps, campaign.npz, summary.json, "
          f"{len(FIGURES)} figures ({time.perf_counter() - t0:.1f} s{resumed})")
    print(summary_line(summary))
    if cfg.init_error_scale != 1.0:
        print(init_error_line(cfg.init_error_scale))
    if args.rrd:  # what write_recording logs (campaign_outputs.py)
        target = (summary.get("target") or {}).get("name", "the target")
        runs = runs_words(min(cfg.sample_runs, cfg.runs))
        print(f"wrote {args.rrd} (Rerun recording of {target} over {summary['steps']} steps: the truth, run 0's "
              f"estimate with its 3-sigma ellipsoid, the errors of {runs} with the "
              f"campaign's +-3 sigma bands, the mean NEES with its band; open it with `envisat view {args.rrd}`)")
    return 0
