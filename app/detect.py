"""`envisat detect`: named corners of every frame of a dataset (full frames, no label used but the intrinsics K),
written as the core's Detections contract plus the shard keys and the half-turn alternative; with --target another
target's keypoints by its keypoint detector (the KeypointDetections contract). The verb parses the flags and calls
the pipeline (pipelines/detector/detect.py: run_detect; detect_target.py: run_detect_target)."""

from __future__ import annotations

import argparse
import json

from envisat_pose.app.common import add_common, add_skip_damaged_argument, skipped_line
from envisat_pose.config import InputError, resolve_job_config
from envisat_pose.out_dirs import check_out_file
from envisat_pose.pipelines.common.job_defaults import target_weights, weights_file, weights_name
from envisat_pose.pipelines.common.threads import default_torch_threads
from envisat_pose.pipelines.detector.detect import DetectJobConfig, run_detect
from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig, run_detect_target
from envisat_pose.pools import MAX_WORKERS
from envisat_pose.shard_reader import skip_hint
from envisat_pose.target import DEFAULT_TARGET, other_target


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "detect",
        help="detect and name the corners A-H (or another --target's keypoints) in full frames (det.npz)",
        description="Run the corner detector on every frame of a dataset: coarse pass, crop, network, line "
        "verification, naming by fitting the box. Writes det.npz: t_s, corners_px, cov_px, confidence, visible, "
        "config_json, plus key, alt_corners_px, alt_probability and ambiguous (the half-turn alternative).",
    )
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped "
                   "weights; with --target FILE.xml, FILE_detector.safetensors beside it)")
    p.add_argument("--target", metavar="FILE.xml", help="another spacecraft's MJCF file: its keypoints by the "
                   "weights `envisat train --target` wrote for it (det.npz: keypoints_px, score, visible_prob...)")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder (shards)")
    p.add_argument("--out", required=True, metavar="det.npz", help="output file")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's, at most the usable cores)")
    p.add_argument("--limit", type=int, help="only the first N frames")
    p.add_argument("--roi", metavar="ROI.npz",
                   help="regions of interest that skip the coarse pass: arrays key (M,) and roi_px (M, 3) "
                   "(x0, y0, side) full-image px, e.g. from a filter's prediction; frames not listed get the "
                   "coarse pass")
    p.add_argument("--refine", action="store_true",
                   help="refine the named corners on the full-resolution pixels (DetectConfig.refine: the box's "
                   "edges fitted and intersected, fused with the network's corner; off by default: it did not pay "
                   "in every corruption group on held-out data)")
    add_common(p)  # the shared --quiet
    add_skip_damaged_argument(p)
    p.set_defaults(func=run_detect_cli, flag_names={"roi": "--roi", "out": "--out", "data": "--data",
                                                    "target": "--target", "weights": "--weights"})


def detector_inputs(args: argparse.Namespace) -> None:
    """The checks the verbs that run the detector share, before any work: --limit at least 1 (where the verb has
    it), --weights (by default the shipped file, or another --target's own beside its file) exists and fits the
    target (--target where the verb has it, else ENVISAT: one line naming the weights, their target and the given
    one), --threads at least 1 (then torch uses that many; else its default, no more than the usable cores)."""
    import os

    import torch

    from envisat_pose.perception.weights import check_weights_target

    if getattr(args, "limit", None) is not None and args.limit < 1:
        raise InputError(f"--limit {args.limit}: expected at least 1")
    target = getattr(args, "target", None) or DEFAULT_TARGET
    args.weights = weights_file(target_weights(args.weights or "", target))  # none: the target's own, beside it
    if not os.path.isfile(args.weights):
        raise InputError(f"--weights {args.weights!r}: no such file")
    check_weights_target(args.weights, target, "--weights", named=weights_name(args.weights))  # no machine path
    if args.threads is not None and not 1 <= args.threads <= MAX_WORKERS:  # 2^31 or more: a ValueError from torch
        raise InputError(f"--threads {args.threads}: expected 1 to {MAX_WORKERS} threads (as train's, run's)")
    torch.set_num_threads(args.threads or default_torch_threads())


def resolve_config(args: argparse.Namespace):
    """The job's config from the flags (after detector_inputs: the weights file resolved), validated."""

    flags = {"weights": args.weights, "device": args.device, "limit": args.limit, "roi": args.roi,
             "refine": bool(args.refine), "skip_damaged": bool(args.skip_damaged)}
    return resolve_job_config(DetectJobConfig, {}, None, flags)


def run_detect_cli(args: argparse.Namespace) -> int:
    check_out_file(args.out)
    detector_inputs(args)
    if other_target(args.target):
        return run_target_cli(args)
    with skip_hint():
        arrays = run_detect(resolve_config(args), args.data, args.out, progress=not args.quiet)
    n = int(arrays["visible"].sum())
    print(f"wrote {args.out}: {len(arrays['key'])} frames, {n} corners found, "
          f"{int(arrays['ambiguous'].sum())} frames ambiguous under the half-turn")
    skipped = json.loads(str(arrays["config_json"]))["skipped_damaged_shards"]
    if skipped:
        print(skipped_line(skipped))
    return 0


def run_target_cli(args: argparse.Namespace) -> int:
    """`envisat detect --target FILE.xml`: another target's keypoints (--roi and --refine are the corners')."""
    if args.roi or args.refine:
        raise InputError(f"{'--roi' if args.roi else '--refine'}: ENVISAT's corner detector's; not with --target")
    cfg = resolve_job_config(TargetDetectJobConfig, {}, None, {
        "target": args.target, "weights": args.weights, "device": args.device, "limit": args.limit,
        "skip_damaged": bool(args.skip_damaged)})
    with skip_hint():
        arrays = run_detect_target(cfg, args.data, args.out, progress=not args.quiet)
    name = json.loads(str(arrays["config_json"]))["target"]["name"]  # as evaluate's line names it
    print(f"wrote {args.out}: {len(arrays['key'])} frames of target {name}, "
          f"{int(arrays['visible'].sum())} keypoints called visible of {arrays['visible'].size}")
    return 0
