"""`envisat calibrate`: fit the detector's covariance scale on held-out labelled frames and ship it in the weights;
on held-out sequences, also the error model a filter needs.

The network's 2x2 covariance per corner is scaled by one factor s (C -> s C) so that the mean of e^T C^-1 e over
correctly named visible corners is 2, the chi-square-2 mean (perception/calibrate.py). The factor goes into the
weights file's metadata (`cov_scale`), where `load_detector` and the verbs that detect read it; the result per
corruption group is printed and stored beside it (`cov_calibration`).

When every --data folder is a sequence (`envisat generate --mode sequence`: consecutive frames of one simulated
truth), the frame-to-frame correlation of the errors, the AR(1) coefficient, the variance inflation for a filter
that takes them as white and the residual bias (apparent scale, radial error) are measured too
(perception/errormodel.py) and stored as `error_model` (the ErrorModel's JSON: what `load_detector` exposes as
`detector.error_model`) and `error_model_record` (every number measured). `--roi labels` detects in the region
of interest the labels give (the closed loop's, with a perfect prior) instead of the coarse pass.

`--refine` calibrates the sub-pixel refinement's covariance instead (DetectConfig.refine, perception/refine.py):
the variance floor f added to the line fits' covariances of the refined corners (C + f I; the fits see the
pixel noise, not the misfit of the model), written as `refine_cov_floor_px2` (with `refine_cov_calibration`);
the network's cov_scale and the error model are left as they are. `--target FILE.xml` fits another target's
keypoint detector instead: a sigma per keypoint (pipelines/detector/calibrate_target.py; detect's cov_px).
"""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_common, add_skip_damaged_argument, skipped_line
from envisat_pose.app.detect import detector_inputs
from envisat_pose.config import InputError, resolve_job_config
from envisat_pose.out_dirs import check_out_file
from envisat_pose.pipelines.detector.calibrate import (
    MAX_LAG,
    CalibrateJobConfig,
    error_model_lines,
    fit_face_cue,
    run_calibration,
)
from envisat_pose.pipelines.detector.calibrate_target import run_calibrate_target, sigma_table
from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig
from envisat_pose.shard_reader import skip_hint
from envisat_pose.target import other_target


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit the detector's pixel-covariance scale (and, on sequences, its error model); write weights with it",
        description="Detect the corners of every frame of held-out labelled datasets (not used in training), "
        "take the correctly named visible corners, fit the scale s that brings the mean e^T (s C)^-1 e to 2, and "
        "write a copy of the weights with s in their metadata. Prints the calibration per corruption group. When "
        "every dataset is a sequence (envisat generate --mode sequence), also measures the errors' frame-to-frame "
        "autocorrelation, AR(1) coefficient, variance inflation and residual bias, stored as 'error_model'.",
    )
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped "
                   "weights; with --target FILE.xml, FILE_detector.safetensors beside it)")
    p.add_argument("--target", metavar="FILE.xml", help="another spacecraft's MJCF file: fit its keypoint detector's "
                   "sigma per keypoint on held-out frames of it (keypoint_sigma_px: detect --target's cov_px)")
    p.add_argument("--data", required=True, nargs="+", metavar="DIR",
                   help="held-out labelled dataset folder(s) (shards); one sequence per folder")
    p.add_argument("--out", required=True, metavar="OUT.safetensors", help="calibrated weights (may equal --weights)")
    p.add_argument("--roi", choices=("coarse", "labels"), default="coarse",
                   help="coarse: the detector's own coarse pass (default); labels: the region of interest of the "
                   "labelled corners (extent x the crop margin, at least 64 px), as the closed loop gives it")
    p.add_argument("--keep-scale", action="store_true",
                   help="leave the weights' cov_scale and cov_calibration as they are (write the error model only)")
    p.add_argument("--refine", action="store_true",
                   help="fit the sub-pixel refinement's covariance floor (refine_cov_floor_px2) on the refined "
                   "corners instead; cov_scale and the error model are kept")
    p.add_argument("--face-cue", action="store_true",
                   help="fit the half-turn's appearance cue (perception/facecue.py) on the labelled frames of --data "
                   "instead, its temperature on --held-out; stored as 'face_cue'")
    p.add_argument("--held-out", nargs="+", metavar="DIR",
                   help="with --face-cue: labelled folders (not in --data) that fit the cue's temperature and its "
                   "record (default: the odd frames of --data, the even ones fitting the cue)")
    p.add_argument("--max-lag", type=int, default=20, help="autocorrelation lags measured (default 20)")
    p.add_argument("--limit", type=int, help="only the first N frames of each dataset")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's, at most the usable cores)")
    add_common(p)  # the shared --quiet
    add_skip_damaged_argument(p)
    p.set_defaults(func=run_calibrate_cli, flag_names={k: "--" + k.replace("_", "-") for k in
                                                       "data held_out out target weights".split()})


