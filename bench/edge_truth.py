"""The edge cue (pipelines/edge_range.py) read at the true pose of foreign frames: what it says where the answer is
known, so its own bias is separated from the tracker's (issue 40).

Per (scenario, seed, resolution), on the foreign sequence bench/adapt.py renders (bench/foreign_frames.py:
MuJoCo Filament, a real camera's habits; made here when missing) and every `--stride`-th frame, remapped to the
pinhole as the tracker sees them:
- the sequence's delta (edge_range.sequence_scale over the frames' fits) with the outline projected at the true
  pose, and at the true pose with the range scaled by 1 -+ `--step` (the cue's gain: it should read -+ step);
- the stations' offsets (px, + outward) at the true pose by the brightness of the face inside the edge (grey
  levels 5 px in): where the renderer's shading moves the edge.
A perfect cue reads 0 at the true pose; its reading there is the part of adapt's range correction that no
tracker can remove. The truth is the bench's, never the library's.

Run:  .venv/bin/python bench/edge_truth.py --seeds 0 1 2 3 --resolutions 512 1024 --work /tmp/adapt-bench
(writes bench/results/edge_truth.json and prints a table).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BRIGHTNESS = ((0, 40), (40, 60), (60, 90), (90, 130), (130, 256))


def one_case(scenario: str, seed: int, res: int, n: int, work: str, stride: int, step: float) -> dict:
    import cv2

    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import foreign_frames

    from envisat_pose.pipelines.edge_range import correct_range, edge_stations, fit_scale, sequence_scale
    from envisat_pose.pipelines.frames import open_source
    from envisat_pose.pipelines.pseudo_labels import corner_labels
    from envisat_pose.pipelines.track import TrackConfig, prepare_frames

    foreign = os.path.join(work, f"{scenario}-{seed}-{res}-{n}", "foreign")
    if not os.path.exists(os.path.join(foreign, "truth.npz")):
        foreign_frames.make_sequence(foreign, scenario, seed, n, res, progress=False)
    src = open_source(os.path.join(foreign, "frames"), timestamps=os.path.join(foreign, "timestamps.csv"))
    _, source, camera, remap, _ = prepare_frames(TrackConfig.from_scenario(scenario), src,
                                                 os.path.join(foreign, "camera.toml"))
    with np.load(os.path.join(foreign, "truth.npz")) as tr:
        x = tr["x"].reshape(-1, 12)
    keep = set(range(0, len(x), stride))
    images = {k: (im if remap is None else cv2.remap(im, remap[0], remap[1], cv2.INTER_LINEAR))
              for k, im in source.frames() if k in keep}
    ks = sorted(images)
    out = {"scenario": scenario, "seed": seed, "resolution_px": res, "frames": len(ks)}
    offsets, inside = [], []
    for e in (-step, 0.0, step):
        xs = correct_range(x[ks], camera.pos_C_m, -e / (1.0 + e))  # range r -> r (1 + e)
        lab = corner_labels(xs, camera)
        fits = []
        for i, k in enumerate(ks):
            st = edge_stations(images[k], lab["corners_px"][i], lab["visible"][i] & lab["in_frame"][i])
            fits.append(fit_scale(st))
            if e == 0.0 and len(st.offset_px):
                p = np.round(st.point_px - 5.0 * st.normal).astype(int)
                offsets.append(st.offset_px)
                inside.append(images[k][p[:, 1], p[:, 0]].astype(float))
        seq = sequence_scale(fits)
        out[f"range_x{1 + e:.4f}"] = {"delta": seq.delta, "delta_se": seq.delta_se,
                                      "frames_measured": int(sum(f.delta is not None for f in fits))}
    off, br = np.concatenate(offsets), np.concatenate(inside)
    out["offset_px_by_inside_grey"] = [
        {"grey": [lo, hi], "stations": int(m.sum()), "mean_px": float(off[m].mean()),
         "median_px": float(np.median(off[m]))}
        for lo, hi in BRIGHTNESS for m in [(br >= lo) & (br < hi)] if m.sum() >= 20]
    out["offset_px_mean"], out["stations"] = float(off.mean()), int(len(off))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["default"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    ap.add_argument("--resolutions", nargs="+", type=int, default=[512])
    ap.add_argument("--num-images", type=int, default=300)
    ap.add_argument("--stride", type=int, default=3)
    ap.add_argument("--step", type=float, default=0.005)
    ap.add_argument("--work", default="/tmp/adapt-bench")
    ap.add_argument("--out", default=os.path.join(ROOT, "bench", "results", "edge_truth.json"))
    args = ap.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    rows = []
    print("| scenario | seed | px | delta at truth | at range x(1-step) | x(1+step) | mean offset px | stations |")
    print("|---|---|---|---|---|---|---|---|")
    for scenario in args.scenarios:
        for res in args.resolutions:
            for seed in args.seeds:
                r = one_case(scenario, seed, res, args.num_images, args.work, args.stride, args.step)
                rows.append(r)
                lo, mid, hi = (r[f"range_x{1 + e:.4f}"]["delta"] for e in (-args.step, 0.0, args.step))
                pct = (lambda v: "-" if v is None else f"{100 * v:+.3f} %")
                print(f"| {scenario} | {seed} | {res} | {pct(mid)} | {pct(lo)} | {pct(hi)} | "
                      f"{r['offset_px_mean']:+.3f} | {r['stations']} |", flush=True)
                from envisat_pose.io import atomic_write_text

                atomic_write_text(args.out, json.dumps({"cases": rows, "argv": sys.argv[1:], "stride": args.stride,
                                                        "step": args.step}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
