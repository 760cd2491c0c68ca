"""`envisat run`: the verb over the closed loop (pipelines/runs/closed_loop.py): MuJoCo truth -> rendered
camera frames -> the space camera -> the Tracker (cold start from the images; `--warm-start` hands each run's
filter the truth plus a draw from P0, for filter studies). The truth only scores.

RUN_DIR gets truth.npz, est.npz (Estimates), det.npz (run 0's detections and the tracker's per-frame columns),
errors.png, run.config.toml, summary.json (scores, timings, real-time factor) and recording.rrd, streamed frame
by frame (`--spawn` or `--connect URL` send it to a live viewer instead).
"""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_bf16_argument, add_common, add_recording_arguments, recording_sink
from envisat_pose.app.flag_rules import job_scenario
from envisat_pose.pipelines.runs.outputs import refused_clause


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="the online closed loop: MuJoCo truth -> rendered camera frames -> the tracker (detector + UKF)",
        description="Run the closed loop on a named scenario: the MuJoCo truth advances, MuJoCo renders the chaser "
        "camera with the space-camera model at the filter rate and the tracker (the same one `envisat track` "
        "runs on a user's frames) starts cold from the images: PnP poses, the half-turn hypotheses, a batch fit, "
        "then the UKF with the detector's covariance. The truth only scores. Writes est.npz, det.npz, truth.npz, "
        "errors.png, run.config.toml, summary.json and recording.rrd into --out (`envisat view RUN_DIR`).",
    )
    add_run_arguments(p)
    add_common(p, out="output folder (created, parents too; files are replaced when the run completes)",
               out_metavar="RUN_DIR", quiet=False, flag_names={"target": "--target"})
    p.set_defaults(func=run_cli)


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", help="named scenario (`envisat scenarios` lists them; default: the --config "
                   "file's, else default)")
    p.add_argument("--duration-s", type=float, help="simulated time, s (default: the scenario's)")
    p.add_argument("--runs", type=int, help="closed loops on the same truth (camera noise; default 1)")
    p.add_argument("--workers", type=int, help="processes for --runs (default: min(runs, usable cores, what "
                   "the memory holds))")
    p.add_argument("--warm-start", action="store_true",
                   help="start each run's filter from the truth plus a draw from P0 (filter studies) instead of "
                   "cold; the start still earns its claim: its first frames (the tracker's confirm_frames, 5) are "
                   "acquiring, without an estimate in est.npz, until its own innovations confirm it")
    p.add_argument("--no-roi", action="store_true", help="always run the detector's coarse pass (no region of interest)")
    p.add_argument("--full-frames", action="store_true", help="render and corrupt every frame whole (default: once "
                   "tracking, only the window the tracker reads, a full frame every `full_frame_every` frames, "
                   "where ENVISAT's array cue reads)")
    p.add_argument("--target", metavar="FILE.xml", help="another spacecraft's MJCF file: MuJoCo renders it and the "
                   "tracker follows it with its keypoint detector (--weights, trained and calibrated with --target; "
                   "default: FILE_detector.safetensors beside FILE.xml, as the upper stage's ships)")
    add_common(p, config="run config (sections image, filter, tracker; top-level keys)", weights=True,
               seed="root seed (default 0)")
    add_bf16_argument(p)
    add_recording_arguments(p)


def resolve_config(args: argparse.Namespace):
    """The scenario's job (pipelines.jobs.resolve_job: its [filter] table, duration and rate), then --config,
    then the flags; validated before any work."""
    from envisat_pose.pipelines.jobs import resolve_job

    flags = {"duration_s": args.duration_s, "runs": args.runs, "seed": args.seed, "weights": args.weights,
             "workers": args.workers, "warm_start": True if args.warm_start else None,
             "tracker.roi.enabled": False if args.no_roi else None,
             "image.target": args.target, "render_window": False if args.full_frames else None,
             "bf16": True if args.bf16 else None}
    return resolve_job("run", job_scenario(args.scenario, args.config), args.config, flags)


def print_table(summary: dict) -> None:
    """The scores (pipelines/runs/scoring.py: first track, false locks, statistics over every frame from the first
    declared tracking on which the tracker claims an estimate), the mean NIS where the summary has it (`track`
    prints it in its status line) and the time per stage."""
    s = summary["scores"]
    ttc, settle, sc = s["time_to_first_correct_track_s"], s["time_to_settle_s"], s["scored"]
    print(f"{summary['start']} start: {s['runs_tracked']}/{s['runs']} run(s) tracked, first track correct in "
          f"{s['first_track_correct']}; time to the first correct track from the first lit frame: median "
          f"{_fmt(ttc['median'])} s, max {_fmt(ttc['max'])} s; false-lock time {s['false_lock_s']:.0f} s "
          f"(attitude > 5 deg or position > 2 % of range while claiming tracking or coasting)")
    r = sc["rmse"]
    print(f"over {sc['frames']} frame(s) from the first tracking: RMSE position {_fmt(r['position'], 4)} m, velocity "
          f"{_fmt(r['velocity'], 5)} m/s, attitude {_fmt(r['attitude'], 3)} deg, rate {_fmt(r['angular_velocity'], 4)} "
          f"deg/s; mean NEES {_fmt(sc['mean_nees'], 1)} (12 expected), beyond its 99.9 % quantile "
          f"{_fmt(None if sc['nees_tail_share'] is None else 100 * sc['nees_tail_share'], 2)} % of frames; SPEC score "
          f"median {_fmt(sc['spec_score_median'], 4)}, p95 {_fmt(sc['spec_score_p95'], 4)}; range bias "
          f"{_fmt(sc['range_bias_m'], 4)} m" + (f"; mean NIS per dof {_fmt(summary['mean_nis_per_dof'], 2)} (1 "
                                               "expected)" if "mean_nis_per_dof" in summary else ""))
    print(f"settled (< 10 cm and < 1 deg to the end): {s['settled']}/{s['runs']}, after median "
          f"{_fmt(settle['median'])} s, max {_fmt(settle['max'])} s")
    t = summary["timing_ms_per_frame"]
    print("per frame (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items())
          + f"; real-time factor {summary['real_time_factor_one_run']:.1f}x (one run)")


def nothing_tracked_line(summary: dict) -> str:
    """What a loop that never tracked says (as `envisat track` says it)."""
    counts = ", ".join(f"{n} {k}" for k, n in summary["scores"]["frames_by_status"].items() if n)
    return (f"nothing tracked ({counts}): the tracker never claimed tracking, so est.npz holds no estimate "
            "(x_hat NaN, status per row)" + refused_clause(summary["run0"].get("last_cold_start_refusal")))


def _fmt(v, digits: int = 0) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def run_cli(args: argparse.Namespace) -> int:
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop

    cfg = resolve_config(args)
    sink = recording_sink(args)
    summary = run_closed_loop(cfg, args.out, progress=not args.quiet, sink=sink)  # staged: nothing half-written
    print_table(summary)
    if not summary["scores"]["runs_tracked"]:
        print(nothing_tracked_line(summary))
    rec = f"recording.rrd ({summary['recording_bytes'] / 2**20:.1f} MiB; `envisat view {args.out}`)" \
        if sink is None else "the recording went to the viewer"
    print(f"wrote {args.out}: est.npz, det.npz, truth.npz, errors.png, run.config.toml, summary.json, {rec}")
    return 0
