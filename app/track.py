"""`envisat track`: the verb over pipelines/track.py: the Tracker on a user's frames (a sequence-mode generate
folder, a folder of image files, or a video), cold, with no truth; labels, where present, only score."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    from envisat_pose.pipelines.dataset_inputs import add_skip_damaged_argument
    from envisat_pose.app.run import add_recording_arguments

    p = sub.add_parser(
        "track",
        help="track the target in your own frames (image folder, video or generate folder): pose history with "
        "covariances, no truth needed",
        description="Run the tracker (corner detector + UKF, cold start from the images) over a sequence of "
        "frames: a folder written by `envisat generate --mode sequence`, a folder of PNG/JPEG/TIFF files whose "
        "names sort in time order (natural order: frame_2 before frame_10; hidden files ignored; --rate-hz or "
        "--timestamps), or a video file. Every frame is checked before anything is written; the outputs are "
        "moved into --out only when complete (an interrupt leaves an earlier run's as they were). Writes est.npz, "
        "det.npz, track.config.toml, summary.json, recording.rrd (and errors.png when the input carries the "
        "truth) into --out.",
    )
    p.add_argument("--images", required=True, metavar="SRC", help="generate folder, image folder or video file")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="output folder (created, parents too; files are "
                   "replaced)")
    p.add_argument("--rate-hz", type=float, help="frame rate of an image folder or a video: frame k at k / R s")
    p.add_argument("--timestamps", metavar="FILE.csv", help="frame times of an image folder (columns file,t_s)")
    p.add_argument("--bit-depth", type=int, metavar="BITS", help="bits of the data in 16-bit image files: 10, 12, "
                   "14 or 16 (default: the smallest that holds the sequence's maximum, reported)")
    p.add_argument("--camera", metavar="FILE.toml", help="intrinsics fx, fy, cx, cy (px), width, height, optional "
                   "distortion (default: the MJCF's chaser_cam at the frames' size)")
    p.add_argument("--scenario", help="where the chaser's orbit and the target's dynamics come from (default: a "
                   "generate folder's own, else 'default')")
    p.add_argument("--config", metavar="FILE.toml", help="track config (orbit, filter, tracker; top-level keys)")
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped ones)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_skip_damaged_argument(p)
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
    from envisat_pose.pipelines.dataset_inputs import skip_hint, skipped_line
    from envisat_pose.app.run import recording_sink
    from envisat_pose.pipelines.build import load_camera
    from envisat_pose.pipelines.camera_file import camera_from_intrinsics
    from envisat_pose.pipelines.frames import open_source, scan_source
    from envisat_pose.pipelines.outputs import status_line
    from envisat_pose.pipelines.track import output_paths, track_frames
    from envisat_pose.runner import check_out_dir, make_out_dir

    check_out_dir(args.out)
    with skip_hint():
        source = open_source(args.images, args.rate_hz or 0.0, args.timestamps, args.bit_depth, args.skip_damaged)
    cfg = resolve_config(args, args.scenario or source.scenario or "default")
    camera, remap = camera_from_intrinsics(args.camera) if args.camera else (None, None)
    size = None if camera is None else (camera.width_px, camera.height_px)
    pixels = scan_source(source, size, min_frames=cfg.tracker.acquire.frames, progress=not args.quiet)
    if camera is None:
        camera = load_camera(size_px=source.size_px)
    make_out_dir(args.out)
    sink = recording_sink(args, output_paths(args.out)["recording"])
    print(f"{args.images}: {len(source.t_s)} frames of {source.size_px[0]} x {source.size_px[1]} px, {pixels}")
    if source.skipped:
        print(skipped_line(source.skipped))
    summary = track_frames(cfg, source, camera, remap, args.out, None if sink.startswith("save:") else sink,
                           progress=not args.quiet)
    print(status_line(summary["source"]["frames"], summary["frames_by_status"], summary["first_tracking_s"],
                      summary["final_status"], summary["mean_nis_per_dof"]))
    if "scores" in summary:
        from envisat_pose.app.run import print_table

        print_table({"scores": summary["scores"], "start": "cold", "timing_ms_per_frame": summary["timing_ms_per_frame"],
                     "real_time_factor_one_run": summary["real_time_factor"]})
    else:
        print(f"real-time factor {summary['real_time_factor']:.1f}x")
    print(f"wrote {args.out}: est.npz, det.npz, track.config.toml, summary.json"
          + (", errors.png" if "scores" in summary else "") + (", recording.rrd" if sink.startswith("save:") else ""))
    return 0
