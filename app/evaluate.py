"""`envisat evaluate`: the verb over the evaluation pipeline (pipelines/detector/evaluate.py): the corner
detector scored against the labels, next to Harris and Shi-Tomasi; a table on stdout and every number in a JSON
file. Here: the flags, the checked inputs, the frames as the camera saw them, the printed table."""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_common, add_skip_damaged_argument, skipped_line
from envisat_pose.app.detect import detector_inputs
from envisat_pose.out_dirs import check_out_file
from envisat_pose.pipelines.detector.detect import camera_samples, read_roi
from envisat_pose.pipelines.detector.evaluate import evaluate_detector, groups_table, read_poses
from envisat_pose.shard_reader import checked_shards, skip_hint
from envisat_pose.target import require_envisat_dataset


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="score the corner detector against labels, next to Harris and Shi-Tomasi (table + JSON)",
        description="Detect and name the corners of every frame of a labelled dataset and score them: per-corner "
        "error (median, p95), PCK at 2 and 5 px, visibility precision/recall, identity swaps, the half-turn "
        "ambiguity, covariance calibration (mean e^T C^-1 e), pose error after solvePnP, by corruption group; "
        "the same for Harris and Shi-Tomasi with oracle association, and the detector without line verification.",
    )
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped weights)")
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
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    add_common(p)  # the shared --quiet
    add_skip_damaged_argument(p)
    p.set_defaults(func=run_evaluate_cli, flag_names={"roi": "--roi", "out": "--out"})


def run_evaluate_cli(args: argparse.Namespace) -> int:
    detector_inputs(args)
    check_out_file(args.json, "--json")
    require_envisat_dataset(args.data, "--data", "evaluate")
    with skip_hint():
        paths, skipped = checked_shards(args.data, args.skip_damaged, "--data")
    roi = read_roi(args.roi) if args.roi else ("labels" if args.roi_labels else None)
    result = evaluate_detector(args.weights, camera_samples(paths), read_poses(paths), args.json, device=args.device,
                               limit=args.limit, roi=roi, refine=args.refine, data_name=args.data,
                               roi_name=args.roi, progress=not args.quiet, skipped_shards=skipped)
    print(groups_table(result["groups"]))
    print(f"wrote {args.json}: {result['frames']} frames")
    if skipped:
        print(skipped_line(skipped))
    return 0
