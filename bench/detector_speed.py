"""Detector speed on 2 CPU threads (skeleton; issue 10's benchmark grows from here).

Part 1 (now): the network's forward time per input size and width (min and median of repeated runs, so a busy
machine shows as spread), and the line head on all pairs of 12 junctions.
Part 2 (with shipped weights, still to do): ms per full 1024 px frame (coarse pass + crop + network + decode +
naming), with a given region of interest, next to Harris and Shi-Tomasi on the same frames; peak memory.
Writes bench/results/detector_speed.json.

    .venv/bin/python bench/detector_speed.py [--repeats 20] [--out bench/results/detector_speed.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "detector_speed.json"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for width in (32, 48, 64):
        for px in (256, 320, 384):
            r = time_forward(ModelConfig(input_px=px, width=width), args.repeats)
            rows.append(r)
            print(f"width {width:3d} input {px}: {r['params'] / 1e6:.2f} M params, forward {r['forward_ms_min']:.1f} "
                  f"ms min / {r['forward_ms_median']:.1f} median; 66 lines {r['line66_ms_min']:.1f} ms", flush=True)
    result = {"threads": args.threads, "torch": torch.__version__, "machine": platform.processor() or platform.machine(),
              "cpu_count": os.cpu_count(), "network": rows,
              "note": "forward of one image, eval mode, inference_mode; full-frame timing still to do"}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=1, sort_keys=True)
        fh.write("\n")


if __name__ == "__main__":
    main()
