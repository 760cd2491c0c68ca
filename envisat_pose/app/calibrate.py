"""`envisat calibrate`: fit the detector's covariance scale on held-out labelled frames and ship it in the weights.

The network's 2x2 covariance per corner is scaled by one factor s (C -> s C) so that the mean of e^T C^-1 e over
correctly named visible corners is 2, the chi-square-2 mean (perception/calibrate.py). The factor goes into the
weights file's metadata (`cov_scale`), where `load_detector` and the verbs that detect read it; the result per
corruption group is printed and stored beside it (`cov_calibration`).
"""

from __future__ import annotations

import argparse
import json
import os

from envisat_pose.config import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit the detector's pixel-covariance scale on held-out frames; write weights that carry it",
        description="Detect the corners of every frame of a held-out labelled dataset (one not used in training), "
        "take the correctly named visible corners, fit the scale s that brings the mean e^T (s C)^-1 e to 2, and "
        "write a copy of the weights with s in their metadata. Prints the calibration per corruption group.",
    )
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped weights)")
    p.add_argument("--data", required=True, metavar="DIR", help="held-out labelled dataset folder (shards)")
    p.add_argument("--out", required=True, metavar="OUT.safetensors", help="calibrated weights (may equal --weights)")
    p.add_argument("--limit", type=int, help="only the first N frames")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_calibrate_cli)


def collect_errors(detector, samples, limit: int | None = None, bar=None):
    """Errors e (M, 2) px, covariances C (M, 2, 2) px^2 (as the detector gives them) and the corruption group of
    the frame (M,) of every usable corner named right within the match radius (an ambiguous frame with its better
    naming)."""
    import numpy as np

    from envisat_pose.perception import evaluate as ev

    errs, covs, groups = [], [], []
    for i, (_key, image, label) in enumerate(samples):
        if limit is not None and i >= limit:
            break
        use = label["visible"] & label["in_frame"]
        f = detector.detect(image, label["K"])
        true = label["corners_px"]
        chosen, used_alt = ev.better_naming(f.corners_px[None], f.alt_corners_px[None], np.array([f.ambiguous]),
                                            true[None], use[None])
        # the alternative naming's corners are the same candidates, renamed: their covariances follow them
        cov = f.cov_px[ev.HALF_TURN_PERM] if used_alt[0] else f.cov_px
        hit = ev.hits(chosen, true[None], use[None], ev.MATCH_PX)[0] & np.all(np.isfinite(cov), axis=(1, 2))
        kind = ev.corruption_groups(*ev.corruption_levels(label["corruption"], image.shape[1]))[1]
        errs.append(chosen[0][hit] - true[hit])
        covs.append(cov[hit])
        groups += [kind] * int(hit.sum())
        if bar is not None:
            bar.update(1)
    if not errs:
        raise InputError("no frames")
    return np.concatenate(errs), np.concatenate(covs), np.array(groups, dtype=str)


def run_calibrate_cli(args: argparse.Namespace) -> int:
    import dataclasses

    from tqdm import tqdm

    from envisat_pose.app.detect import camera_samples, detector_inputs
    from envisat_pose.io import check_writable_output
    from envisat_pose.perception.calibrate import calibration_by_group, fit_scale
    from envisat_pose.perception.data import shard_paths
    from envisat_pose.perception.detect import DetectConfig, load_detector
    from envisat_pose.perception.weights import with_metadata

    detector_inputs(args)
    if os.path.abspath(args.out) != os.path.abspath(args.weights):
        check_writable_output(args.out)
    paths = shard_paths(args.data)
    # the network's own covariances (scale 1), whatever the file carried before
    det = load_detector(args.weights, config=dataclasses.replace(DetectConfig(), cov_scale=1.0))
    bar = tqdm(disable=args.quiet, desc="calibrate", unit="frame")
    err, cov, groups = collect_errors(det, camera_samples(paths), args.limit, bar)
    bar.close()
    if len(err) < 20:
        raise InputError(f"--data {args.data!r}: only {len(err)} correctly named corners; calibration needs more "
                         "held-out frames (at least 20 corners)")
    scale = fit_scale(err, cov)
    before = calibration_by_group(err, cov, groups)
    after = calibration_by_group(err, cov * scale, groups)
    print(f"{'group':12s} {'corners':>8s} {'NEES raw':>9s} {'NEES calibrated':>16s}")
    for g in before:
        print(f"{g:12s} {before[g]['count']:8d} {before[g]['mean_nees']:9.2f} {after[g]['mean_nees']:16.2f}")
    record = {"scale": scale, "data": os.path.abspath(args.data), "corners": int(len(err)),
              "mean_nees_by_group": {g: v["mean_nees"] for g, v in after.items()},
              "count_by_group": {g: v["count"] for g, v in after.items()}}
    with_metadata(args.weights, args.out, {"cov_scale": scale, "cov_calibration": json.dumps(record, sort_keys=True)})
    print(f"cov_scale {scale:.4g} (mean e^T C^-1 e 2.00 on {len(err)} corners); wrote {args.out}")
    return 0
