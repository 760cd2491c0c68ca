"""A camera whose focal length is off, tracked with and without the cold start's focal check: what it refuses, what
it lets through, and what it costs a right camera.

One sequence (`envisat generate --mode sequence`, the scenario, seed and frames given) is tracked (`envisat track`'s
pipeline function, the shipped detector) through the MJCF camera its frames were made with, and through that camera
with its focal length times each factor of --factors; each once with the focal check (pipelines/tracking/
focal_check.py, the default) and once without it (`[tracker.integrity] focal_check = false`), its peer. Per run,
scored against the labels' truth (pipelines/runs/scoring.py: wrong is 5 deg or 2 % of range): whether it tracked,
its first claim (s), the seconds claimed while wrong, the second half's range error (estimate over truth, claimed
frames) and the last cold start's refusal (its reason names the focal length the frames read and the likelihood
ratio). The floors: 0 s claimed while wrong for factors the check refuses, the right camera's first claim as
without the check.

Run:  .venv/bin/python bench/focal_check.py --seed 21 --num-images 200
      (writes bench/results/focal_check.json; ~5 min on 2 cores)
"""

from __future__ import annotations

import dataclasses
import os
import sys
import tempfile

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

FACTORS = (1.0, 0.8, 0.9, 1.1, 1.15, 1.25, 2.0)


def track_once(folder: str, scenario: str, factor: float, check: bool, out_dir: str) -> dict:
    """The sequence in folder tracked through the MJCF camera with its focal length times factor, the focal check on
    or off: the run's figures (module doc)."""
    from envisat_pose.geometry import load_camera
    from envisat_pose.io import open_npz
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.frames import open_source
    from envisat_pose.pipelines.runs.scoring import claims_estimate
    from envisat_pose.pipelines.runs.track import track_frames

    cfg = resolve_job("track", scenario, None, {"tracker.integrity.focal_check": check})
    cam = load_camera()
    camera = dataclasses.replace(cam, f_px=cam.f_px * factor)
    summary = track_frames(cfg, open_source(folder), camera, None, out_dir, progress=False)
    scores = summary["scores"]
    with open_npz(os.path.join(out_dir, "est.npz")) as z:
        x_hat, x_true, status = z["x_hat"][0], z["x_true"][0], z["status"][0]
    half = np.arange(len(status)) >= len(status) // 2
    use = half & claims_estimate(status)
    ratio = np.linalg.norm(x_hat[use, :3], axis=1) / np.linalg.norm(x_true[use, :3], axis=1)
    return {"factor": factor, "check": check, "tracked": bool(summary["tracked"]),
            "first_tracking_s": summary["first_tracking_s"], "false_lock_s": float(scores["false_lock_s"]),
            "range_ratio_2nd_half": float(np.median(ratio)) if len(ratio) else None,
            "last_cold_start_refusal": summary["last_cold_start_refusal"]}


def main() -> int:
    from _common import WholeFlagParser, count, description, out_file, positive, provenance, results_path, write_json

    from envisat_pose.config import resolve_job_config
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig

    p = WholeFlagParser(description=description(__doc__))
    p.add_argument("--scenario", default="default")
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--num-images", type=count(20), default=200)
    p.add_argument("--factors", type=positive, nargs="+", default=list(FACTORS),
                   help="focal-length factors of the camera the tracker is given (1: the frames' own)")
    p.add_argument("--out", type=out_file, default=results_path("focal_check"))
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="focal_check_") as work:
        folder = os.path.join(work, "seq")
        gcfg = resolve_job_config(GenerateConfig, {}, None, {"mode": "sequence", "num_images": args.num_images,
                                                             "seed": args.seed, "sequence.scenario": args.scenario})
        run_generate(gcfg, folder)
        print(f"{'factor':>6} {'check':>5} {'tracked':>7} {'first s':>7} {'wrong s':>7} {'range':>6}  refusal")
        for factor in args.factors:
            for check in (True, False):
                r = track_once(folder, args.scenario, factor, check, os.path.join(work, f"t-{factor}-{check}"))
                rows.append(r)
                first = "-" if r["first_tracking_s"] is None else f"{r['first_tracking_s']:.0f}"
                rr = "-" if r["range_ratio_2nd_half"] is None else f"{r['range_ratio_2nd_half']:.3f}"
                why = (r["last_cold_start_refusal"] or "")[:90]
                print(f"{factor:6.2f} {'on' if check else 'off':>5} {str(r['tracked']):>7} {first:>7} "
                      f"{r['false_lock_s']:7.0f} {rr:>6}  {why}", flush=True)
    write_json(args.out, {"bench": "focal_check", **provenance(args), "runs": rows}, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from _common import run_main

    run_main(main)
