"""Training speed of `envisat train`'s own loop: samples/s on this CPU and, where one is, on a GPU.

Three parts side by side in one run: the model step alone on a synthetic batch (no data:
forward, losses, backward, clipping, AdamW; the multi-tensor optimizer against the per-parameter loop, fp32 and
bf16, with the op count of one step from torch.profiler and, on CUDA, the GPU busy share: kernel time over wall
time), the data path alone (the DataLoader's batches, nothing trained), and the whole loop below.

The pipeline the verb calls (pipelines/detector/train.py: DataLoader workers each reading their own shards,
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

import dataclasses
import itertools
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import torch

TOP_OPS = 10  # the step rows name the ops with the most self time

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
    from envisat_pose.pipelines.detector.train import train_detector

    cfg = TrainConfig(steps=steps, batch_size=batch_size, warmup_steps=min(10, steps),
                      checkpoint_every=10 ** 6)
    t0 = time.perf_counter()
    end = train_detector(cfg, [data], run_dir, device=device, workers=workers, bf16=bf16, progress=False,
                         command="bench/train_speed.py")
    return {"source": "shards", "device": device, "workers": workers, "bf16": bf16, "batch_size": batch_size,
            "steps": end["step"],
            "samples_s": end["samples_s"], "first_batch_s": end["first_batch_s"],
            "data_wait_s": end["data_wait_s"], "wall_s": round(time.perf_counter() - t0, 2),
            "loss_end": round(end["loss"], 4)}


def synthetic_batch(batch_size: int, input_px: int, seed: int) -> dict:
    """A batch of the trainer's shapes from real targets (corners drawn in the input, encoded as in training)."""
    import numpy as np

    from envisat_pose.perception.data import line_targets
    from envisat_pose.perception.heatmaps import CORNER_JTYPE, encode_junctions
    from envisat_pose.perception.stream import collate_batch

    rng = np.random.default_rng(seed)
    samples = []
    for _ in range(batch_size):
        corners = rng.uniform(0.2, 0.8, (8, 2)) * input_px
        valid = rng.random(8) < 0.75
        cells = input_px // 4
        t = encode_junctions(corners, valid, CORNER_JTYPE, (cells, cells), 4, 1.0)
        segs, lab, wt = line_targets(corners, valid, rng, input_px)
        samples.append({"image": rng.normal(size=(1, input_px, input_px)).astype(np.float32), "jmap": t["jmap"],
                        "joff": t["joff"], "jmask": t["jmask"], "segments_px": segs, "line_label": lab,
                        "line_weight": wt})
    return collate_batch(samples)


def time_step(device: str, batch_size: int, bf16: bool, foreach: bool, steps: int) -> dict:
    """The model step alone (default network) on one synthetic batch, repeated: ms a step, samples/s, aten ops
    of one step (profiler), and on CUDA the busy share (kernel time / wall time over the profiled steps)."""
    from torch.profiler import ProfilerActivity, profile

    from envisat_pose.perception.train import TrainConfig, Trainer, init_model

    cfg = TrainConfig(batch_size=batch_size)
    dev = torch.device(device)
    model = init_model(cfg).to(dev)
    if dev.type == "cuda":
        model = model.to(memory_format=torch.channels_last)
    kind = {"fused": True} if (foreach and dev.type == "cuda") else {"foreach": foreach}
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, **kind)
    batch = {k: v.to(dev) for k, v in synthetic_batch(batch_size, cfg.model.input_px, 0).items()}

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    def run_steps(n):  # the trainer's loop with no hook: n steps on the batch already on the device
        Trainer(dataclasses.replace(cfg, steps=n), model, opt, dev=dev, bf16=bf16).run(itertools.repeat((batch, {}), n))

    run_steps(2)  # warm-up: allocator, cuDNN's choice of kernels
    sync()
    t0 = time.perf_counter()
    run_steps(steps)
    sync()
    ms = (time.perf_counter() - t0) / steps * 1e3
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    n_prof = 3
    with profile(activities=acts) as prof:
        t1 = time.perf_counter()
        run_steps(n_prof)
        sync()
        wall = time.perf_counter() - t1
    events = prof.key_averages()
    ops = sum(e.count for e in events if e.key.startswith("aten::")) / n_prof
    # where the time goes: the ops with the most self time (the device's on CUDA, the host's on a CPU)
    own = [(e.key, (getattr(e, "self_device_time_total", 0.0) if dev.type == "cuda" else e.self_cpu_time_total))
           for e in events]
    total_us = sum(t for _, t in own) or 1.0
    top = [{"op": k, "ms_step": round(t / n_prof * 1e-3, 2), "share": round(t / total_us, 3)}
           for k, t in sorted(own, key=lambda kt: -kt[1])[:TOP_OPS] if t > 0]
    # the calls that read a value back to the host (each stalls a GPU's queue; on a CPU they cost nothing)
    syncs = sum(e.count for e in events if e.key in ("aten::nonzero", "aten::item"))
    busy = None
    if dev.type == "cuda":
        kernel_us = sum(getattr(e, "self_device_time_total", 0.0) for e in events)
        busy = round(kernel_us * 1e-6 / wall, 3)
    return {"part": "step", "device": device, "batch_size": batch_size, "bf16": bf16,
            "optimizer": ("fused" if dev.type == "cuda" else "foreach") if foreach else "per-parameter",
            "ms_step": round(ms, 1), "samples_s": round(batch_size / ms * 1e3, 1), "aten_ops_step": round(ops),
            "host_reads_step": round(syncs / n_prof, 1), "gpu_busy": busy, "top_ops": top}


