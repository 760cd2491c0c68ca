"""`envisat track`: the verb over pipelines/track.py: the Tracker on a user's frames (a sequence-mode generate
folder, a folder of image files, or a video), cold, with no truth; labels, where present, only score."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    from envisat_pose.app.run import add_recording_arguments

    p = sub.add_parser(
        "track",
        help="track the target in your own frames (image folder, video or generate folder): pose history with "
        "covariances, no truth needed",
        description="Run the tracker (corner detector + UKF, cold start from the images) over a sequence of "
        "frames: a folder written by `envisat generate --mode sequence`, a folder of PNG/JPEG/TIFF files whose "
        "names sort in time order (--rate-hz or --timestamps), or a video file. Every frame is checked before "
        "anything is written. Writes est.npz, det.npz, track.config.toml, summary.json, recording.rrd (and "
        "errors.png when the input carries the truth) into --out.",
    )
    p.add_argument("--images", required=True, metavar="SRC", help="generate folder, image folder or video file")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="output folder (created; files are replaced)")
    p.add_argument("--rate-hz", type=float, help="frame rate of an image folder or a video: frame k at k / R s")
    p.add_argument("--timestamps", metavar="FILE.csv", help="frame times of an image folder (columns file,t_s)")
    p.add_argument("--camera", metavar="FILE.toml", help="intrinsics fx, fy, cx, cy (px), width, height, optional "
                   "distortion (default: the MJCF's chaser_cam at the frames' size)")
    p.add_argument("--scenario", help="where the chaser's orbit and the target's dynamics come from (default: a "
                   "generate folder's own, else 'default')")
    p.add_argument("--config", metavar="FILE.toml", help="track config (orbit, filter, tracker; top-level keys)")
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped ones)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_recording_arguments(p)
    p.set_defaults(func=track_cli)


def resolve_config(args: argparse.Namespace, scenario: str):
    """Defaults, then the scenario's orbit and gravity-gradient switch, then --config, then the flags."""
    from envisat_pose.app.run import check_weights, with_default_weights
    from envisat_pose.app.scenarios import job_defaults
    from envisat_pose.config import resolve_job_config
    from envisat_pose.datagen.scenario import scenario_dict
    from envisat_pose.pipelines.track import TrackConfig, stage_types
    from envisat_pose.pipelines.tracker import TRACKER_FILTER

    stage_types()
    truth = scenario_dict(scenario)  # unknown names fail here with the known ones
    defaults = {"scenario": scenario, "orbit": dict(truth.get("orbit", {})),
                "gravity_gradient": bool(truth.get("target", {}).get("gravity_gradient", False)),
                "filter": {**TRACKER_FILTER, **job_defaults(scenario).get("filter", {})}}
    flags = {"rate_hz": args.rate_hz, "weights": args.weights}

    cfg = resolve_job_config(TrackConfig, defaults, args.config, flags, with_default_weights)
    check_weights(cfg.weights)
    return cfg


def track_cli(args: argparse.Namespace) -> int:
    from envisat_pose.app.run import recording_sink
    from envisat_pose.geometry import load_camera
    from envisat_pose.pipelines.track import (camera_from_intrinsics, check_source, open_source, output_paths,
                                              track_frames)
    from envisat_pose.runner import check_out_dir, make_out_dir

    check_out_dir(args.out)
    source = open_source(args.images, args.rate_hz or 0.0, args.timestamps)
    cfg = resolve_config(args, args.scenario or source.scenario or "default")
    if args.camera:
        camera, remap = camera_from_intrinsics(args.camera)
    else:
        first = next(iter(source.frames()))[1]
        camera, remap = load_camera().scaled(first.shape[1], first.shape[0]), None
    check_source(source, camera, progress=not args.quiet)
    make_out_dir(args.out)
    sink = recording_sink(args, output_paths(args.out)["recording"])
    summary = track_frames(cfg, source, camera, remap, args.out, sink, progress=not args.quiet)
    fb = summary["frames_by_status"]
    print(f"{summary['source']['frames']} frames: {fb['tracking']} tracking, {fb['acquiring']} acquiring, "
          f"{fb['lost']} lost; first tracking at t = {summary['first_tracking_s']} s; final status "
          f"{summary['final_status']}; mean NIS per dof {summary['mean_nis_per_dof']:.2f}")
    if "scores" in summary:
        from envisat_pose.app.run import print_table

        print_table({"scores": summary["scores"], "start": "cold", "timing_ms_per_frame": summary["timing_ms_per_frame"],
                     "real_time_factor_one_run": float(summary["source"]["frames"]) / max(summary["wall_s"], 1e-9)})
    print(f"wrote {args.out}: est.npz, det.npz, track.config.toml, summary.json"
          + (", errors.png" if "scores" in summary else "") + ", recording.rrd")
    return 0
