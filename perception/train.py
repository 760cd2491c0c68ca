"""The training loop: batches from worker processes (perception/stream.py), the model, the losses, checkpoints in
a run directory.

Run directory (one per run, as L-CNN's):
    config.json         the frozen TrainConfig (model, data, loss, schedule), the command and the git hash
    metrics.jsonl       one JSON line per epoch (a pass over the data) and one at the end: step, loss terms, time;
                        the end line also this call's speed (samples_s, first_batch_s, data_wait_s, workers)
    checkpoint.safetensors   the model (perception/weights.py: safetensors, the ModelConfig in its metadata)
    optimizer.pt        AdamW state, tensors only (torch.load(weights_only=True) reads it)
    state.json          step, epoch, batch within the epoch, workers, time_s: where --resume goes on
Determinism: the model is initialized from a torch.Generator seeded by cfg.seed (no global seeding), each
sample's crop and augmentation from (seed, epoch, shard, index), the batches of an epoch from (seed, epoch,
worker count); a resumed run skips the batches its epoch already did. With a time budget the learning rate
follows the clock, so such a run is not bitwise repeatable (its data order still is).
DDP: when torch.distributed is initialized (torchrun), each rank reads its own shards (perception/stream.py),
gradients are averaged, and only rank 0 writes; a budgeted run stops on rank 0's clock.
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
from envisat_pose.perception.data import DataConfig, shard_paths
from envisat_pose.perception.losses import LossConfig, corner_losses
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.stream import epoch_loader
from envisat_pose.perception.weights import load_state, load_tensors, read_weights, save_tensors, save_weights


@dataclass(frozen=True)
class TrainConfig:
    """steps: optimizer steps in all; batch_size: per rank; lr: AdamW peak rate (cosine decay after warmup_steps);
    seed: root seed of the weights' initialization and the data order; checkpoint_every: steps between
    checkpoints; line_jitter_px: noise on the segments' end points (the verifier sees detected, not true, corners);
    time_budget_s: when positive, the run's seconds: the rate decays over them instead of over the steps and the
    run stops inside them with a checkpoint (steps then only caps it)."""

    steps: int = 20000
    batch_size: int = 16
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    seed: int = 0
    checkpoint_every: int = 500
    line_jitter_px: float = 1.0
    time_budget_s: float = 0.0
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    loss: LossConfig = field(default_factory=LossConfig)

    def validate(self, prefix: str = "") -> None:
        from envisat_pose.config import check

        p = f"{prefix}." if prefix else ""
        check(self.steps >= 1, f"{p}steps", self.steps, "at least 1 step")
        check(self.batch_size >= 1, f"{p}batch_size", self.batch_size, "at least 1 sample per batch")
        check(self.lr > 0, f"{p}lr", self.lr, "a positive learning rate")
        check(self.warmup_steps >= 1, f"{p}warmup_steps", self.warmup_steps, "at least 1 step")
        check(self.time_budget_s >= 0, f"{p}time_budget_s", self.time_budget_s, "seconds >= 0 (0: no budget)")
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


def to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """The batch on device (asynchronous from pinned memory on CUDA)."""
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def cosine_factor(frac: float) -> float:
    """The cosine decay from 1 at frac 0 to 0.05 at frac 1 (and after)."""
    return 0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * min(max(frac, 0.0), 1.0)))


def lr_at(cfg: TrainConfig, step: int, elapsed_s: float = 0.0) -> float:
    """The learning rate of optimizer step `step`: a linear warm-up over warmup_steps, then a cosine decay to 5 %
    over the steps, or, with a time budget, over the budget's seconds (the lower of the warm-up ramp and the
    decay at elapsed_s: a run stopped by its budget ends decayed even if its warm-up was not done)."""
    ramp = (step + 1) / cfg.warmup_steps if step < cfg.warmup_steps else 1.0
    if cfg.time_budget_s > 0:
        factor = min(ramp, cosine_factor(elapsed_s / cfg.time_budget_s))
    elif step < cfg.warmup_steps:
        factor = ramp
    else:
        factor = cosine_factor((step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps))
    # a Python float: it goes into the optimizer's state, which torch.load(weights_only=True) must read back
    return float(cfg.lr * factor)


def _dist():
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist, dist.get_rank(), dist.get_world_size()
    return None, 0, 1


RESUMABLE_CHANGES = ("steps", "time_budget_s")  # a resumed run may go further or longer, nothing else


def _check_resume(run_dir: str, cfg: TrainConfig) -> dict:
    path = os.path.join(run_dir, "config.json")
    if not os.path.exists(path):
        raise InputError(f"--resume: {run_dir!r} holds no config.json (not a run directory)")
    with open(path, encoding="utf-8") as fh:
        old = json.load(fh)["train"]
    new = cfg.to_dict()
    changed = sorted(k for k in new if k not in RESUMABLE_CHANGES and old.get(k) != new[k])
    if changed:
        raise InputError(f"--resume: {run_dir!r} was trained with another config ({', '.join(changed)} differ)")
    with open(os.path.join(run_dir, "state.json"), encoding="utf-8") as fh:
        return json.load(fh)


SHUTDOWN_RESERVE_S = 1.0  # a budgeted run keeps this for the final log, checkpoint and the workers' shutdown


def _autocast(dev: torch.device, bf16: bool):
    return torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16)


def _train_step(model: CornerNet, net: torch.nn.Module, opt, batch: dict, cfg: TrainConfig, step: int,
                dev: torch.device, bf16: bool) -> dict:
    """One optimizer step on a batch already on dev: the network (bf16 autocast when asked), the losses in
    float32, clipped gradients. Returns the loss terms (tensors)."""
    with _autocast(dev, bf16):
        out = net(batch["image"])
        segs = batch["segments_px"]
        if cfg.line_jitter_px > 0:
            gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)  # resumable: per step
            segs = segs + cfg.line_jitter_px * torch.randn(segs.shape, generator=gen).to(dev)
        logits = model.line_logits(out["features"], segs)
    out = {k: v.float() for k, v in out.items()}
    terms = corner_losses(out, batch, logits.float(), cfg.loss, cfg.model.stride)
    opt.zero_grad(set_to_none=True)
    terms["loss"].backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
    opt.step()
    return terms


def _shared_clock(dist, dev: torch.device, elapsed_s: float, reserve_s: float) -> tuple[float, float]:
    """Rank 0's clock for every rank (a budgeted DDP run must stop at the same step on all ranks)."""
    if dist is None:
        return elapsed_s, reserve_s
    t = torch.tensor([elapsed_s, reserve_s], dtype=torch.float64, device=dev)
    dist.broadcast(t, src=0)
    return float(t[0]), float(t[1])