def time_data(data: str, workers: int, batch_size: int, batches: int) -> dict:
    """The data path alone: the first `batches` batches of epoch 0 from `workers` processes, nothing trained."""
    from envisat_pose.perception.data import DataConfig, shard_paths
    from envisat_pose.perception.stream import epoch_batches

    t0 = time.perf_counter()
    it = epoch_batches(shard_paths(data), DataConfig(), 0, 0, batch_size, workers)
    n, first = 0, None
    for _ in it:
        n += 1
        if first is None:
            first = time.perf_counter() - t0
        if n >= batches:
            break
    total = time.perf_counter() - t0
    del it
    # from the call to the last batch, the workers' start included (a shuffle buffer fills before the first batch)
    return {"part": "data", "source": "shards", "workers": workers, "batch_size": batch_size, "batches": n,
            "first_batch_s": round(first or 0.0, 2), "samples_s": round(n * batch_size / total, 1)}



def online_config(resolution_px: int, workers: int):
    """The online source of `envisat train --online` at resolution_px (the generate defaults in random mode, seed
    1), K = 8."""
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.pipelines.detector.train import OnlineConfig

    return OnlineConfig(GenerateConfig(mode="random", resolution_px=resolution_px, seed=1), workers, 8)


def time_online_data(resolution_px: int, workers: int, batch_size: int, batches: int, device: str) -> dict:
    """The online data path alone: `batches` batches of pipelines/detector/online.online_batches (renderer processes, the
    crops and augmentation in batch on the device), nothing trained; the renderers' start is first_batch_s."""
    from envisat_pose.perception.data import DataConfig
    from envisat_pose.pipelines.detector.online import online_batches

    src = online_config(resolution_px, workers)
    t0 = time.perf_counter()
    it = online_batches(src.looks, DataConfig(), 0, batch_size, workers, device, src.uses_per_frame)
    n, first, state = 0, None, {}
    try:
        for _, state in it:
            n += 1
            if first is None:
                first = time.perf_counter() - t0
                t1 = time.perf_counter()
            if n > batches:
                break
    finally:
        it.close()
    span = time.perf_counter() - t1
    frames = state.get("frames_taken", 0)
    return {"part": "data", "source": "online", "device": device, "workers": workers, "batch_size": batch_size,
            "resolution_px": resolution_px, "batches": batches, "first_batch_s": round(first or 0.0, 2),
            "samples_s": round(batches * batch_size / span, 1), "frames_rendered": frames,
            "frames_s": round(batches * batch_size / src.uses_per_frame / span, 1)}