def _print_groups(before: dict, after: dict) -> None:
    print(f"{'group':12s} {'corners':>8s} {'NEES raw':>9s} {'NEES calibrated':>16s}")
    for g in before:
        print(f"{g:12s} {before[g]['count']:8d} {before[g]['mean_nees']:9.2f} {after[g]['mean_nees']:16.2f}")


def resolve_config(args: argparse.Namespace):
    """The job's config from the flags (after detector_inputs: the weights file resolved), validated."""

    flags = {"weights": args.weights, "roi": args.roi, "keep_scale": bool(args.keep_scale),
             "refine": bool(args.refine), "max_lag": args.max_lag, "limit": args.limit,
             "skip_damaged": bool(args.skip_damaged)}
    return resolve_job_config(CalibrateJobConfig, {}, None, flags)


def run_calibrate_cli(args: argparse.Namespace) -> int:
    detector_inputs(args)
    if not 1 <= args.max_lag <= MAX_LAG:
        raise InputError(f"--max-lag {args.max_lag}: expected 1 to {MAX_LAG} lags (pipelines/detector/calibrate.py)")
    check_out_file(args.out)
    if other_target(args.target):
        return run_calibrate_target_cli(args)
    if args.held_out and not args.face_cue:
        raise InputError("--held-out belongs to --face-cue")
    if args.face_cue:
        if args.refine or args.keep_scale or args.roi != "coarse":
            raise InputError("--face-cue fits the appearance cue alone: drop --refine, --keep-scale and --roi")
        with skip_hint():
            record = fit_face_cue(args.weights, args.data, args.held_out or [], args.out, args.limit, not args.quiet,
                                  args.skip_damaged)
        print(f"face cue: {record['fit_regions']} regions fitted; on {record['held_out_frames_with_a_face']} "
              f"held-out frames: right {record['right_share']:.1%}, decided {record['decided_share_at_0.1']:.1%} "
              f"(wrongly {record['decided_wrong_share_at_0.1']:.1%}), temperature {record['temperature']:.3g}; "
              f"wrote {args.out}")
        if record["skipped_damaged_shards"]:
            print(skipped_line(record["skipped_damaged_shards"]))
        return 0
    with skip_hint():
        res = run_calibration(resolve_config(args), args.data, args.out, progress=not args.quiet)
    if res["skipped"]:
        print(skipped_line(res["skipped"]))
    _print_groups(res["before"], res["after"])
    if res["refine"]:
        print(f"refine_cov_floor_px2 {res['floor']:.4g} (mean e^T C^-1 e 2.00 on {res['corners']} refined corners, "
              f"{res['record']['refined_share']:.0%} of those named right); wrote {args.out}")
        return 0
    model, record = res["error_model"], res["error_model_record"]
    if model is not None:
        print("\n".join(error_model_lines(model, record)))
    else:
        print(res["removed_error_model"] or "not every --data folder is a sequence (envisat generate --mode sequence): "
              "no error model")
    kept = " (kept the file's cov_scale)" if args.keep_scale else ""
    print(f"cov_scale {res['scale']:.4g} (mean e^T C^-1 e 2.00 on {res['corners']} corners){kept}; wrote {args.out}")
    return 0


def run_calibrate_target_cli(args: argparse.Namespace) -> int:
    """`envisat calibrate --target FILE.xml`: another target's keypoint detector (the corners' own flags refused)."""
    given = [f for f, on in (("--face-cue", args.face_cue), ("--held-out", args.held_out), ("--refine", args.refine),
                             ("--keep-scale", args.keep_scale), ("--roi", args.roi != "coarse")) if on]
    if given:
        raise InputError(f"{given[0]}: ENVISAT's corner detector's; not with --target")
    cfg = resolve_job_config(TargetDetectJobConfig, {}, None, {"target": args.target, "weights": args.weights,
                                                               "limit": args.limit, "skip_damaged": args.skip_damaged})
    with skip_hint():
        record = run_calibrate_target(cfg, args.data, args.out, progress=not args.quiet)
    print(sigma_table(record))
    if record["error_model"] is not None:  # every --data folder a sequence: the errors' frame-to-frame model
        print("\n".join(error_model_lines(record["error_model"], record["error_model_record"])))
    if record["removed_error_model"]:  # random views after sequences: the earlier error model is gone
        print(record["removed_error_model"])
    print(f"{record['calibrated']} of {len(record['count'])} keypoints calibrated ({record['corners']} correct "
          f"detections in {record['frames']} frames); wrote {args.out}")
    return 0
