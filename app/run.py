"""`envisat run`: the verb over the closed loop (pipelines/closed_loop.py): MuJoCo truth -> rendered
camera frames -> the space camera -> the Tracker (cold start from the images; `--warm-start` hands each run's
filter the truth plus a draw from P0, for filter studies). The truth only scores.

RUN_DIR gets truth.npz, est.npz (Estimates), det.npz (run 0's detections and the tracker's per-frame columns),
errors.png, run.config.toml, summary.json (scores, timings, real-time factor) and recording.rrd, streamed frame
by frame (`--spawn` or `--connect URL` send it to a live viewer instead).
"""

from __future__ import annotations

import argparse
import os

from envisat_pose.config import InputError


def default_weights_path() -> str:
    """The shipped detector weights (perception.weights.shipped_weights_path); InputError when absent."""
    from envisat_pose.perception.weights import shipped_weights_path

    return shipped_weights_path()


def with_default_weights(data: dict) -> dict:
    """A config dict with the shipped weights where it names none (the run and track verbs' default)."""
    if not data.get("weights"):
        data["weights"] = default_weights_path()
    return data


def check_weights(path: str) -> None:
    """InputError when the weights file does not exist (before any work)."""
    if not os.path.isfile(path):
        raise InputError(f"--weights {path!r}: no such file")


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
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="output folder (created, parents too; files are "
                   "replaced when the run completes)")
    p.set_defaults(func=run_cli)


def add_recording_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--spawn", action="store_true", help="stream the recording to a new local Rerun viewer")
    g.add_argument("--connect", metavar="URL", help="stream the recording to a running viewer "
                   "(e.g. rerun+http://127.0.0.1:9876/proxy) instead of RUN_DIR/recording.rrd")


def recording_sink(args: argparse.Namespace, path: str) -> str:
    """The recording sink of the flags (Rerun's own examples' --save/--spawn/--connect)."""
    if getattr(args, "spawn", False):
        return "spawn"
    if getattr(args, "connect", None):
        return f"connect:{args.connect}"
    return f"save:{os.path.abspath(path)}"


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="default", help="named scenario (`envisat scenarios` lists them)")
    p.add_argument("--duration-s", type=float, help="simulated time, s (default: the scenario's)")
    p.add_argument("--config", metavar="FILE.toml", help="run config (sections image, filter, tracker; top-level keys)")
    p.add_argument("--weights", metavar="W.safetensors",
                   help="detector weights (default: the shipped models/detector.safetensors)")
    p.add_argument("--runs", type=int, help="closed loops on the same truth (camera noise; default 1)")
    p.add_argument("--workers", type=int, help="processes for --runs (default: min(runs, CPU cores))")
    p.add_argument("--seed", type=int, help="root seed (default 0)")
    p.add_argument("--warm-start", action="store_true",
                   help="start each run's filter from the truth plus a draw from P0 (filter studies) instead of cold")
    p.add_argument("--no-roi", action="store_true", help="always run the detector's coarse pass (no region of interest)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)


def run_defaults(scenario: str) -> dict:
    """What a named scenario sets of a run config (under --config and the flags): its name, the tracker's filter
    under the scenario's [filter] table, its duration and its measurement rate (the camera's). Unknown names raise
    ConfigError listing the known ones. The benchmarks resolve their runs from these too."""
    from envisat_pose.app.scenarios import job_defaults
    from envisat_pose.pipelines.tracker import TRACKER_FILTER

    scen = job_defaults(scenario)
    defaults: dict = {"scenario": scenario, "filter": {**TRACKER_FILTER, **scen.get("filter", {})}}
    if "duration_s" in scen:
        defaults["duration_s"] = scen["duration_s"]
    if "rate_hz" in scen.get("measurement", {}):  # the camera runs at the scenario's measurement rate
        defaults["rate_hz"] = scen["measurement"]["rate_hz"]
    return defaults


def resolve_config(args: argparse.Namespace):
    """Defaults, then the scenario's [filter] table and duration, then --config, then the flags; validated
    before any work."""
    flags = {"duration_s": args.duration_s, "runs": args.runs, "seed": args.seed, "weights": args.weights,
             "workers": args.workers, "warm_start": True if args.warm_start else None,
             "tracker.roi.enabled": False if args.no_roi else None}
    return run_config(args.scenario, flags, args.config)


def run_config(scenario: str, flags: dict, config_path: str | None = None):
    """The RunConfig `envisat run` runs for a named scenario, a config file and flags {'section.key': value}
    (None: not given) over them, resolved by config.resolve_job_config (the scenario's defaults, then the file,
    then the flags) and validated before any work: what the tests and benchmarks build their runs with too."""
    from envisat_pose.config import resolve_job_config
    from envisat_pose.pipelines.run_config import RunConfig, finish_config, stage_types

    stage_types()

    def complete(data: dict) -> dict:
        if "workers" not in data:  # one process per run, at most one per core
            runs = data.get("runs", 1)
            data["workers"] = max(1, min(runs if isinstance(runs, int) else 1, os.cpu_count() or 1))
        return with_default_weights(data)

    cfg = resolve_job_config(RunConfig, run_defaults(scenario), config_path, {**flags, "scenario": scenario},
                             complete)
    check_weights(cfg.weights)
    return finish_config(cfg)


def print_table(summary: dict) -> None:
    """The scores (pipelines/scoring.py: first track, false locks, statistics over every frame from the first
    declared tracking on which the tracker claims an estimate) and the time per stage."""
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
          f"{_fmt(sc['range_bias_m'], 4)} m")
    print(f"settled (< 10 cm and < 1 deg to the end): {s['settled']}/{s['runs']}, after median "
          f"{_fmt(settle['median'])} s, max {_fmt(settle['max'])} s")
    t = summary["timing_ms_per_frame"]
    print("per frame (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items())
          + f"; real-time factor {summary['real_time_factor_one_run']:.1f}x (one run)")


def _fmt(v, digits: int = 0) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def run_cli(args: argparse.Namespace) -> int:
    from envisat_pose.pipelines.closed_loop import output_paths, run_closed_loop
    from envisat_pose.runner import make_out_dir

    from envisat_pose.io import staged_folder

    cfg = resolve_config(args)
    make_out_dir(args.out, parents=True)
    names = [os.path.basename(p) for p in output_paths(args.out).values()]
    with staged_folder(args.out, names) as stage:  # moved into --out when complete; an interrupt leaves it as it was
        sink = recording_sink(args, output_paths(stage)["recording"])
        summary = run_closed_loop(cfg, stage, progress=not args.quiet, sink=sink)
    print_table(summary)
    rec = f"recording.rrd ({summary['recording_bytes'] / 2**20:.1f} MiB; `envisat view {args.out}`)" \
        if sink.startswith("save:") else "the recording went to the viewer"
    print(f"wrote {args.out}: est.npz, det.npz, truth.npz, errors.png, run.config.toml, summary.json, {rec}")
    return 0
