"""The training loop: batches from perception/data.py, the model, the losses, checkpoints in a run directory.

Run directory (one per run, as L-CNN's):
    config.json         the frozen TrainConfig (model, data, loss, schedule), the command and the git hash
    metrics.jsonl       one JSON line per epoch (a pass over the data) and one at the end: step, loss terms, time
    checkpoint.safetensors   the model (perception/weights.py: safetensors, the ModelConfig in its metadata)
    optimizer.pt        AdamW state, tensors only (torch.load(weights_only=True) reads it)
    state.json          step, epoch, batch within the epoch: where --resume goes on
Determinism: the model is initialized from a torch.Generator seeded by cfg.seed (no global seeding), each
sample's crop and augmentation from (seed, epoch, index); a resumed run skips the batches its epoch already did.
DDP: when torch.distributed is initialized (torchrun), each rank reads every world-th sample, gradients are
averaged, and only rank 0 writes.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from envisat_pose.config import InputError, from_dict
from envisat_pose.io import atomic_write_text
from envisat_pose.perception.data import DataConfig, iterate_samples, shard_paths
from envisat_pose.perception.losses import LossConfig, corner_losses
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import load_state, load_tensors, read_weights, save_tensors, save_weights


@dataclass(frozen=True)
class TrainConfig:
    """steps: optimizer steps in all; batch_size: per rank; lr: AdamW peak rate (cosine decay after warmup_steps);
    seed: root seed of the weights' initialization and the data order; checkpoint_every: steps between
    checkpoints; line_jitter_px: noise on the segments' end points (the verifier sees detected, not true, corners)."""

    steps: int = 20000
    batch_size: int = 16
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    seed: int = 0
    checkpoint_every: int = 500
    line_jitter_px: float = 1.0
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    loss: LossConfig = field(default_factory=LossConfig)

    def validate(self, prefix: str = "") -> None:
        from envisat_pose.config import check

        p = f"{prefix}." if prefix else ""
        check(self.steps >= 1, f"{p}steps", self.steps, "at least 1 step")
        check(self.batch_size >= 1, f"{p}batch_size", self.batch_size, "at least 1 sample per batch")
        check(self.lr > 0, f"{p}lr", self.lr, "a positive learning rate")
        check(self.model.input_px == self.data.input_px, f"{p}data.input_px", self.data.input_px,
              f"the model's input_px ({self.model.input_px})")
        check(self.data.stride == self.model.stride, f"{p}data.stride", self.data.stride, "the model's stride (4)")

    def to_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self)))


def config_from_dict(data: dict) -> TrainConfig:
    return from_dict(TrainConfig, data)


def init_model(cfg: TrainConfig) -> CornerNet:
    """A CornerNet whose weights are drawn from a generator seeded by cfg.seed (not the global one)."""
    model = CornerNet(cfg.model)
    gen = torch.Generator().manual_seed(cfg.seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if p.ndim > 1:
                fan_in = p[0].numel()
                std = (2.0 / fan_in) ** 0.5 * (0.01 if name.startswith("jhead.1") else 1.0)  # heads start calm
                p.copy_(torch.randn(p.shape, generator=gen) * std)
            elif name.endswith(".bias") and not name.startswith("jhead.1"):
                p.zero_()
    return model


def collate(samples: list[dict], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.stack([s[k] for s in samples])).to(device) for k in samples[0]}


def batches(paths: list[str], cfg: TrainConfig, epoch: int, rank: int, world: int):
    """Full batches of one epoch for this rank (the ragged end is dropped, so every rank takes the same count)."""
    buf = []
    for s in iterate_samples(paths, cfg.data, cfg.seed, epoch, rank, world, train=True):
        buf.append(s)
        if len(buf) == cfg.batch_size:
            yield buf
            buf = []


def lr_at(cfg: TrainConfig, step: int) -> float:
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    frac = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    # a Python float: it goes into the optimizer's state, which torch.load(weights_only=True) must read back
    return float(cfg.lr * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * min(frac, 1.0)))))


def _dist():
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist, dist.get_rank(), dist.get_world_size()
    return None, 0, 1


def _check_resume(run_dir: str, cfg: TrainConfig) -> dict:
    path = os.path.join(run_dir, "config.json")
    if not os.path.exists(path):
        raise InputError(f"--resume: {run_dir!r} holds no config.json (not a run directory)")
    with open(path, encoding="utf-8") as fh:
        old = json.load(fh)["train"]
    new = cfg.to_dict()
    changed = sorted(k for k in new if k != "steps" and old.get(k) != new[k])
    if changed:
        raise InputError(f"--resume: {run_dir!r} was trained with another config ({', '.join(changed)} differ)")
    with open(os.path.join(run_dir, "state.json"), encoding="utf-8") as fh:
        return json.load(fh)