def time_online_training(run_dir: str, device: str, workers: int, bf16: bool, steps: int, batch_size: int,
                         resolution_px: int) -> dict:
    """One fresh online run (`envisat train --online`) of `steps` steps through the pipeline."""
    from envisat_pose.perception.train import TrainConfig
    from envisat_pose.pipelines.detector.train import train_detector

    cfg = TrainConfig(steps=steps, batch_size=batch_size, warmup_steps=min(10, steps), checkpoint_every=10 ** 6)
    t0 = time.perf_counter()
    end = train_detector(cfg, [], run_dir, device=device, bf16=bf16, progress=False, command="bench/train_speed.py",
                         online=online_config(resolution_px, workers))
    return {"source": "online", "device": device, "workers": workers, "bf16": bf16, "batch_size": batch_size,
            "resolution_px": resolution_px, "steps": end["step"], "samples_s": end["samples_s"],
            "first_batch_s": end["first_batch_s"], "data_wait_s": end["data_wait_s"],
            "wall_s": round(time.perf_counter() - t0, 2), "loss_end": round(end["loss"], 4)}

def save(args, rows: list[dict], parts: list[dict]) -> None:
    """Write what was measured so far (after every row: a run stopped at its time limit keeps its rows),
    atomically."""
    from _common import provenance  # bench/_common.py, beside this script

    from envisat_pose.io import atomic_write_text
    from envisat_pose.pipelines.detector.train import dataset_provenance

    cores = len(os.sched_getaffinity(0))
    result = {"torch": torch.__version__, "machine": platform.processor() or platform.machine(), "cores": cores,
              "torch_threads": torch.get_num_threads(), "load_average_1min_end": round(os.getloadavg()[0], 2),
              "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "data": dataset_provenance(args.data) if args.data else
              {"generate": f"--num-images {args.images} --shard-size {args.shard_size} --seed 1 (1024 px, defaults)",
               "gpu_generate": f"--num-images {args.gpu_images} --shard-size {args.gpu_shard_size} --seed 1"},
              "rows": rows, "parts": parts, "provenance": provenance(args),
              "note": "envisat train's loop through envisat_pose.pipelines.detector.train.train_detector, the default "
                      "network (TrainConfig defaults), a fresh run per row; samples/s from the first batch to the "
                      "final checkpoint. parts: the model step alone on a synthetic batch (its optimizer per "
                      "parameter or multi-tensor; top_ops: where its time goes) and the data path alone. A loaded "
                      "machine (load average above the cores) reads slower."}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=1, sort_keys=True) + "\n")


