"""The corner detector in float32 and in bfloat16 side by side (DetectConfig.bf16, `envisat run --bf16`).

On held-out frames of a labelled dataset (`envisat generate`, ENVISAT), the shipped weights with their
calibration, each frame detected twice per precision: whole (the coarse pass, as acquisition looks) and in the
region of interest of its labelled corners (extent x 1.4, at least 64 px: the tracker's path, the 192-px crop
and the corner patches). Per precision and path: PCK at 2 and 5 px of the corners named and labelled visible,
median error, mean signed error (x, y; the bias), mean e^T C^-1 e of the errors under the detector's covariance
(2 when calibrated), corners named, and the detector's ms per frame (median, 1 torch thread); then how far the
bfloat16 corners lie from the float32 ones where both name a corner. Whether the CPU has native bfloat16
(AVX512-BF16 or AMX) is recorded: elsewhere torch emulates it, slower.

    .venv/bin/python bench/detector_bf16.py --data DIR [--limit 200] [--weights W]
        [--out bench/results/detector_bf16.json]
"""

from __future__ import annotations

import os
import platform
import time

import cv2
import numpy as np
import torch

from envisat_pose.datagen.dataset import iter_samples, sample_image
from envisat_pose.perception.detect import load_detector
from envisat_pose.perception.evaluate import label_roi
from envisat_pose.perception.weights import shipped_weights_path

HERE = os.path.dirname(os.path.abspath(__file__))


def cpu_bf16() -> str:
    """The CPU's bfloat16 instructions as /proc/cpuinfo names them ('' where none, or not Linux)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            flags = next((line.split(":", 1)[1].split() for line in fh if line.startswith("flags")), [])
    except OSError:
        return ""
    return " ".join(f for f in ("avx512_bf16", "amx_bf16") if f in flags)


def detect_all(detector, frames, roi: bool) -> tuple[list, list]:
    """(detections, ms per frame) of every frame (image, label), whole or in its labelled region of interest."""
    out, ms = [], []
    for image, lab in frames:
        box = label_roi(np.asarray(lab["corners_px"], float), image.shape) if roi else None
        K = np.asarray(lab["K"], float)
        t0 = time.perf_counter()
        out.append(detector.detect(image, K, roi_px=box))
        ms.append(1e3 * (time.perf_counter() - t0))
    return out, ms


def scores(dets, frames, ms) -> dict:
    """PCK, errors, bias and calibration of the named corners against the labels (module docstring)."""
    err, nees, named = [], [], 0
    for d, (_, lab) in zip(dets, frames):
        truth = np.asarray(lab["corners_px"], float)
        ok = d.visible & np.asarray(lab["visible"], bool)
        named += int(d.visible.sum())
        for k in np.flatnonzero(ok):
            e = d.corners_px[k] - truth[k]
            err.append(e)
            nees.append(float(e @ np.linalg.solve(d.cov_px[k], e)))
    e = np.asarray(err).reshape(-1, 2)
    r = np.linalg.norm(e, axis=1)
    return {"corners": len(r), "named": named, "pck_2px": float(np.mean(r <= 2)), "pck_5px": float(np.mean(r <= 5)),
            "median_px": float(np.median(r)), "bias_x_px": float(e[r <= 5, 0].mean()),
            "bias_y_px": float(e[r <= 5, 1].mean()), "mean_nees_within_5px": float(np.mean(np.asarray(nees)[r <= 5])),
            "ms_per_frame_median": float(np.median(ms))}


def differences(a, b) -> dict:
    """Where both name a corner: how far apart (px), and how often they name different corners visible."""
    d, flips = [], 0
    for x, y in zip(a, b):
        both = x.visible & y.visible
        d += list(np.linalg.norm(x.corners_px[both] - y.corners_px[both], axis=1))
        flips += int(np.sum(x.visible != y.visible))
    d = np.asarray(d)
    return {"corners_both": len(d), "median_px": float(np.median(d)), "p95_px": float(np.percentile(d, 95)),
            "max_px": float(d.max()), "named_by_one_only": flips}


def main() -> None:
    # bench/_common.py, beside this script
    from _common import WholeFlagParser, count, dataset, description, existing_file, out_file, provenance, write_json

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--data", required=True, type=dataset, help="a labelled ENVISAT dataset (envisat generate)")
    ap.add_argument("--limit", type=count(), default=200)
    ap.add_argument("--weights", type=existing_file, default=shipped_weights_path())
    ap.add_argument("--out", type=out_file, default=os.path.join(HERE, "results", "detector_bf16.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    frames = [(sample_image(m, lab), lab) for _, lab, m in iter_samples(args.data, limit=args.limit)]
    result = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "cpu_bf16": cpu_bf16(),
                          "torch": torch.__version__},
              "data": os.path.basename(os.path.normpath(args.data)), "frames": len(frames),
              "weights": os.path.basename(args.weights), "paths": {}}
    print(f"{len(frames)} frames of {args.data}; CPU bfloat16: {result['machine']['cpu_bf16'] or 'none (emulated)'}")
    print(f"{'path':<6} {'precision':<9} {'PCK@2':>6} {'PCK@5':>6} {'median':>7} {'bias x':>7} {'bias y':>7} "
          f"{'NEES':>5} {'named':>6} {'ms':>6}")
    for path, roi in (("whole", False), ("roi", True)):
        dets, row = {}, {}
        for precision in ("fp32", "bf16"):
            detector = load_detector(args.weights, bf16=precision == "bf16")
            detect_all(detector, frames[:2], roi)  # warm
            dets[precision], ms = detect_all(detector, frames, roi)
            s = row[precision] = scores(dets[precision], frames, ms)
            print(f"{path:<6} {precision:<9} {100 * s['pck_2px']:>5.1f}% {100 * s['pck_5px']:>5.1f}% "
                  f"{s['median_px']:>7.3f} {s['bias_x_px']:>+7.3f} {s['bias_y_px']:>+7.3f} "
                  f"{s['mean_nees_within_5px']:>5.2f} {s['named']:>6d} {s['ms_per_frame_median']:>6.1f}")
        row["bf16_minus_fp32"] = differences(dets["fp32"], dets["bf16"])
        dd = row["bf16_minus_fp32"]
        print(f"{path:<6} bf16 vs fp32 corners: median {dd['median_px']:.3f} px, p95 {dd['p95_px']:.3f}, max "
              f"{dd['max_px']:.3f}; named by one only: {dd['named_by_one_only']}")
        result["paths"][path] = row
    result["provenance"] = provenance(args)
    write_json(args.out, result, indent=1, sort_keys=True)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
