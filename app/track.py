"""`envisat track`: the verb over pipelines/runs/track.py: the Tracker on a user's frames (a sequence-mode generate
folder, a folder of image files, or a video), cold, with no truth; labels, where present, only score. ENVISAT by
default; --target FILE.xml another spacecraft, with its keypoint detector's --weights."""

from __future__ import annotations

import argparse

from envisat_pose.app.common import (
    add_bf16_argument,
    add_common,
    add_frame_inputs,
    add_recording_arguments,
    add_skip_damaged_argument,
    recording_sink,
    skipped_line,
)
from envisat_pose.app.flag_rules import job_scenario
from envisat_pose.app.run import print_table
from envisat_pose.out_dirs import check_out_dir
from envisat_pose.pipelines.runs.frames import open_source
from envisat_pose.pipelines.runs.outputs import status_line
from envisat_pose.shard_reader import skip_hint


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track",
        help="track the target in your own frames (image folder, video or generate folder): pose history with "
        "covariances, no truth needed",
        description="Run the tracker (detector + UKF, cold start from the images) over a sequence of frames of "
        "ENVISAT (its corner detector) or of another spacecraft (--target: its keypoint detector, trained and "
        "calibrated for it): a folder written by `envisat generate --mode sequence` of that target, a folder of "
        "PNG/JPEG/TIFF/BMP/PGM/WebP files whose names sort in time order (natural order: frame_2 before frame_10; hidden files "
        "ignored; --rate-hz or --timestamps), or a video file. Every frame is checked before anything is written; the outputs are "
        "moved into --out only when complete (an interrupt leaves an earlier run's as they were). Writes est.npz, "
        "det.npz, track.config.toml, summary.json, recording.rrd (and errors.png when the input carries the "
        "truth) into --out.",
    )
    add_frame_inputs(p)
    p.add_argument("--target", metavar="FILE.xml", help="another spacecraft's MJCF file (default: ENVISAT, "
                   "models/envisat.xml): its keypoint detector's --weights (`envisat train --target`, then `envisat "
                   "calibrate --target`; default: FILE_detector.safetensors beside FILE.xml, as the upper stage's "
                   "ships)")
    add_common(p, out="output folder (created, parents too; files are replaced)", out_metavar="RUN_DIR",
               config="track config (orbit, filter, tracker; top-level keys)", weights=True, flag_names=FLAGS)
    add_bf16_argument(p)
    add_skip_damaged_argument(p)
    add_recording_arguments(p)
    p.set_defaults(func=track_cli)


# the library's argument names -> this verb's flags (app/common.as_flags)
FLAGS = {"source": "--images", "rate_hz": "--rate-hz", "timestamps": "--timestamps", "bit_depth": "--bit-depth",
         "camera": "--camera", "skip_damaged": "--skip-damaged", "target": "--target"}


def track_cli(args: argparse.Namespace) -> int:
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.track import track_frames

    check_out_dir(args.out)
    with skip_hint():
        source = open_source(args.images, args.rate_hz or 0.0, args.timestamps, args.bit_depth, args.skip_damaged)
    cfg = resolve_job("track", job_scenario(args.scenario, args.config, None) or source.scenario or "default", args.config,
                      rate_hz=args.rate_hz, weights=args.weights, target=args.target,
                      bf16=True if args.bf16 else None)
    sink = recording_sink(args)
    summary = track_frames(cfg, source, args.camera, None, args.out, sink, progress=not args.quiet)
    w, h = summary["source"]["size_px"]
    print(f"{args.images}: {len(source.t_s)} frames of {w} x {h} px, {summary['source']['pixels']}")
    cam = summary["camera"]
    print(f"camera {cam['file'] or 'the MJCF chaser_cam'}: f {cam['f_px']:.2f} px, principal point "
          f"({cam['cx_px']:.1f}, {cam['cy_px']:.1f}) px" + (", frames undistorted to it" if cam["undistorted"] else ""))
    if source.skipped:
        print(skipped_line(source.skipped))
    print(status_line(summary["source"]["frames"], summary["frames_by_status"], summary["first_tracking_s"],
                      summary["final_status"], summary["mean_nis_per_dof"], summary["last_cold_start_refusal"]))
    if "scores" in summary:
        print_table({"scores": summary["scores"], "start": "cold", "timing_ms_per_frame": summary["timing_ms_per_frame"],
                     "real_time_factor_one_run": summary["real_time_factor"]})
    else:
        print(f"real-time factor {summary['real_time_factor']:.1f}x")
    print(f"wrote {args.out}: est.npz, det.npz, track.config.toml, summary.json"
          + (", errors.png" if "scores" in summary else "") + (", recording.rrd" if sink is None else ""))
    return 0