def main() -> None:
    from _common import WholeFlagParser, count, dataset, description, out_file, results_path  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--steps", type=count(), default=24, help="steps per CPU row")
    ap.add_argument("--batch-size", type=count(), default=8, help="batch of the CPU rows")
    ap.add_argument("--images", type=count(), default=40, help="images generated for the CPU rows")
    ap.add_argument("--shard-size", type=count(), default=10)
    ap.add_argument("--gpu-steps", type=count(), default=300, help="steps per GPU row")
    ap.add_argument("--gpu-batch-sizes", type=count(), nargs="+", default=[64],
                    help="batches of the GPU rows, each in both precisions (e.g. 64 128 256)")
    ap.add_argument("--gpu-images", type=count(), default=1920, help="images generated for the GPU rows")
    ap.add_argument("--gpu-shard-size", type=count(), default=64)
    ap.add_argument("--data", type=dataset, help="an existing dataset for every row instead of generating")
    ap.add_argument("--no-cpu", action="store_true", help="GPU rows only")
    ap.add_argument("--step-steps", type=count(), default=4, help="timed steps per model-step row (CPU)")
    ap.add_argument("--gpu-step-steps", type=count(), default=50, help="timed steps per model-step row (GPU)")
    ap.add_argument("--no-whole", action="store_true", help="the step and data parts only")
    ap.add_argument("--no-online", action="store_true", help="no online rows (frames rendered as training goes)")
    ap.add_argument("--online-resolution", type=count(), default=512,
                    help="renders' side of the CPU's online rows (the GPU's: 1024, the recipe's)")
    ap.add_argument("--online-steps", type=count(), default=12, help="steps per CPU online row")
    ap.add_argument("--out", type=out_file, default=results_path("train_speed"))
    args = ap.parse_args()
    cores = len(os.sched_getaffinity(0))
    parts, rows = [], []
    devices = ([] if args.no_cpu else ["cpu"]) + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        for batch in ([args.batch_size] if device == "cpu" else args.gpu_batch_sizes):
            for bf16 in (False, True):
                for foreach in (False, True):
                    row = time_step(device, batch, bf16, foreach,
                                    args.step_steps if device == "cpu" else args.gpu_step_steps)
                    parts.append(row)
                    save(args, rows, parts)
                    print(f"step  {device:5s} batch {batch:3d} {'bf16' if bf16 else 'fp32'} {row['optimizer']:13s}: "
                          f"{row['ms_step']:8.1f} ms, {row['samples_s']:8.1f} samples/s, {row['aten_ops_step']} aten "
                          f"ops, {row['host_reads_step']} host reads, GPU busy {row['gpu_busy']}; most time: "
                          + ", ".join(f"{t['op']} {100 * t['share']:.0f} %" for t in row["top_ops"][:4]), flush=True)
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
        for data, device, workers in sorted({(p[0], p[1], p[2]) for p in plans}):
            batch = args.batch_size if device == "cpu" else max(args.gpu_batch_sizes)
            row = time_data(data, workers, batch, 6 if device == "cpu" else 100)
            parts.append({**row, "device": device})
            save(args, rows, parts)
            print(f"data  {device:5s} workers {workers:2d} batch {batch:3d}: {row['samples_s']} samples/s (first batch "
                  f"{row['first_batch_s']} s)", flush=True)
        for i, plan in enumerate([] if args.no_whole else plans):
            row = time_training(plan[0], os.path.join(tmp, f"run{i}"), *plan[1:])
            rows.append(row)
            save(args, rows, parts)
            print(f"{row['device']:5s} workers {row['workers']:2d} {'bf16' if row['bf16'] else 'fp32'} batch "
                  f"{row['batch_size']:3d}: {row['samples_s']:8.1f} samples/s (first batch {row['first_batch_s']:.1f} "
                  f"s, waited for data {row['data_wait_s']:.1f} s of {row['wall_s']:.1f} s)", flush=True)
        # online: renderer processes (the cores less one) hand frames straight to the trainer, no shards
        online_plans = [] if args.no_online else \
            ([("cpu", max(cores - 1, 1), args.online_steps, args.batch_size, args.online_resolution)]
             if not args.no_cpu else []) + \
            ([("cuda", max(cores - 1, 1), args.gpu_steps, b, 1024) for b in args.gpu_batch_sizes]
             if torch.cuda.is_available() else [])
        for device, workers, steps, batch, res in online_plans:
            row = time_online_data(res, workers, batch, 6 if device == "cpu" else 50, device)
            parts.append(row)
            save(args, rows, parts)
            print(f"data  {device:5s} online {res} px, {workers:2d} renderers, batch {batch:3d}: {row['samples_s']} "
                  f"samples/s, {row['frames_s']} frames/s (first batch {row['first_batch_s']} s)", flush=True)
        for i, (device, workers, steps, batch, res) in enumerate([] if args.no_whole else online_plans):
            for bf16 in ((True,) if device == "cpu" else (False, True)):
                row = time_online_training(os.path.join(tmp, f"online{i}{int(bf16)}"), device, workers, bf16, steps,
                                           batch, res)
                rows.append(row)
                save(args, rows, parts)
                print(f"{device:5s} online {res} px, {workers:2d} renderers {'bf16' if bf16 else 'fp32'} batch "
                      f"{batch:3d}: {row['samples_s']:8.1f} samples/s (first batch {row['first_batch_s']:.1f} s, "
                      f"waited for data {row['data_wait_s']:.1f} s of {row['wall_s']:.1f} s)", flush=True)
    print(f"\n{'source':7s} {'device':6s} {'workers':>7s} {'precision':>9s} {'batch':>5s} {'samples/s':>10s} "
          f"{'data wait s':>11s}")
    for r in rows:
        print(f"{r['source']:7s} {r['device']:6s} {r['workers']:7d} {'bf16' if r['bf16'] else 'fp32':>9s} "
              f"{r['batch_size']:5d} {r['samples_s']:10.1f} {r['data_wait_s']:11.1f}")
    save(args, rows, parts)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
