"""`envisat detect`: named corners of every frame of a dataset (full frames, no label used but the intrinsics K),
written as the core's Detections contract plus the shard keys and the half-turn alternative."""

from __future__ import annotations

import argparse
import json

from envisat_pose.config import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "detect",
        help="detect and name the corners A-H in full frames (det.npz: the Detections contract)",
        description="Run the corner detector on every frame of a dataset: coarse pass, crop, network, line "
        "verification, naming by fitting the box. Writes det.npz: t_s, corners_px, cov_px, confidence, visible, "
        "config_json, plus key, alt_corners_px, alt_probability and ambiguous (the half-turn alternative).",
    )
    p.add_argument("--weights", required=True, metavar="W.safetensors", help="detector weights")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder (shards)")
    p.add_argument("--out", required=True, metavar="det.npz", help="output file")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    p.add_argument("--limit", type=int, help="only the first N frames")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_detect_cli)


def run_detect_cli(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from tqdm import tqdm

    from envisat_pose.contracts import Detections
    from envisat_pose.io import check_writable_output, save_npz
    from envisat_pose.perception.data import read_samples, shard_paths
    from envisat_pose.perception.detect import Detector
    from envisat_pose.perception.weights import load_model

    check_writable_output(args.out)
    paths = shard_paths(args.data)
    if args.threads is not None:
        if args.threads < 1:
            raise InputError(f"--threads {args.threads}: expected at least 1")
        torch.set_num_threads(args.threads)
    model = load_model(args.weights, args.device)
    det = Detector(model, device=args.device)
    rows = {k: [] for k in ("key", "t_s", "corners_px", "cov_px", "confidence", "visible", "alt_corners_px",
                            "alt_probability", "ambiguous")}
    bar = tqdm(disable=args.quiet, desc="detect", unit="frame")
    for i, (key, image, label) in enumerate(read_samples(paths)):
        if args.limit is not None and i >= args.limit:
            break
        f = det.detect(image, label["K"])  # the label's intrinsics only: positions come from the image
        rows["key"].append(key)
        rows["t_s"].append(float(i))
        for name in ("corners_px", "cov_px", "confidence", "visible", "alt_corners_px", "alt_probability",
                     "ambiguous"):
            rows[name].append(getattr(f, name))
        bar.update(1)
    bar.close()
    if not rows["key"]:
        raise InputError(f"--data {args.data!r}: no frames")
    config = {"weights": args.weights, "data": args.data, "model": model.cfg.to_dict()}
    arrays = {k: np.array(v) for k, v in rows.items()}
    arrays["key"] = arrays["key"].astype(str)
    arrays["config_json"] = json.dumps(config, sort_keys=True)
    Detections.validated(arrays, args.out)  # the contract's checks before writing
    save_npz(args.out, {**arrays, "config_json": np.array(arrays["config_json"])})
    n = int(arrays["visible"].sum())
    print(f"wrote {args.out}: {len(arrays['key'])} frames, {n} corners found, "
          f"{int(arrays['ambiguous'].sum())} frames ambiguous under the half-turn")
    return 0