def train(cfg: TrainConfig, data_dir: str | list[str], run_dir: str, resume: bool = False, device: str = "cpu",
          progress: bool = True, provenance: dict | None = None, init_weights: str | None = None,
          workers: int | None = None, bf16: bool = False, clock=time.perf_counter) -> dict:
    """Train (or go on training, with resume) into run_dir. Returns the last metrics line.

    data_dir: one dataset folder or several (their shards are read together). init_weights: a safetensors file
    of the same architecture to start from instead of the seeded initialization (fine-tuning; a new run only).
    workers: DataLoader worker processes feeding the batches (perception/stream.py; 0: in-process); None: the
    run's own count on resume, else 0. The batches depend on the count, so a resumed run keeps it. The workers
    start from a fork server, so a script calling this with workers guards its main (`if __name__ ==
    "__main__":`), as any multiprocessing program that does not fork.
    bf16: the network's forward under bfloat16 autocast (CUDA or CPU); losses, weights and optimizer in float32.
    With cfg.time_budget_s the run stops before the next step would leave too little of the budget for the
    final checkpoint (the budget counts from this call's start, plus what a resumed run had already used).
    clock: the seconds every time figure and the budget are read from (a test gives its own).
    """
    from tqdm import tqdm

    dist, rank, world = _dist()
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available")
    if workers is not None and workers < 0:
        raise InputError(f"--workers {workers}: expected 0 (in-process) or more worker processes")
    t_start = clock()
    dirs = [data_dir] if isinstance(data_dir, str) else list(data_dir)
    paths = [p for d in dirs for p in shard_paths(d)]
    model = init_model(cfg).to(dev)
    if init_weights is not None and not resume:
        tensors, _ = read_weights(init_weights)
        load_state(model, tensors, init_weights)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state = {"step": 0, "epoch": 0, "batch": 0, "workers": 0 if workers is None else workers, "time_s": 0.0}
    if resume:
        saved = _check_resume(run_dir, cfg)
        ran_with = int(saved.get("workers", 0))
        if workers is not None and workers != ran_with:
            raise InputError(f"--workers {workers}: {run_dir!r} was trained with {ran_with} (its batches depend on "
                             f"the count); resume it with --workers {ran_with}")
        state = {**state, **saved, "workers": ran_with}
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
    time0 = float(state["time_s"])

    def elapsed() -> float:
        return time0 + clock() - t_start

    bar = tqdm(total=cfg.steps, initial=state["step"], disable=not progress or rank != 0, desc="train", unit="step")
    sums: dict[str, float] = {}
    count = 0
    terms_mean: dict[str, float] = {}
    lr = lr_at(cfg, state["step"], time0)
    run = {"steps": 0, "first_batch_s": None, "data_wait_s": 0.0}  # this call's own figures
    iter_s: list[float] = []  # the last steps' wall times, data wait included
    checkpoint_s = 0.5  # until one is measured

    def checkpoint() -> None:
        if rank != 0:
            return
        state["time_s"] = round(elapsed(), 3)
        save_weights(os.path.join(run_dir, "checkpoint.safetensors"), model, {"step": str(state["step"])})
        save_tensors(os.path.join(run_dir, "optimizer.pt"), opt.state_dict())
        atomic_write_text(os.path.join(run_dir, "state.json"), json.dumps(state, sort_keys=True) + "\n")

    def log(kind: str, extra: dict | None = None) -> dict:
        """A metrics line: the loss terms averaged since the last line (an end line right after an epoch line
        repeats that line's terms)."""
        nonlocal sums, count, terms_mean
        if count:
            terms_mean = {k: v / count for k, v in sums.items()}
        line = {"kind": kind, "epoch": state["epoch"], "step": state["step"], "lr": lr, "time_s": round(elapsed(), 3),
                **terms_mean, **(extra or {})}
        if rank == 0:
            with open(os.path.join(run_dir, "metrics.jsonl"), "a", encoding="utf-8") as fh:
                fh.write(json.dumps(line, sort_keys=True) + "\n")
        sums, count = {}, 0
        return line

    def batches_of(epoch: int):
        return iter(epoch_loader(paths, cfg.data, cfg.seed, epoch, cfg.batch_size, state["workers"], rank, world,
                                 pin_memory=dev.type == "cuda"))

    stop = False
    upcoming = None  # the next epoch's batches, started early (with workers): no stall at the epoch boundary
    while state["step"] < cfg.steps and not stop:
        n_batches = 0
        skip = state["batch"]  # a resumed epoch: these batches were trained on before
        current = upcoming if upcoming is not None else batches_of(state["epoch"])
        upcoming = batches_of(state["epoch"] + 1) if state["workers"] > 0 else None
        t_ask = clock()
        for i, cpu_batch in enumerate(current):
            if i < skip:
                t_ask = clock()
                continue
            if state["step"] >= cfg.steps:
                break
            t_got = clock()
            run["data_wait_s"] += t_got - t_ask
            if run["first_batch_s"] is None:
                run["first_batch_s"] = t_got - t_start
            if cfg.time_budget_s > 0:
                reserve = 1.5 * max(iter_s[-10:], default=0.0) + checkpoint_s + SHUTDOWN_RESERVE_S
                now_s, reserve = _shared_clock(dist, dev, elapsed(), reserve)
                if now_s + reserve >= cfg.time_budget_s:
                    stop = True
                    break
            else:
                now_s = elapsed()
            lr = lr_at(cfg, state["step"], now_s)
            for g in opt.param_groups:
                g["lr"] = lr
            terms = _train_step(model, net, opt, to_device(cpu_batch, dev), cfg, state["step"], dev, bf16)
            state["step"] += 1
            state["batch"] = i + 1
            n_batches += 1
            run["steps"] += 1
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
            count += 1
            bar.update(1)
            bar.set_postfix(loss=f"{float(terms['loss'].detach()):.3f}")
            if state["step"] % cfg.checkpoint_every == 0:
                t_ck = clock()
                checkpoint()
                checkpoint_s = clock() - t_ck
            iter_s.append(clock() - t_ask)
            t_ask = clock()
        else:
            if n_batches == 0 and state["batch"] == 0:
                raise InputError(f"--data {data_dir!r}: fewer samples than one batch of {cfg.batch_size} per "
                                 f"worker ({state['workers']} workers, {len(paths)} shards, {world} ranks): "
                                 "use fewer workers or a smaller batch")
            log("epoch")
            state["epoch"] += 1
            state["batch"] = 0
            continue
        break
    current = upcoming = None  # the workers of both epochs shut down
    bar.close()
    ddp = {}
    if dist is not None:
        for b in model.buffers():  # BatchNorm statistics of the last forward are each rank's own: take rank 0's
            dist.broadcast(b, src=0)
        ddp = {"ranks_identical": float(_ranks_identical(dist, model, world)), "world": float(world)}
    checkpoint()
    loop_s = clock() - t_start - (run["first_batch_s"] or 0.0)
    speed = {"steps_run": run["steps"], "workers": state["workers"], "bf16": bf16,
             "samples_s": round(run["steps"] * cfg.batch_size * world / max(loop_s, 1e-9), 2),
             "first_batch_s": round(run["first_batch_s"] or 0.0, 3), "data_wait_s": round(run["data_wait_s"], 3),
             "stopped_by": "time_budget" if stop else "steps"}
    return log("end", {**ddp, **speed})


def _ranks_identical(dist, model: torch.nn.Module, world: int) -> bool:
    """Every rank holds the same parameters and buffers, bit for bit (gathered and compared on all ranks)."""
    flat = torch.cat([t.detach().reshape(-1).double().cpu() for t in model.state_dict().values()])
    gathered = [torch.empty_like(flat) for _ in range(world)]
    dist.all_gather(gathered, flat)
    return all(torch.equal(gathered[0], g) for g in gathered[1:])
