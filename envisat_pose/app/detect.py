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
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped weights)")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder (shards)")
    p.add_argument("--out", required=True, metavar="det.npz", help="output file")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    p.add_argument("--limit", type=int, help="only the first N frames")
    p.add_argument("--roi", metavar="ROI.npz",
                   help="regions of interest that skip the coarse pass: arrays key (M,) and roi_px (M, 3) "
                   "(x0, y0, side) full-image px, e.g. from a filter's prediction; frames not listed get the "
                   "coarse pass")
    p.add_argument("--refine", action="store_true",
                   help="refine the named corners on the full-resolution pixels (DetectConfig.refine: the box's "
                   "edges fitted and intersected, fused with the network's corner; off by default: it did not pay "
                   "in every corruption group on held-out data)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_detect_cli)


def detector_inputs(args: argparse.Namespace) -> None:
    """The checks the verbs that run the detector share, before any work: --limit at least 1 (where the verb has
    it), --weights (the shipped file by default) exists, --threads at least 1 (then torch uses that many)."""
    import os

    import torch

    from envisat_pose.perception.weights import shipped_weights_path

    if getattr(args, "limit", None) is not None and args.limit < 1:
        raise InputError(f"--limit {args.limit}: expected at least 1")
    args.weights = args.weights or shipped_weights_path()
    if not os.path.isfile(args.weights):
        raise InputError(f"--weights {args.weights!r}: no such file")
    if args.threads is not None:
        if args.threads < 1:
            raise InputError(f"--threads {args.threads}: expected at least 1")
        torch.set_num_threads(args.threads)


def camera_samples(paths: list[str]):
    """(key, image, label) of every sample as the camera saw it: a shard stored clean (`image_stored` 'clean')
    gets its label's recorded sensor corruption applied on read (datagen's space camera, deterministic)."""
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.perception.data import read_samples

    for key, image, label in read_samples(paths):
        if label.get("image_stored") == "clean":
            image = apply_corruption(image, label["corruption"])
        yield key, image, label


def read_roi(path: str) -> dict[str, "object"]:
    """{key: roi_px (3,) int} from an ROI file (npz of key (M,) str and roi_px (M, 3) finite, side > 0);
    InputError naming the file and the problem otherwise. Loaded without pickle."""
    import os

    import numpy as np

    if not os.path.isfile(path):
        raise InputError(f"--roi {path!r}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            keys, roi = z["key"].astype(str), np.asarray(z["roi_px"], dtype=np.float64)
    except (KeyError, ValueError, OSError) as err:
        raise InputError(f"--roi {path!r}: expected an npz with key (M,) and roi_px (M, 3) ({err})") from None
    if roi.shape != (len(keys), 3) or not np.all(np.isfinite(roi)) or np.any(roi[:, 2] <= 0):
        raise InputError(f"--roi {path!r}: roi_px has shape {roi.shape}, expected ({len(keys)}, 3) finite with "
                         "side > 0")
    return {k: np.round(r).astype(np.int64) for k, r in zip(keys.tolist(), roi)}


def run_detect_cli(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm import tqdm

    from envisat_pose.contracts import Detections
    from envisat_pose.io import check_writable_output, save_npz
    from envisat_pose.perception.data import shard_paths
    from envisat_pose.perception.detect import load_detector

    check_writable_output(args.out)
    detector_inputs(args)
    paths = shard_paths(args.data)
    rois = read_roi(args.roi) if args.roi else {}
    det = load_detector(args.weights, device=args.device)
    if args.refine:
        import dataclasses

        det.cfg = dataclasses.replace(det.cfg, refine=True)
    rows = {k: [] for k in ("key", "t_s", "corners_px", "cov_px", "confidence", "visible", "alt_corners_px",
                            "alt_probability", "ambiguous")}
    bar = tqdm(disable=args.quiet, desc="detect", unit="frame")
    for i, (key, image, label) in enumerate(camera_samples(paths)):
        if args.limit is not None and i >= args.limit:
            break
        # the label's intrinsics only: positions come from the image
        f = det.detect(image, label["K"], roi_px=rois.get(key))
        rows["key"].append(key)
        rows["t_s"].append(float(label.get("t_s", i)))
        for name in ("corners_px", "cov_px", "confidence", "visible", "alt_corners_px", "alt_probability",
                     "ambiguous"):
            rows[name].append(getattr(f, name))
        bar.update(1)
    bar.close()
    if not rows["key"]:
        raise InputError(f"--data {args.data!r}: no frames")
    config = {"weights": args.weights, "data": args.data, "model": det.model.cfg.to_dict(),
              "cov_scale": det.cfg.cov_scale, "roi": args.roi, "refine": bool(args.refine)}
    arrays = {k: np.array(v) for k, v in rows.items()}
    arrays["key"] = arrays["key"].astype(str)
    arrays["config_json"] = json.dumps(config, sort_keys=True)
    Detections.validated(arrays, args.out)  # the contract's checks before writing
    save_npz(args.out, {**arrays, "config_json": np.array(arrays["config_json"])})
    n = int(arrays["visible"].sum())
    print(f"wrote {args.out}: {len(arrays['key'])} frames, {n} corners found, "
          f"{int(arrays['ambiguous'].sum())} frames ambiguous under the half-turn")
    return 0
