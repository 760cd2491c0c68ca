"""`envisat evaluate`: the verb over the evaluation pipeline (pipelines/detector/evaluate.py): the corner
detector scored against the labels, next to Harris and Shi-Tomasi; a table on stdout and every number in a JSON
file; with --target another target's keypoint detector on a dataset of that target
(pipelines/detector/evaluate_target.py). Here: the flags, the checked inputs, the frames as the camera saw them,
the printed table."""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_common, add_skip_damaged_argument, skipped_line
from envisat_pose.app.detect import detector_inputs
from envisat_pose.config import InputError, resolve_job_config
from envisat_pose.out_dirs import check_out_file
from envisat_pose.pipelines.detector.detect import DetectJobConfig
from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig
from envisat_pose.pipelines.detector.evaluate import groups_table, run_evaluate
from envisat_pose.pipelines.detector.evaluate_target import evaluate_target_detector, keypoint_table
from envisat_pose.shard_reader import skip_hint
from envisat_pose.target import other_target


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="score a detector against labels (ENVISAT's next to Harris and Shi-Tomasi; --target: per "
        "keypoint) (table + JSON)",
        description="Detect and name the corners of every frame of a labelled dataset and score them: per-corner "
        "error (median, p95), PCK at 2 and 5 px, visibility precision/recall, identity swaps, the half-turn "
        "ambiguity, covariance calibration (mean e^T C^-1 e), pose error after solvePnP, by corruption group; "
        "the same for Harris and Shi-Tomasi with oracle association, and the detector without line verification.",
    )
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped "
                   "weights; with --target FILE.xml, FILE_detector.safetensors beside it)")
    p.add_argument("--target", metavar="FILE.xml", help="another spacecraft's MJCF file: score its keypoint "
                   "detector (--weights from `envisat train --target`) on a dataset of it: per-keypoint PCK, "
                   "visibility, keypoints named wrongly, pose after PnP, as named and under the best twin naming")
    p.add_argument("--data", required=True, metavar="DIR", help="labelled dataset folder (shards)")
    p.add_argument("--json", required=True, metavar="OUT.json", help="output file of every metric")
    p.add_argument("--limit", type=int, help="only the first N frames")
    roi = p.add_mutually_exclusive_group()
    roi.add_argument("--roi", metavar="ROI.npz", help="regions of interest (as envisat detect --roi): adds the "
                     "method detector_roi")
    roi.add_argument("--roi-labels", action="store_true", help="adds the method detector_roi, given the region "
                     "of interest of the labelled corners (extent x 1.4, at least 64 px)")
    p.add_argument("--refine", action="store_true", help="adds detector_refined (and detector_roi_refined): the "
                   "named corners refined on the full-resolution pixels (DetectConfig.refine)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's, at most the usable cores)")
    add_common(p)  # the shared --quiet
    add_skip_damaged_argument(p)
    p.set_defaults(func=run_evaluate_cli, flag_names={"roi": "--roi", "roi_labels": "--roi-labels", "json_path": "--json",
                                                      "limit": "--limit", "out": "--out", "target": "--target",
                                                      "data": "--data", "weights": "--weights"})


def run_evaluate_cli(args: argparse.Namespace) -> int:
    detector_inputs(args)
    check_out_file(args.json, "--json")
    if other_target(args.target):
        return run_evaluate_target_cli(args)
    cfg = DetectJobConfig(weights=args.weights, device=args.device, limit=args.limit, roi=args.roi,
                          refine=args.refine, skip_damaged=bool(args.skip_damaged))
    with skip_hint():
        result = run_evaluate(cfg, args.data, args.json, roi_labels=args.roi_labels, progress=not args.quiet)
    skipped = result["skipped_damaged_shards"]
    print(groups_table(result["groups"]))
    print(f"wrote {args.json}: {result['frames']} frames")
    if skipped:
        print(skipped_line(skipped))
    return 0


def run_evaluate_target_cli(args: argparse.Namespace) -> int:
    """`envisat evaluate --target FILE.xml`: another target's keypoint detector (--roi, --roi-labels and --refine
    are the corners')."""
    given = [f for f, on in (("--roi", args.roi), ("--roi-labels", args.roi_labels), ("--refine", args.refine)) if on]
    if given:
        raise InputError(f"{given[0]}: ENVISAT's corner detector's; not with --target")
    cfg = resolve_job_config(TargetDetectJobConfig, {}, None, {
        "target": args.target, "weights": args.weights, "device": args.device, "limit": args.limit,
        "skip_damaged": bool(args.skip_damaged)})
    with skip_hint():
        result = evaluate_target_detector(cfg, args.data, args.json, progress=not args.quiet)
    print(keypoint_table(result))
    print(f"wrote {args.json}: {result['frames']} frames of target {result['target']['name']}")
    if result["skipped_damaged_shards"]:
        print(skipped_line(result["skipped_damaged_shards"]))
    return 0
