"""Detector speed on 2 CPU threads.

Part 1: the network's forward time per input size and width (min and median of repeated runs, so a busy
machine shows as spread), and the line head on all pairs of 12 junctions.
Part 2: ms per full 1024 px frame of the whole detector (coarse pass + crop + network + decode + line
verification + naming), and with a given region of interest (the crop around the label's corners standing in
for the filter's prediction: no coarse pass), both again with the sub-pixel refinement of the named corners
(DetectConfig.refine, perception/refine.py), next to Harris and Shi-Tomasi (goodFeaturesToTrack + cornerSubPix,
as perception/evaluate.py runs them) on the same frames; peak memory (max RSS of this process, which generates
nothing: the frames come from `envisat generate` in a child process). The shipped weights are timed by default
(--weights W for others; --untrained times an untrained default-size network, which finds no junction above
threshold and stops after one network pass: a lower bound). Writes bench/results/detector_speed.json.

    .venv/bin/python bench/detector_speed.py [--repeats 20] [--frames 8] [--weights W | --untrained] [--out ...json]
"""

from __future__ import annotations

import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

from envisat_pose.perception.model import CornerNet, ModelConfig


def time_forward(cfg: ModelConfig, repeats: int) -> dict:
    model = CornerNet(cfg).eval()
    x = torch.zeros(1, 1, cfg.input_px, cfg.input_px)
    pairs = 66  # all pairs of 12 junctions
    segs = torch.linspace(0, cfg.input_px - 1, pairs * 4).reshape(1, pairs, 2, 2)
    with torch.inference_mode():
        for _ in range(3):
            out = model(x)
        fwd, line = [], []
        for _ in range(repeats):
            t = time.perf_counter()
            out = model(x)
            fwd.append(time.perf_counter() - t)
            t = time.perf_counter()
            model.line_logits(out["features"], segs)
            line.append(time.perf_counter() - t)
    return {"input_px": cfg.input_px, "width": cfg.width, "depth": cfg.depth,
            "params": int(sum(p.numel() for p in model.parameters())),
            "forward_ms_min": 1e3 * min(fwd), "forward_ms_median": 1e3 * float(np.median(fwd)),
            "line66_ms_min": 1e3 * min(line), "line66_ms_median": 1e3 * float(np.median(line))}


def make_frames(n: int, out_dir: str) -> list:
    """n full 1024 px frames (the default space camera) from `envisat generate --seed 7` in a child process."""
    from envisat_pose.perception.data import read_samples, shard_paths

    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "osmesa"))
    subprocess.run([sys.executable, "-m", "envisat_pose.app.cli", "generate", "--num-images", str(n), "--seed", "7",
                    "--resolution", "1024", "--out", out_dir, "--quiet"], check=True, env=env)
    return list(read_samples(shard_paths(out_dir)))


def _ms(fn, repeats: int) -> list[float]:
    """Median ms of `repeats` calls (after one warm-up call)."""
    fn()
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(t))


def time_frames(frames: list, weights: str | None, repeats: int) -> dict:
    """ms per frame (median over frames of each frame's median) of the detector (full frame, ROI) and the
    classical peers."""
    from envisat_pose.perception.data import DataConfig, crop_box
    from envisat_pose.perception.detect import Detector, load_detector
    from envisat_pose.perception.evaluate import classical_corners

    if weights:
        det = load_detector(weights)
    else:
        torch.manual_seed(0)  # this bench's own draw of untrained weights
        det = Detector(CornerNet(ModelConfig()))
    model = det.model
    import dataclasses

    refined = Detector(model, dataclasses.replace(det.cfg, refine=True))
    per = {"detector_full_frame": [], "detector_roi": [], "detector_full_frame_refined": [],
           "detector_roi_refined": [], "harris": [], "shi_tomasi": []}
    for _, image, label in frames:
        use = label["visible"] & label["in_frame"]
        roi = crop_box(label["corners_px"], use, image.shape, DataConfig(), None)
        per["detector_full_frame"].append(_ms(lambda: det.detect(image, label["K"]), repeats))
        per["detector_roi"].append(_ms(lambda: det.detect(image, label["K"], roi_px=roi), repeats))
        per["detector_full_frame_refined"].append(_ms(lambda: refined.detect(image, label["K"]), repeats))
        per["detector_roi_refined"].append(_ms(lambda: refined.detect(image, label["K"], roi_px=roi), repeats))
        per["harris"].append(_ms(lambda: classical_corners(image, True), repeats))
        per["shi_tomasi"].append(_ms(lambda: classical_corners(image, False), repeats))
    return {"model": model.cfg.to_dict(), "trained": bool(weights), "frames": len(frames),
            "image_px": list(frames[0][1].shape),
            "ms_per_frame": {k: {"median": float(np.median(v)), "max": float(np.max(v))} for k, v in per.items()}}


