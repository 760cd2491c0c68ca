"""`envisat estimate`: the verb over the estimate pipeline (pipelines/campaigns/estimate.py): the batched UKF
over R Monte Carlo runs of one MuJoCo truth (`--truth run.npz` or simulated for `--scenario NAME`), written as
est.npz. Here: the flags, the config's resolution and the printed lines.
"""

from __future__ import annotations

import argparse

from envisat_pose.analysis.stats import nees_bands
from envisat_pose.app.common import MEASUREMENT_FLAGS, add_common, init_error_line
from envisat_pose.app.flag_rules import check_noise_flags
from envisat_pose.filtering.estimator import FilterConfig, nees, nis_alarms_alone, unjudged_runs
from envisat_pose.pipelines.campaigns.campaign_config import runs_words
from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, recorded_scenario
from envisat_pose.pipelines.campaigns.estimate import run_estimate as run_pipeline
from envisat_pose.pipelines.campaigns.lines import mean_nees_words
from envisat_pose.pipelines.jobs import resolve_job
from envisat_pose.state import error_summary, unjudged_why

# the library's argument names -> this verb's flags (app/common.as_flags)
FLAGS = {"truth_path": "--truth", "scenario": "--scenario", "duration_s": "--duration-s", "rrd": "--rrd",
         "plot": "--plot", "runs": "--runs", "target": "--target", "init_error_scale": "--init-error-scale",
         **MEASUREMENT_FLAGS}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "estimate",
        help="run the UKF on a truth trajectory (R Monte Carlo runs) and write est.npz",
        description="Estimate the relative pose of the tumbling target with the batched UKF over R Monte Carlo runs "
        "(runs differ in the initial error drawn from P0 and in measurement noise) and write est.npz: t_s, x_true, "
        "x_hat, P, n_meas, nis, nis_dof, diverged, judged (whether the divergence rule judged the run), config_json.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--truth", metavar="RUN.npz", help="truth trajectory written by `envisat simulate`")
    p.add_argument("--target", metavar="FILE.xml", help="with --scenario: the spacecraft's MJCF file that flies it "
                   "(as montecarlo --target); with --truth: its target file where the path the truth records is not "
                   "found from here (its sha256 must match)")
    src.add_argument("--scenario", metavar="NAME",
                     help="simulate this named scenario (`envisat scenarios` lists them) with the MuJoCo truth first; "
                     "its [measurement] and [filter] tables are the defaults under --config and the flags")
    p.add_argument("--duration-s", type=float, help="with --scenario: simulated time, s (default: the scenario's)")
    add_common(p, out="output .npz (default est.npz); its config goes next to it", out_default="est.npz",
               out_metavar="EST.npz", config="estimate config (sections measurement, filter; runs, seed)",
               seed="root seed (default 0)", flag_names=FLAGS)
    p.add_argument("--measurements", choices=["markers3d", "pixels", "pixels+range"],
                   help="what is measured of each visible keypoint (default: the scenario's; markers3d for default)")
    p.add_argument("--sigma-m", type=float,
                   help="3D keypoint noise per axis, m (default: the scenario's; 0.02 for default)")
    p.add_argument("--sigma-px", type=float, help="pixel noise per axis, px (default: the scenario's; 1 for default)")
    p.add_argument("--sigma-range-m", type=float, help="range noise for pixels+range, m (default 0.05)")
    p.add_argument("--max-markers", type=int, help="use at most N keypoints per step, the first visible in the "
                   "target's order (A..H for ENVISAT; default all)")
    p.add_argument("--failure-prob", type=float, help="probability that a visible keypoint is lost at a step")
    p.add_argument("--outage", type=float, nargs=2, action="append", metavar=("START_S", "END_S"),
                   help="a window without measurements (repeatable)")
    p.add_argument("--rate-hz", type=float, help="filter/measurement rate, Hz (default: the scenario's; 1 for default)")
    p.add_argument("--adaptive-r", action="store_const", const=True, help="innovation-based measurement noise")
    p.add_argument("--adaptive-q", action="store_const", const=True, help="residual-based process noise")
    p.add_argument("--no-gate", action="store_const", const=True, help="switch the chi-square gate off")
    p.add_argument("--runs", type=int, help="number of Monte Carlo runs, filtered as one batch (default 1)")
    p.add_argument("--init-error-scale", type=float, metavar="S",
                   help="draw each run's initial error from (S x P0's sigmas)^2 while the filter is told P0: a filter "
                   "started with the wrong uncertainty (default 1)")
    p.add_argument("--plot", action="store_true", help="also write a PNG of the errors with 3-sigma bounds next to --out")
    p.add_argument("--rrd", metavar="FILE.rrd",
                   help="also write a Rerun recording: truth, run 0's estimate with its 3-sigma ellipsoid, every run's "
                   "errors with +-3 sigma bands (`envisat view FILE`)")
    p.set_defaults(func=run_estimate_cli)


