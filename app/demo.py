"""`envisat demo`: the project's main job on the embedded default: the closed loop (`envisat run`) on the default
scenario for 10 minutes of simulated time with the shipped detector weights, then where to look."""

from __future__ import annotations

import argparse
import os


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the closed loop on the default scenario, 10 simulated minutes with the shipped weights",
        description="Run `envisat run --scenario default --duration-s 600` with the shipped detector weights "
        "(models/detector.safetensors) and print where the recording, the plots and the summary are.",
    )
    p.add_argument("--out", default=os.path.join("out", "demo"), metavar="RUN_DIR",
                   help="output folder (default out/demo)")
    p.add_argument("--duration-s", type=float, default=600.0, help="simulated time, s (default 600)")
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped ones)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    from envisat_pose.app.run import print_table, resolve_config
    from envisat_pose.pipelines.closed_loop import output_paths, run_closed_loop
    from envisat_pose.io import staged_folder
    from envisat_pose.runner import make_out_dir

    ns = argparse.Namespace(scenario="default", duration_s=args.duration_s, config=None, weights=args.weights,
                            runs=1, workers=1, seed=0, no_roi=False, warm_start=False, quiet=args.quiet)
    cfg = resolve_config(ns)
    make_out_dir(args.out)
    print(f"envisat demo: the tracker, cold start, on scenario 'default', {cfg.duration_s:.0f} s simulated at {cfg.rate_hz:g} Hz, "
          f"weights {cfg.weights}")
    names = [os.path.basename(p) for p in output_paths(args.out).values()]
    with staged_folder(args.out, names) as stage:  # moved into --out when complete; an interrupt leaves it as it was
        summary = run_closed_loop(cfg, stage, progress=not args.quiet)
    print_table(summary)
    paths = output_paths(args.out)
    print(f"recording: {paths['recording']} ({summary['recording_bytes'] / 2**20:.1f} MiB); open it with "
          f"`envisat view {args.out}`")
    print(f"plots:     {paths['plot']}")
    print(f"summary:   {paths['summary']} (errors, time per stage, real-time factor)")
    print(f"arrays:    {paths['est']} (estimates), {paths['det']} (detections), {paths['truth']} (truth); "
          f"config {paths['config']}")
    return 0