def main() -> None:
    from _common import (  # bench/_common.py
        WholeFlagParser,
        count,
        description,
        existing_file,
        out_file,
        provenance,
        write_json,
    )

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--repeats", type=count(), default=20)
    ap.add_argument("--threads", type=count(), default=2)
    ap.add_argument("--frames", type=count(), default=8, help="full 1024 px frames for part 2")
    ap.add_argument("--frame-repeats", type=count(), default=5, help="timed runs per frame in part 2")
    ap.add_argument("--weights", type=existing_file, help="trained weights (default: the shipped ones)")
    ap.add_argument("--untrained", action="store_true", help="time an untrained default-size network instead")
    ap.add_argument("--out", type=out_file,
                    default=os.path.join(os.path.dirname(__file__), "results", "detector_speed.json"))
    args = ap.parse_args()
    if not args.untrained and not args.weights:
        from envisat_pose.perception.weights import shipped_weights_path

        args.weights = shipped_weights_path()
    if args.untrained:
        args.weights = None
    torch.set_num_threads(args.threads)
    import cv2

    cv2.setNumThreads(args.threads)
    rows = []
    for width in (32, 48, 64):
        for px in (256, 320, 384):
            r = time_forward(ModelConfig(input_px=px, width=width), args.repeats)
            rows.append(r)
            print(f"width {width:3d} input {px}: {r['params'] / 1e6:.2f} M params, forward {r['forward_ms_min']:.1f} "
                  f"ms min / {r['forward_ms_median']:.1f} median; 66 lines {r['line66_ms_min']:.1f} ms", flush=True)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    with tempfile.TemporaryDirectory() as tmp:
        frames = make_frames(args.frames, os.path.join(tmp, "ds"))
    full = time_frames(frames, args.weights, args.frame_repeats)
    full["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    full["peak_rss_mib_before_part2"] = rss0
    print(f"\nfull {full['image_px'][1]} px frames ({full['frames']}, {args.threads} threads, "
          f"{'trained' if full['trained'] else 'untrained'} weights, input {full['model']['input_px']} px):")
    print(f"{'method':22s} {'ms median':>10s} {'ms max':>8s}")
    for k, v in full["ms_per_frame"].items():
        print(f"{k:22s} {v['median']:10.1f} {v['max']:8.1f}")
    print(f"peak RSS {full['peak_rss_mib']:.0f} MiB (before part 2: {rss0:.0f} MiB); floor: full frame < 100 ms")
    result = {"threads": args.threads, "torch": torch.__version__, "machine": platform.processor() or platform.machine(),
              "cpu_count": os.cpu_count(), "network": rows, "full_frame": full,
              "note": "network: forward of one image, eval mode, inference_mode. full_frame: the whole detector "
                      "(coarse pass, crop, network, decode, line verification, naming) per 1024 px frame; "
                      + (f"trained weights {os.path.basename(args.weights)}" if args.weights else
                         "UNTRAINED weights (--untrained): the untrained network finds no junction above "
                         "threshold, so detector_full_frame and detector_roi stop after one network pass each: a "
                         "LOWER BOUND, without the crop pass, line verification and naming; no accuracy implied")}
    result["provenance"] = provenance(args)
    write_json(args.out, result, indent=1, sort_keys=True)


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