def resolve_config(args: argparse.Namespace) -> EstimateConfig:
    """The named scenario's [measurement] and [filter] tables (with --scenario; pipelines.jobs.resolve_job), then
    the file, then the flags; validated before any work. Unknown scenario names fail with the known ones."""
    flags = {
        "measurement.kind": args.measurements,
        "measurement.sigma_m": args.sigma_m,
        "measurement.sigma_px": args.sigma_px,
        "measurement.sigma_range_m": args.sigma_range_m,
        "measurement.max_markers": args.max_markers,
        "measurement.failure_prob": args.failure_prob,
        "measurement.outages_s": [list(w) for w in args.outage] if args.outage else None,
        "measurement.rate_hz": args.rate_hz,
        "filter.adaptive_r": args.adaptive_r,
        "filter.adaptive_q": args.adaptive_q,
        "filter.gate_prob": 0.0 if args.no_gate else None,
        "runs": args.runs,
        "seed": args.seed,
        "init_error_scale": args.init_error_scale,
    }
    # a truth file's own scenario (where it records one) gives the tables a --scenario would
    scenario = args.scenario or (recorded_scenario(args.truth) if args.truth else None)
    return resolve_job("estimate", scenario, args.config, flags)


def summary(arrays: dict, fcfg: FilterConfig) -> str:
    """Errors over the second half of the run: RMS position (cm) and attitude angle (deg), ANEES with its 95 % bands
    (worded as montecarlo's: lines.mean_nees_words); the diverged
    runs, and how many of them the filter flagged alone (its NIS monitor or a failed update: nis_alarms_alone);
    runs the rule did not judge (est.npz's judged; arrays without it: unjudged_runs) counted apart, never as not
    diverged."""

    t_s = arrays["t_s"]
    T = t_s.shape[0]
    late = slice(T // 2, None)
    R, n_late = len(arrays["diverged"]), T - T // 2
    e = error_summary(t_s, arrays["x_true"], arrays["x_hat"], after_s=float(t_s[T // 2]) if T else 0.0)
    nees_rt = nees(arrays["x_true"], arrays["x_hat"], arrays["P"], fcfg.sigma_chart)
    alone = int(nis_alarms_alone(arrays["diverged"], nees_rt, fcfg).sum())
    judged = arrays.get("judged")
    unjudged = int(unjudged_runs(arrays["diverged"], T, fcfg).sum() if judged is None else (~judged).sum())
    nees_words = mean_nees_words({"nees_mean": float(nees_rt[:, late].mean()), **nees_bands(R, n_late)})
    return (f"after t = {e['after_s']:.0f} s: RMS position error {100 * e['position_m']['rms_after']:.3f} cm, RMS "
            f"attitude error {e['attitude_deg']['rms_after']:.4f} deg, {nees_words}; diverged runs "
            f"{int(arrays['diverged'].sum())}/{R}"
            + (f" ({alone} flagged by the filter alone (its NIS monitor or a failed update), their "
               "errors within the NEES rule)" if alone else "")
            + (f", {unjudged} not judged ({unjudged_why(T, fcfg.divergence_settle_steps, fcfg.divergence_window)})"
               if unjudged else ""))


def run_estimate_cli(args: argparse.Namespace) -> int:
    cfg = resolve_config(args)
    check_noise_flags(args, cfg.measurement.kind)
    res = run_pipeline(cfg, args.out, truth_path=args.truth, scenario=args.scenario, duration_s=args.duration_s,
                       plot=args.plot, rrd=args.rrd, progress=not args.quiet, target=args.target)
    cfg, arrays = res["config"], res["arrays"]
    print(f"wrote {res['est']} ({runs_words(cfg.runs)} x {len(arrays['t_s'])} steps), config {res['config_toml']}")
    print(summary(arrays, cfg.filter))
    if cfg.init_error_scale != 1.0:
        print(init_error_line(cfg.init_error_scale))
    if res["plot"]:
        print(f"wrote {res['plot']}")
    if res["rrd"]:
        print(f"wrote {args.rrd} (Rerun recording; open it with `envisat view {args.rrd}`)")
    return 0
