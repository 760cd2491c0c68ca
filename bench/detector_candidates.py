"""Detector weights side by side on the same held-out sets: which to ship.

Each candidate runs the shipped detection chain (DetectConfig defaults, its own cov_scale: coarse pass, crop,
patch pass, naming) on every frame of every set, on the full frame ('detector', a cold start's regime) and in
the labels' region of interest ('detector_roi', the regime of a converged track), and is scored by
perception.evaluate.score_method as `envisat evaluate` scores it. The sets are labelled datasets (`envisat
generate` folders) of seeds no candidate was trained on. Prints a table, writes a JSON (default
bench/results/detector_candidates.json) with each set's manifest sha256 and each weights file's sha256.

    nice -n 10 .venv/bin/python bench/detector_candidates.py --weights shipped=models/detector.safetensors \\
        leg1=out/l1/detector.safetensors --data r8181=out/l1/r8181 e8282=out/l1/e8282 [--limit N] [--threads 1]
"""

from __future__ import annotations

import json
import os
import platform
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

METHODS = ("detector", "detector_roi")
COLUMNS = (("median px", "median_px", ".3f"), ("p95 px", "p95_px", ".1f"), ("PCK@2", "pck_2px", ".3f"),
           ("PCK@5", "pck_5px", ".3f"), ("swaps", "swap_rate_strict", ".3f"), ("ambig", "ambiguous_share", ".2f"),
           ("vis P", "visibility_precision", ".3f"), ("vis R", "visibility_recall", ".3f"),
           ("NEES", "mean_nees", ".2f"), ("scale-1", "scale_minus_1", ".5f"))


def named_paths(items: list[str], flag: str) -> dict[str, str]:
    """NAME=PATH arguments as {name: path}; a clear error for a malformed one or a missing path."""
    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"{flag}: expected NAME=PATH, got {item!r}")
        if not os.path.exists(path):
            raise SystemExit(f"{flag} {name}: {path!r} does not exist")
        out[name] = path
    return out


def figures(score: dict) -> dict:
    """The table's figures from one score_method result."""
    scale = score["bias"]["scale_mean"]
    return {"frames": score["frames"], "usable_corners": score["usable_corners"],
            "median_px": score["errors"]["all"]["median_px"], "p95_px": score["errors"]["all"]["p95_px"],
            "pck_2px": score["pck_2px"], "pck_5px": score["pck_5px"], "swap_rate_strict": score["swap_rate_strict"],
            "ambiguous_share": score["ambiguous_share"],
            "visibility_precision": score["visibility"]["precision"],
            "visibility_recall": score["visibility"]["recall"],
            "mean_nees": score["calibration"]["mean_nees"],
            "scale_minus_1": scale - 1.0 if np.isfinite(scale) else None}


def score_weights(weights: str, frames: list, device: str = "cpu") -> dict[str, dict]:
    """{method: figures} of one weights file over one set's frames [(key, image, label)]."""
    from envisat_pose.perception.detect import DetectConfig, Detector, weights_cov_scale
    from envisat_pose.perception.evaluate import label_roi, score_method
    from envisat_pose.perception.weights import load_model

    det = Detector(load_model(weights, device), DetectConfig(cov_scale=weights_cov_scale(weights)), device=device)
    found = {m: {"pred": [], "alt": [], "amb": [], "vis": [], "cov": []} for m in METHODS}
    true, usable = [], []
    for _, image, label in frames:
        true.append(label["corners_px"])
        usable.append(label["visible"] & label["in_frame"])
        for m, roi in (("detector", None), ("detector_roi", label_roi(label["corners_px"], image.shape))):
            f = det.detect(image, label["K"], roi_px=roi)
            for k, v in zip(("pred", "alt", "amb", "vis", "cov"),
                            (f.corners_px, f.alt_corners_px, f.ambiguous, f.visible, f.cov_px)):
                found[m][k].append(v)
    true, usable = np.array(true), np.array(usable)
    out = {}
    for m, r in found.items():
        a = {k: np.array(v) for k, v in r.items()}
        out[m] = figures(score_method(a["pred"], true, usable, alt_px=a["alt"], ambiguous=a["amb"],
                                      pred_visible=a["vis"], cov_px=a["cov"]))
    return out


def main() -> None:
    from _common import WholeFlagParser, count, description, out_file, provenance  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--weights", nargs="+", required=True, help="NAME=W.safetensors, one per candidate")
    ap.add_argument("--data", nargs="+", required=True, help="NAME=DIR, labelled held-out sets")
    ap.add_argument("--limit", type=count(), help="only the first N frames of each set")
    ap.add_argument("--threads", type=count(), default=1, help="torch CPU threads")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--out", type=out_file, default=os.path.join(ROOT, "bench", "results", "detector_candidates.json"))
    args = ap.parse_args()
    import torch
    from tqdm import tqdm

    from envisat_pose.io import atomic_write_text, json_safe, sha256_file
    from envisat_pose.perception.data import shard_paths
    from envisat_pose.pipelines.detector.detect import camera_samples
    from envisat_pose.provenance import manifest_sha256

    torch.set_num_threads(args.threads)
    weights, sets = named_paths(args.weights, "--weights"), named_paths(args.data, "--data")
    rows, t0 = [], time.time()
    for set_name, folder in sets.items():
        frames = list(camera_samples(shard_paths(folder)))[:args.limit]
        for w_name, path in tqdm(weights.items(), desc=set_name, unit="weights"):
            for method, fig in score_weights(path, frames, args.device).items():
                rows.append({"weights": w_name, "set": set_name, "method": method, **fig})
    head = f"{'set':8s} {'method':13s} {'weights':10s} " + " ".join(f"{c[0]:>9s}" for c in COLUMNS)
    print(head)
    for r in sorted(rows, key=lambda r: (r["set"], r["method"], r["weights"])):
        cells = (f"{'-':>9s}" if r[c[1]] is None else f"{r[c[1]]:9{c[2]}}" for c in COLUMNS)
        print(f"{r['set']:8s} {r['method']:13s} {r['weights']:10s} " + " ".join(cells))
    result = {"what": __doc__.split("\n\n")[1].replace("\n", " "),
              "weights": {n: {"sha256": sha256_file(p), "file": os.path.basename(p)} for n, p in weights.items()},
              "sets": {n: {"manifest_sha256": manifest_sha256(p), "frames": args.limit or "all"}
                       for n, p in sets.items()},
              "machine": platform.machine(), "device": args.device, "torch_threads": args.threads,
              "wall_s": round(time.time() - t0, 1), "rows": rows}
    result["provenance"] = provenance(args)
    atomic_write_text(args.out, json.dumps(json_safe(result), indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
