"""Training speed of `envisat train`'s own loop (issue 26): samples/s on this CPU and, where one is, on a GPU.

The pipeline the verb calls (pipelines/train.py: DataLoader workers each reading their own shards,
the default network, the losses, AdamW, checkpoints) trains a fresh run for a few dozen steps per row: workers
0 (in-process), 1 and the cores less one, in float32 and with bf16 autocast; on CUDA (`torch.cuda.is_available()`)
the cores less one at each of the GPU batches asked for (--gpu-batch-sizes), both precisions. samples/s counts
from the first batch's arrival to the final checkpoint (the workers' start-up is `first_batch_s`, apart);
`data_wait_s` is the time the loop waited for batches. The data: `envisat generate --seed 1` in a child process
(--images, --shard-size; 1024 px, the default config), or --data. Writes bench/results/train_speed.json. Run it
where the package is installed, or from outside the checkout when the package is laid out by
scripts/gpu_layout.py (its worker processes start from the current folder, whose `envisat_pose/` holds the core
alone).

    nice -n 10 .venv/bin/python bench/train_speed.py [--steps 24] [--batch-size 8] [--data DIR] [--out ...json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import torch


def make_data(out_dir: str, images: int, shard_size: int) -> str:
    """`envisat generate --num-images images --shard-size shard_size --seed 1` on every core (child process)."""
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "osmesa"))
    cores = len(os.sched_getaffinity(0))
    subprocess.run([sys.executable, "-m", "envisat_pose.app.cli", "generate", "--num-images", str(images),
                    "--shard-size", str(shard_size), "--seed", "1", "--workers", str(cores), "--out", out_dir,
                    "--quiet"], check=True, env=env)
    return out_dir


def time_training(data: str, run_dir: str, device: str, workers: int, bf16: bool, steps: int,
                  batch_size: int) -> dict:
    """One fresh run of `steps` steps through the pipeline; its end line's speed figures."""
    from envisat_pose.perception.train import TrainConfig
    from envisat_pose.pipelines.train import train_detector

    cfg = TrainConfig(steps=steps, batch_size=batch_size, warmup_steps=min(10, steps),
                      checkpoint_every=10 ** 6)
    t0 = time.perf_counter()
    end = train_detector(cfg, [data], run_dir, device=device, workers=workers, bf16=bf16, progress=False,
                         command="bench/train_speed.py")
    return {"device": device, "workers": workers, "bf16": bf16, "batch_size": batch_size, "steps": end["step"],
            "samples_s": end["samples_s"], "first_batch_s": end["first_batch_s"],
            "data_wait_s": end["data_wait_s"], "wall_s": round(time.perf_counter() - t0, 2),
            "loss_end": round(end["loss"], 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=24, help="steps per CPU row")
    ap.add_argument("--batch-size", type=int, default=8, help="batch of the CPU rows")
    ap.add_argument("--images", type=int, default=40, help="images generated for the CPU rows")
    ap.add_argument("--shard-size", type=int, default=10)
    ap.add_argument("--gpu-steps", type=int, default=300, help="steps per GPU row")
    ap.add_argument("--gpu-batch-sizes", type=int, nargs="+", default=[64],
                    help="batches of the GPU rows, each in both precisions (e.g. 64 128 256)")
    ap.add_argument("--gpu-images", type=int, default=1920, help="images generated for the GPU rows")
    ap.add_argument("--gpu-shard-size", type=int, default=64)
    ap.add_argument("--data", help="an existing dataset for every row instead of generating")
    ap.add_argument("--no-cpu", action="store_true", help="GPU rows only")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "train_speed.json"))
    args = ap.parse_args()
    from envisat_pose.pipelines.train import dataset_provenance

    cores = len(os.sched_getaffinity(0))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        plans = []
        if not args.no_cpu:
            data = args.data or make_data(os.path.join(tmp, "cpu"), args.images, args.shard_size)
            for workers in sorted({0, 1, max(cores - 1, 0)}):
                plans += [(data, "cpu", workers, bf16, args.steps, args.batch_size) for bf16 in (False, True)]
        if torch.cuda.is_available():
            data = args.data or make_data(os.path.join(tmp, "gpu"), args.gpu_images, args.gpu_shard_size)
            plans += [(data, "cuda", max(cores - 1, 0), bf16, args.gpu_steps, batch)
                      for batch in args.gpu_batch_sizes for bf16 in (False, True)]
        for i, plan in enumerate(plans):
            row = time_training(plan[0], os.path.join(tmp, f"run{i}"), *plan[1:])
            rows.append(row)
            print(f"{row['device']:5s} workers {row['workers']:2d} {'bf16' if row['bf16'] else 'fp32'} batch "
                  f"{row['batch_size']:3d}: {row['samples_s']:8.1f} samples/s (first batch {row['first_batch_s']:.1f} "
                  f"s, waited for data {row['data_wait_s']:.1f} s of {row['wall_s']:.1f} s)", flush=True)
    print(f"\n{'device':6s} {'workers':>7s} {'precision':>9s} {'batch':>5s} {'samples/s':>10s} {'data wait s':>11s}")
    for r in rows:
        print(f"{r['device']:6s} {r['workers']:7d} {'bf16' if r['bf16'] else 'fp32':>9s} {r['batch_size']:5d} "
              f"{r['samples_s']:10.1f} {r['data_wait_s']:11.1f}")
    result = {"torch": torch.__version__, "machine": platform.processor() or platform.machine(), "cores": cores,
              "torch_threads": torch.get_num_threads(), "load_average_1min_end": round(os.getloadavg()[0], 2),
              "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "data": dataset_provenance(args.data) if args.data else
              {"generate": f"--num-images {args.images} --shard-size {args.shard_size} --seed 1 (1024 px, defaults)",
               "gpu_generate": f"--num-images {args.gpu_images} --shard-size {args.gpu_shard_size} --seed 1"},
              "rows": rows,
              "note": "envisat train's loop through envisat_pose.pipelines.train.train_detector, the default "
                      "network (TrainConfig defaults), a fresh run per row; samples/s from the first batch to the "
                      "final checkpoint. A loaded machine (load average above the cores) reads slower."}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=1, sort_keys=True)
        fh.write("\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
