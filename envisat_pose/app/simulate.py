"""`envisat simulate`: the MuJoCo truth of a scenario, written as the design's truth trajectory (run.npz)."""

from __future__ import annotations

import argparse

from envisat_pose.datagen.scenario import ScenarioConfig, scenario_dict
from envisat_pose.config import InputError, resolve_job_config, to_dict, to_toml
from envisat_pose.io import atomic_write_text, check_writable_output


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate the tumbling target and the chaser (MuJoCo truth) and write run.npz",
        description="Simulate the truth of a scenario with MuJoCo (RK4, relative-orbit gravity plugin) and write "
        "the truth trajectory: t_s, x (12 states), chaser orbit, corners in C, visibility, config_json.",
    )
    p.add_argument("--config", metavar="FILE.toml", help="scenario config (sections orbit, target, relative)")
    p.add_argument("--scenario", default="default",
                   help="named scenario the config starts from (default: default; `envisat scenarios` lists them)")
    p.add_argument("--duration-s", type=float, help="simulated time, s (default: the scenario's, 1800)")
    p.add_argument("--dt-s", type=float, help="output step, s (default 1)")
    p.add_argument("--seed", type=int, help="root seed of the random initial attitude (default 0)")
    p.add_argument("--out", default="run.npz", help="output .npz (default run.npz)")
    p.add_argument("--plot", action="store_true", help="also write a PNG of the 12 states next to --out")
    p.add_argument("--rrd", metavar="FILE.rrd", help="also write a Rerun recording of the truth (`envisat view FILE`)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_simulate)


def resolve_config(args: argparse.Namespace) -> ScenarioConfig:
    """Defaults, then the named scenario's truth tables, then the file, then the flags; validated before any work."""
    flags = {"duration_s": args.duration_s, "dt_s": args.dt_s, "seed": args.seed}
    return resolve_job_config(ScenarioConfig, scenario_dict(args.scenario), args.config, flags)


def output_paths(out: str) -> tuple[str, str, str]:
    """run.npz -> (run.npz, run.config.toml, run.png)."""
    stem = out[:-4] if out.endswith(".npz") else out
    return out, stem + ".config.toml", stem + ".png"


def run_simulate(args: argparse.Namespace) -> int:
    if not args.out.endswith(".npz"):
        raise InputError(f"--out {args.out!r}: expected a path ending in .npz")
    cfg = resolve_config(args)
    out, cfg_path, png = output_paths(args.out)
    check_writable_output(out)
    if args.rrd:
        from envisat_pose.app.view import check_rrd_output

        check_rrd_output(args.rrd)
    from envisat_pose.datagen.truth import simulate

    traj = simulate(cfg, progress=not args.quiet)
    traj.save(out)
    atomic_write_text(cfg_path, "# envisat simulate: the full validated config of this run\n" + to_toml(to_dict(cfg)))
    print(f"wrote {out} ({len(traj.t_s)} samples over {traj.t_s[-1]:.0f} s), config {cfg_path}")
    if args.plot:
        from envisat_pose.analysis.plots import plot_states

        plot_states(traj.t_s, traj.x, png, title=f"ENVISAT truth, scenario {args.scenario!r}, seed {cfg.seed}",
                    visible=traj.visible)
        print(f"wrote {png}")
    if args.rrd:
        from envisat_pose.analysis.recording import write_truth_recording

        write_truth_recording(args.rrd, traj)
        print(f"wrote {args.rrd} (Rerun recording; open it with `envisat view {args.rrd}`)")
    return 0
