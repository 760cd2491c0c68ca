"""Speed of the space camera (datagen/sensor.py's apply_sensor) on the closed loop's frames: 1024 px renders of
the default scenario in sequence mode with the sequence mode's defaults (the factory's appearance and corruption draws),
the previous implementation and the current one timed in the same run on the same frames and parameters.

The previous implementation is the file datagen/sensor.py at REFERENCE_COMMIT (read with `git show`, loaded as a
module): the whole frame pixel by pixel (numpy's Poisson for every pixel below 100 e-). The current one draws the
unlit pixels from their exact distribution by table lookup and runs the chain pixel by pixel only in the box
around the light. Beside the times: per pixel class (unlit, lit) the mean and variance of the 8-bit output over
noise seeds, for both (the same distribution: they must agree within their sampling error).

Run: .venv/bin/python bench/sensor_speed.py [--frames 6] [--repeats 5] [--seeds 40] [--reference COMMIT]
     [--out bench/results/sensor_speed.json]
"""

from __future__ import annotations

import importlib.util
import os
import platform
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np

REFERENCE_COMMIT = "dacdd26"  # the last sensor.py before the fast path
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def reference_module(commit: str):
    """datagen/sensor.py as it was at `commit`, loaded as a module (None when git cannot show it)."""
    try:
        text = subprocess.run(["git", "show", f"{commit}:datagen/sensor.py"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = os.path.join(tempfile.mkdtemp(prefix="sensor-ref-"), "sensor_reference.py")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    spec = importlib.util.spec_from_file_location("sensor_reference", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def closed_loop_frames(n: int) -> list[tuple[np.ndarray, dict]]:
    """n clean 1024 px frames of the default scenario (sequence mode, 30 s apart) with their space-camera
    parameters, drawn as the closed loop draws them."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.factory import draw_corruption_params, with_appearance
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.datagen.render_cache import shared_renderer
    from envisat_pose.datagen.views import sample_seed, sequence_view

    cfg = from_dict(GenerateConfig, {"mode": "sequence", "num_images": 30 * n, "resolution_px": 1024})
    r = shared_renderer(cfg.resolution_px, cfg.shadows, 0, 0)
    frames = []
    for i in range(n):
        k = 30 * i
        view, x, scene = sequence_view(cfg, k)
        view, _ = with_appearance(cfg, view, scene, sample_seed(cfg.seed, 0, k))
        out = r.render(view)
        rng = np.random.default_rng(sample_seed(cfg.seed, 0, k))
        frames.append((out.gray_u8, draw_corruption_params(cfg, out, x, r.K[0, 0], r.target_boxes, rng)))
    return frames


def time_ms(fn, frames, repeats: int) -> list[float]:
    """Per-frame times (ms) of fn(image, params), each frame `repeats` times after one warm-up."""
    times = []
    for img, p in frames:
        fn(img, p)
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn(img, p)
            times.append(1e3 * (time.perf_counter() - t0))
    return times


def class_moments(fn, frames, seeds: int) -> dict:
    """Mean and variance of the 8-bit output over `seeds` noise seeds, averaged over the unlit and the lit
    pixels (clean value 0 or not) of every frame."""
    acc = {"unlit": [0.0, 0.0, 0], "lit": [0.0, 0.0, 0]}
    for img, p in frames:
        s1 = np.zeros(img.shape)
        s2 = np.zeros(img.shape)
        for k in range(seeds):
            o = fn(img, {**p, "noise_seed": 10_000 + k}).astype(np.float64)
            s1 += o
            s2 += o * o
        m = s1 / seeds
        v = s2 / seeds - m * m
        for name, sel in (("unlit", img == 0), ("lit", img > 0)):
            acc[name][0] += m[sel].sum()
            acc[name][1] += v[sel].sum()
            acc[name][2] += int(sel.sum())
    return {k: {"mean": a[0] / a[2], "var": a[1] / a[2], "pixels": a[2]} for k, a in acc.items()}


def main(argv=None) -> int:
    from _common import WholeFlagParser, count, description, out_file, provenance, write_json  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--frames", type=count(), default=6)
    ap.add_argument("--repeats", type=count(), default=5)
    ap.add_argument("--seeds", type=count(), default=40)
    ap.add_argument("--reference", default=REFERENCE_COMMIT)
    ap.add_argument("--out", type=out_file, default=os.path.join(ROOT, "bench", "results", "sensor_speed.json"))
    args = ap.parse_args(argv)

    import cv2

    cv2.setNumThreads(1)  # as in a factory worker
    from envisat_pose.datagen import sensor

    frames = closed_loop_frames(args.frames)
    impls = {"current": sensor.apply_sensor}
    ref = reference_module(args.reference)
    if ref is None:
        print(f"sensor_speed: --reference {args.reference}: git cannot show its datagen/sensor.py here; the current "
              "implementation alone", file=sys.stderr)
    else:
        impls = {f"previous ({args.reference})": ref.apply_sensor, **impls}
    rows = {}
    for name, fn in impls.items():
        t = time_ms(fn, frames, args.repeats)
        rows[name] = {"ms_median": float(np.median(t)), "ms_p90": float(np.percentile(t, 90)),
                      "ms_mean": float(np.mean(t)), "moments": class_moments(fn, frames, args.seeds)}
    print(f"space camera on {len(frames)} closed-loop frames (1024 px, sequence-mode defaults), 1 thread")
    print(f"{'implementation':24s} {'median ms':>10s} {'p90 ms':>8s}   unlit mean/var      lit mean/var")
    for name, r in rows.items():
        mu, ml = r["moments"]["unlit"], r["moments"]["lit"]
        print(f"{name:24s} {r['ms_median']:10.1f} {r['ms_p90']:8.1f}   {mu['mean']:7.4f}/{mu['var']:7.4f}  "
              f"{ml['mean']:8.3f}/{ml['var']:7.3f}")
    names = list(rows)
    speedup = rows[names[0]]["ms_median"] / rows[names[-1]]["ms_median"] if len(names) > 1 else None
    if speedup:
        print(f"speed-up (median): {speedup:.1f}x")
    result = {"bench": "sensor_speed", "frames": len(frames), "repeats": args.repeats, "seeds": args.seeds,
              "resolution_px": 1024, "cv2_threads": 1, "reference_commit": args.reference if ref else None,
              "implementations": rows, "speedup_median": speedup,
              "params": [{k: p[k] for k in ("psf", "adc_bits", "white_e", "full_well_e", "read_noise_e",
                                            "dark_current_e_per_s", "exposure_s", "motion_blur_length_px")}
                         for _, p in frames],
              "lit_share": float(np.mean([(img > 0).mean() for img, _ in frames])),
              "machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                          "cpus": os.cpu_count()}}
    result["provenance"] = provenance(args)
    write_json(args.out, result, indent=2, sort_keys=True)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