def train(cfg: TrainConfig, data_dir: str | list[str], run_dir: str, resume: bool = False, device: str = "cpu",
          progress: bool = True, provenance: dict | None = None, init_weights: str | None = None) -> dict:
    """Train (or go on training, with resume) into run_dir. Returns the last metrics line.

    data_dir: one dataset folder or several (their shards are read together). init_weights: a safetensors file
    of the same architecture to start from instead of the seeded initialization (fine-tuning; a new run only).
    """
    from tqdm import tqdm

    dist, rank, world = _dist()
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available")
    dirs = [data_dir] if isinstance(data_dir, str) else list(data_dir)
    paths = [p for d in dirs for p in shard_paths(d)]
    model = init_model(cfg).to(dev)
    if init_weights is not None and not resume:
        tensors, _ = read_weights(init_weights)
        load_state(model, tensors, init_weights)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state = {"step": 0, "epoch": 0, "batch": 0}
    if resume:
        state = _check_resume(run_dir, cfg)
        tensors, _ = read_weights(os.path.join(run_dir, "checkpoint.safetensors"))
        load_state(model, tensors, os.path.join(run_dir, "checkpoint.safetensors"))
        opt.load_state_dict(load_tensors(os.path.join(run_dir, "optimizer.pt")))
    elif rank == 0:
        os.makedirs(run_dir, exist_ok=True)
        if os.path.exists(os.path.join(run_dir, "state.json")):
            raise InputError(f"--out {run_dir!r} already holds a run: use --resume, or another folder")
        atomic_write_text(os.path.join(run_dir, "config.json"), json.dumps(
            {"train": cfg.to_dict(), **(provenance or {})}, indent=1, sort_keys=True) + "\n")
    net = model
    if dist is not None:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)
    model.train()
    t0 = time.perf_counter()
    bar = tqdm(total=cfg.steps, initial=state["step"], disable=not progress or rank != 0, desc="train", unit="step")
    sums: dict[str, float] = {}
    count = 0
    last: dict = {}

    def checkpoint() -> None:
        if rank != 0:
            return
        save_weights(os.path.join(run_dir, "checkpoint.safetensors"), model, {"step": str(state["step"])})
        save_tensors(os.path.join(run_dir, "optimizer.pt"), opt.state_dict())
        atomic_write_text(os.path.join(run_dir, "state.json"), json.dumps(state, sort_keys=True) + "\n")

    def log(kind: str) -> dict:
        nonlocal sums, count
        line = {"kind": kind, "epoch": state["epoch"], "step": state["step"], "lr": lr_at(cfg, state["step"]),
                "time_s": round(time.perf_counter() - t0, 3), **{k: v / max(count, 1) for k, v in sums.items()}}
        if rank == 0:
            with open(os.path.join(run_dir, "metrics.jsonl"), "a", encoding="utf-8") as fh:
                fh.write(json.dumps(line, sort_keys=True) + "\n")
        sums, count = {}, 0
        return line

    while state["step"] < cfg.steps:
        n_batches = 0
        for i, samples in enumerate(batches(paths, cfg, state["epoch"], rank, world)):
            if i < state["batch"]:
                continue  # a resumed epoch: these were trained on before
            if state["step"] >= cfg.steps:
                break
            batch = collate(samples, dev)
            for g in opt.param_groups:
                g["lr"] = lr_at(cfg, state["step"])
            out = net(batch["image"])
            segs = batch["segments_px"]
            if cfg.line_jitter_px > 0:
                gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + state["step"])  # resumable: per step
                segs = segs + cfg.line_jitter_px * torch.randn(segs.shape, generator=gen).to(dev)
            logits = model.line_logits(out["features"], segs)
            terms = corner_losses(out, batch, logits, cfg.loss, cfg.model.stride)
            opt.zero_grad(set_to_none=True)
            terms["loss"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            opt.step()
            state["step"] += 1
            state["batch"] = i + 1
            n_batches += 1
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
            count += 1
            bar.update(1)
            bar.set_postfix(loss=f"{float(terms['loss'].detach()):.3f}")
            if state["step"] % cfg.checkpoint_every == 0:
                checkpoint()
        else:
            if n_batches == 0 and state["batch"] == 0:
                raise InputError(f"--data {data_dir!r}: fewer samples than one batch of {cfg.batch_size} per rank")
            last = log("epoch")
            state["epoch"] += 1
            state["batch"] = 0
            continue
        break
    bar.close()
    if dist is not None:
        for b in model.buffers():  # BatchNorm statistics of the last forward are each rank's own: take rank 0's
            dist.broadcast(b, src=0)
        sums["ranks_identical"] = float(_ranks_identical(dist, model, world)) * max(count, 1)
        sums["world"] = float(world) * max(count, 1)
    if count or dist is not None:
        last = log("end")
    checkpoint()
    return last


def _ranks_identical(dist, model: torch.nn.Module, world: int) -> bool:
    """Every rank holds the same parameters and buffers, bit for bit (gathered and compared on all ranks)."""
    flat = torch.cat([t.detach().reshape(-1).double().cpu() for t in model.state_dict().values()])
    gathered = [torch.empty_like(flat) for _ in range(world)]
    dist.all_gather(gathered, flat)
    return all(torch.equal(gathered[0], g) for g in gathered[1:])
