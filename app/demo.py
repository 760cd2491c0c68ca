"""`envisat demo`: the project's main job on the embedded default: the closed loop (`envisat run`) on the default
scenario for 10 minutes of simulated time with the shipped detector weights, then where to look."""

from __future__ import annotations

import argparse
import os

from envisat_pose.app.common import add_bf16_argument, add_common
from envisat_pose.app.run import nothing_tracked_line, print_table


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the closed loop on the default scenario, 10 simulated minutes with the shipped weights",
        description="Run `envisat run --scenario default --duration-s 600` with the shipped detector weights "
        "(models/detector.safetensors) and print where the recording, the plots and the summary are.",
    )
    p.add_argument("--duration-s", type=float, default=600.0, help="simulated time, s (default 600)")
    add_common(p, out="output folder (default out/demo)", out_default=os.path.join("out", "demo"),
               out_metavar="RUN_DIR", weights=True)
    add_bf16_argument(p)
    p.set_defaults(func=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    from envisat_pose.pipelines.common.job_defaults import weights_name
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop, run_output_paths
    from envisat_pose.pipelines.runs.run_config import RunConfig

    cfg = RunConfig(scenario="default", duration_s=args.duration_s, weights=args.weights or "", runs=1, workers=1,
                    seed=0, bf16=args.bf16)
    print(f"envisat demo: the tracker, cold start, on scenario 'default', {cfg.duration_s:.0f} s simulated at {cfg.rate_hz:g} Hz, "
          f"weights {weights_name(cfg.weights)}")
    summary = run_closed_loop(cfg, args.out, progress=not args.quiet)  # staged: an interrupt leaves --out as it was
    print_table(summary)
    if not summary["scores"]["runs_tracked"]:
        print(nothing_tracked_line(summary))
    paths = run_output_paths(args.out)
    print(f"recording: {paths['recording']} ({summary['recording_bytes'] / 2**20:.1f} MiB); open it with "
          f"`envisat view {args.out}`")
    print(f"plots:     {paths['plot']}")
    print(f"summary:   {paths['summary']} (errors, time per stage, real-time factor)")
    print(f"arrays:    {paths['est']} (estimates), {paths['det']} (detections), {paths['truth']} (truth); "
          f"config {paths['config']}")
    return 0
