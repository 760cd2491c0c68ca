"""`envisat simulate`: the verb over the simulate pipeline (pipelines/campaigns/simulate.py): the MuJoCo truth of
a scenario, written as the design's truth trajectory (run.npz). Here: the flags, the config and the printed lines."""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_common
from envisat_pose.app.flag_rules import job_scenario
from envisat_pose.datagen.scenario import ScenarioConfig
from envisat_pose.pipelines.campaigns.simulate import run_simulate as run_pipeline


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate the tumbling target and the chaser (MuJoCo truth) and write run.npz",
        description="Simulate the truth of a scenario with MuJoCo (RK4, relative-orbit gravity plugin) and write "
        "the truth trajectory: t_s, x (12 states), chaser orbit, the keypoints in C (corners_C_m), visibility, "
        "config_json.",
    )
    add_common(p, out="output .npz (default run.npz)", out_default="run.npz", out_metavar="RUN.npz",
               config="scenario config (sections orbit, target, relative)",
               seed="root seed of the random initial attitude (default 0)", flag_names={"rrd": "--rrd"})
    p.add_argument("--scenario",
                   help="named scenario the config starts from (`envisat scenarios` lists them; default: the --config "
                   "file's `scenario`, as a written run.config.toml records it, else default)")
    p.add_argument("--duration-s", type=float, help="simulated time, s (default: the scenario's, 1800)")
    p.add_argument("--dt-s", type=float, help="output step, s (default 1)")
    p.add_argument("--target", metavar="FILE.xml", help="the target's MJCF file (its inertia drives the tumble, its "
                   "kp_ sites are the keypoints; default models/envisat.xml)")
    p.add_argument("--plot", action="store_true", help="also write a PNG of the 12 states next to --out")
    p.add_argument("--rrd", metavar="FILE.rrd", help="also write a Rerun recording of the truth (`envisat view FILE`)")
    p.set_defaults(func=run_simulate_cli)


def resolve_config(args: argparse.Namespace) -> ScenarioConfig:
    """The named scenario's truth tables (pipelines.jobs.resolve_job), then the file, then the flags; validated
    before any work."""
    from envisat_pose.pipelines.jobs import resolve_job

    flags = {"duration_s": args.duration_s, "dt_s": args.dt_s, "seed": args.seed, "target.file": args.target}
    return resolve_job("simulate", job_scenario(args.scenario, args.config), args.config, flags)


def run_simulate_cli(args: argparse.Namespace) -> int:
    cfg = resolve_config(args)
    res = run_pipeline(cfg, args.out, plot=args.plot, rrd=args.rrd, progress=not args.quiet, label=cfg.scenario)
    traj = res["truth"]
    print(f"wrote {res['truth_file']} ({len(traj.t_s)} samples over {traj.t_s[-1]:.0f} s), config {res['config_toml']}")
    if res["plot"]:
        print(f"wrote {res['plot']}")
    if res["rrd"]:
        print(f"wrote {args.rrd} (Rerun recording; open it with `envisat view {args.rrd}`)")
    return 0
