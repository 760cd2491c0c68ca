"""The training loop: batches from worker processes (perception/stream.py), the model, the losses, checkpoints in
a run directory.

Run directory (one per run, as L-CNN's):
    config.json         the frozen TrainConfig (model, data, loss, schedule), the command and the git hash
    metrics.jsonl       one JSON line per epoch (a pass over the data) and one at the end: step, loss terms, time;
                        the end line also this call's speed (samples_s, first_batch_s, data_wait_s, workers)
    checkpoint.safetensors   the model (perception/weights.py: safetensors, the ModelConfig in its metadata)
    optimizer.pt        AdamW state, tensors only (torch.load(weights_only=True) reads it)
    pre_cooldown.safetensors, pre_cooldown_optimizer.pt   (schedule 'constant_cooldown') the same at the
                        cooldown's first step (or at a budget's stop that came before it): the next leg's start
    ema.safetensors     (ema_decay > 0) the moving average of the weights
    state.json          step, epoch, batch within the epoch, workers, time_s: where --resume goes on
Determinism: the model is initialized from a torch.Generator seeded by cfg.seed (no global seeding), each
sample's crop and augmentation from (seed, epoch, shard, index), the batches of an epoch from (seed, epoch,
worker count); a resumed run skips the batches its epoch already did. With a time budget the learning rate
follows the clock, so such a run is not bitwise repeatable (its data order still is).
DDP: when torch.distributed is initialized (torchrun), each rank reads its own shards (perception/stream.py),
gradients are averaged, and only rank 0 writes; a budgeted run stops on rank 0's clock.
The run folder appears with the first step trained (a run refused or failing before it leaves nothing). SIGINT
(Ctrl-C) or SIGTERM stops the run after the step in progress with a checkpoint and raises TrainingInterrupted (a
KeyboardInterrupt) that says how to resume; a second Ctrl-C stops at once.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
import torch

from envisat_pose.config import InputError, flatten
from envisat_pose.io import atomic_write_text
from envisat_pose.perception.data import DataConfig, shard_paths
from envisat_pose.perception.losses import LossConfig, corner_losses
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.stream import close_batches, epoch_batches, loader_batches
from envisat_pose.perception.weights import load_state, load_tensors, read_weights, save_tensors, save_weights


@dataclass(frozen=True)
class TrainConfig:
    """steps: optimizer steps in all; batch_size: per rank; lr: AdamW peak rate (cosine decay after warmup_steps);
    seed: root seed of the weights' initialization and the data order; checkpoint_every: steps between
    checkpoints; line_jitter_px: noise on the segments' end points (the verifier sees detected, not true, corners);
    time_budget_s: the run's seconds (None: train by steps): the rate decays over them instead of over the steps
    and the run stops inside them with a checkpoint (steps then only caps it). A resumed run given another
    budget than its own trains that many seconds more.
    schedule: 'cosine' (to 5 % over the steps or the budget) or 'constant_cooldown' (the peak rate, then a
    1 - sqrt cooldown to zero over the last cooldown_frac of the steps or the budget; the weights and optimizer
    at the cooldown's start are kept as pre_cooldown.safetensors / pre_cooldown_optimizer.pt, the next leg's
    start: Hagele et al., NeurIPS 2024). ema_decay: when positive, an exponential moving average of the weights
    (and batch-norm statistics) kept beside them as ema.safetensors, to evaluate next to the last weights.
    Validated when built."""

    steps: int = 20000
    batch_size: int = 16
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    seed: int = 0
    checkpoint_every: int = 500
    line_jitter_px: float = 1.0
    time_budget_s: float | None = None
    schedule: Literal["cosine", "constant_cooldown"] = "cosine"
    cooldown_frac: float = 0.2
    ema_decay: float = 0.0
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
        check(self.time_budget_s is None or self.time_budget_s > 0, f"{p}time_budget_s", self.time_budget_s,
              "seconds > 0 (leave it out to train by steps)")
        check(self.schedule in ("cosine", "constant_cooldown"), f"{p}schedule", self.schedule,
              "'cosine' or 'constant_cooldown'")
        check(0 < self.cooldown_frac <= 1, f"{p}cooldown_frac", self.cooldown_frac, "a share of the run in (0, 1]")
        check(0 <= self.ema_decay < 1, f"{p}ema_decay", self.ema_decay, "a decay in [0, 1) (0: no average)")
        check(self.weight_decay >= 0, f"{p}weight_decay", self.weight_decay, "a decay >= 0")
        check(self.checkpoint_every >= 1, f"{p}checkpoint_every", self.checkpoint_every, "at least 1 step")
        check(self.line_jitter_px >= 0, f"{p}line_jitter_px", self.line_jitter_px, "pixels >= 0")
        check(self.model.input_px == self.data.input_px, f"{p}data.input_px", self.data.input_px,
              f"the model's input_px ({self.model.input_px})")
        check(self.data.stride == self.model.stride, f"{p}data.stride", self.data.stride, "the model's stride (4)")

    def __post_init__(self) -> None:
        self.validate()

    def to_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self)))


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


def cooldown_factor(frac: float, cooldown_frac: float) -> float:
    """The constant-then-cooldown factor: 1 until 1 - cooldown_frac of the run, then 1 - sqrt(x) over the
    cooldown's share x, 0 at the end (and after)."""
    x = (min(max(frac, 0.0), 1.0) - (1.0 - cooldown_frac)) / cooldown_frac
    return 1.0 if x <= 0 else float(1.0 - np.sqrt(min(x, 1.0)))


def run_fraction(cfg: TrainConfig, step: int, elapsed_s: float, budget_end_s: float | None) -> float:
    """How far through its decay the run is: the budget's seconds used, or the steps after the warm-up."""
    end_s = budget_end_s if budget_end_s is not None else cfg.time_budget_s
    if end_s is not None:
        return elapsed_s / end_s
    return (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)


def in_cooldown(cfg: TrainConfig, step: int, elapsed_s: float = 0.0, budget_end_s: float | None = None) -> bool:
    """A constant_cooldown run is past its constant phase at this step."""
    return cfg.schedule == "constant_cooldown" and \
        run_fraction(cfg, step, elapsed_s, budget_end_s) > 1.0 - cfg.cooldown_frac


def lr_at(cfg: TrainConfig, step: int, elapsed_s: float = 0.0, budget_end_s: float | None = None) -> float:
    """The learning rate of optimizer step `step`: a linear warm-up over warmup_steps, then the schedule's decay
    (cosine to 5 %, or constant then a cooldown to 0) over the steps, or, with a time budget, over the run's
    seconds up to budget_end_s (default the config's budget; the lower of the warm-up ramp and the decay at
    elapsed_s: a run stopped by its budget ends decayed even if its warm-up was not done)."""
    ramp = (step + 1) / cfg.warmup_steps if step < cfg.warmup_steps else 1.0
    by_time = (budget_end_s if budget_end_s is not None else cfg.time_budget_s) is not None
    frac = run_fraction(cfg, step, elapsed_s, budget_end_s)
    decay = cosine_factor(frac) if cfg.schedule == "cosine" else cooldown_factor(frac, cfg.cooldown_frac)
    if by_time:
        factor = min(ramp, decay)
    elif step < cfg.warmup_steps:
        factor = ramp
    else:
        factor = decay
    # a Python float: it goes into the optimizer's state, which torch.load(weights_only=True) must read back
    return float(cfg.lr * factor)


def _dist():
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist, dist.get_rank(), dist.get_world_size()
    return None, 0, 1


RESUMABLE_CHANGES = ("steps", "time_budget_s")  # a resumed run may go further or longer, nothing else


class TrainingInterrupted(KeyboardInterrupt):
    """A run stopped by SIGINT or SIGTERM after its checkpoint was written: step, run_dir and how to go on."""

    def __init__(self, step: int, run_dir: str, signal_name: str):
        self.step, self.run_dir, self.signal_name = step, run_dir, signal_name
        if step > 0:
            text = f"{signal_name} at step {step}: checkpoint written in {run_dir!r}"
        else:
            text = f"{signal_name} before the first step: nothing written"
        super().__init__(text)


def _data_name(records: list[dict]) -> str:
    def one(r):
        sha = (r.get("manifest_sha256") or "none")[:12]
        if r.get("images") is None:  # frames rendered online: its configs' hash
            return f"{r.get('name')} (configs {sha})"
        return f"{r.get('name')} ({r.get('images')} images, manifest {sha})"

    return ", ".join(one(r) for r in records)


def _check_resume(run_dir: str, cfg: TrainConfig, data: list[dict] | None) -> tuple[dict, dict]:
    """(state.json, the run's config.json) of a run to resume; InputError when it is not one, or when the config
    (other than steps and the budget) or the data (by manifest hash) differ: each difference spelled out."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.exists(path) or not os.path.exists(os.path.join(run_dir, "state.json")):
        raise InputError(f"resume: {run_dir!r} holds no trained run (no config.json and state.json)")
    with open(path, encoding="utf-8") as fh:
        saved = json.load(fh)
    old, new = flatten(saved["train"]), flatten(cfg.to_dict())
    changed = [f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in sorted(set(old) | set(new))
               if k not in RESUMABLE_CHANGES and old.get(k) != new.get(k)]
    if changed:
        raise InputError(f"resume: {run_dir!r} was trained with another config: {'; '.join(changed)} (only `steps` "
                         "and `time_budget_s` may change; start a new run with `init` = its checkpoint instead)")
    if data is not None and "data" in saved:
        def key(records):
            return [r.get("manifest_sha256") or r.get("name") for r in records]

        if key(saved["data"]) != key(data):
            raise InputError(f"resume: {run_dir!r} was trained on {_data_name(saved['data'])}, not on "
                             f"{_data_name(data)}: resume with the same data, or start a new run with "
                             "`init` = its checkpoint")
    with open(os.path.join(run_dir, "state.json"), encoding="utf-8") as fh:
        return json.load(fh), saved


SHUTDOWN_RESERVE_S = 1.0  # a budgeted run keeps this for the final log, checkpoint and the workers' shutdown
POSTFIX_EVERY = 10  # steps between the progress bar's loss readings (each one waits for the device)


def _autocast(dev: torch.device, bf16: bool):
    return torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16)


def make_optimizer(model: torch.nn.Module, cfg: TrainConfig, dev: torch.device) -> torch.optim.Optimizer:
    """AdamW over the model, its update as one fused kernel on CUDA and as multi-tensor (foreach) ops elsewhere:
    the same arithmetic as the per-parameter loop, in a few dozen ops instead of thousands."""
    fast = {"fused": True} if dev.type == "cuda" else {"foreach": True}
    return torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, **fast)


def _train_step(model: CornerNet, net: torch.nn.Module, opt, batch: dict, cfg: TrainConfig, step: int,
                dev: torch.device, bf16: bool) -> dict:
    """One optimizer step on a batch already on dev: the network (bf16 autocast when asked), the losses in
    float32, clipped gradients (multi-tensor norm). Returns the loss terms (tensors on dev: nothing here waits
    for the device)."""
    image = batch["image"]
    if dev.type == "cuda":
        image = image.contiguous(memory_format=torch.channels_last)
    with _autocast(dev, bf16):
        out = net(image)
        segs = batch["segments_px"]
        if cfg.line_jitter_px > 0:
            gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)  # resumable: per step
            segs = segs + cfg.line_jitter_px * torch.randn(segs.shape, generator=gen).to(dev, non_blocking=True)
        logits = model.line_logits(out["features"], segs)
    out = {k: v.float() for k, v in out.items()}
    terms = corner_losses(out, batch, logits.float(), cfg.loss, cfg.model.stride)
    opt.zero_grad(set_to_none=True)
    terms["loss"].backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0, foreach=True)
    opt.step()
    return {k: v.detach() for k, v in terms.items()}


def make_ema(model: CornerNet, cfg: TrainConfig):
    """The moving average of the weights and buffers (torch's AveragedModel), or None when ema_decay is 0."""
    if cfg.ema_decay <= 0:
        return None
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(cfg.ema_decay), use_buffers=True)


def _shared_clock(dist, dev: torch.device, elapsed_s: float, reserve_s: float) -> tuple[float, float]:
    """Rank 0's clock for every rank (a budgeted DDP run must stop at the same step on all ranks)."""
    if dist is None:
        return elapsed_s, reserve_s
    t = torch.tensor([elapsed_s, reserve_s], dtype=torch.float64, device=dev)
    dist.broadcast(t, src=0)
    return float(t[0]), float(t[1])


@contextlib.contextmanager
def _stop_on_signals(flag: dict):
    """While training: SIGINT and SIGTERM set flag['signal'] (the loop stops after its step, with a checkpoint);
    a second SIGINT raises KeyboardInterrupt at once. Only in the main thread (signals are delivered there)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, _frame):
        if flag.get("signal") and signum == signal.SIGINT:
            raise KeyboardInterrupt
        flag["signal"] = signal.Signals(signum).name

    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _budget_end_s(cfg: TrainConfig, saved: dict | None, state: dict) -> float | None:
    """The run's clock reading at which a budgeted call stops: the config's budget for a new run, or for a
    resumed run given its own budget again (what is left of it); time_s + the new budget for a resumed run given
    another (that many seconds more). None: by steps."""
    if cfg.time_budget_s is None:
        return None
    if saved is None:
        return cfg.time_budget_s
    if state.get("budget_end_s") is not None and saved["train"].get("time_budget_s") == cfg.time_budget_s:
        return float(state["budget_end_s"])
    return float(state["time_s"]) + cfg.time_budget_s


def _progress(cfg: TrainConfig, state: dict, budget_end_s: float | None, time0: float, enabled: bool):
    """A step bar, or under a budget a bar of the budget's seconds (elapsed / budget)."""
    from tqdm import tqdm

    if budget_end_s is None:
        return tqdm(total=cfg.steps, initial=state["step"], disable=not enabled, desc="train", unit="step")
    return tqdm(total=round(budget_end_s - time0, 1), disable=not enabled, desc="train", unit="s",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of the budget{postfix}")


def _advance_budget_bar(bar, seconds: float) -> None:
    """Move a budget's bar to `seconds` into it, never past its end: tqdm drops the total of a bar past it, and
    the bar's percentage then fails to format (a last step that ends after the budget's end)."""
    bar.update(max(0.0, min(round(seconds, 1), bar.total) - bar.n))


def train(cfg: TrainConfig, data_dir: str | list[str], run_dir: str, resume: bool = False, device: str = "cpu",
          progress: bool = True, provenance: dict | None = None, init_weights: str | None = None,
          workers: int | None = None, bf16: bool = False, clock=time.perf_counter,
          paths: list[str] | None = None, online=None) -> dict:
    """Train (or go on training, with resume) into run_dir. Returns the last metrics line.

    data_dir: one dataset folder or several (their shards are read together); paths: the shard files to read
    when the caller checked them already (else every shard of data_dir). init_weights: a safetensors file of
    the same architecture to start from instead of the seeded initialization (fine-tuning; a new run only).
    workers: DataLoader worker processes feeding the batches (perception/stream.py; 0: in-process); None: the
    run's own count on resume, else 0. The batches depend on the count, so a resumed run keeps it. The workers
    start from a fork server without the calling script (perception/stream.py), so a plain script needs no
    `if __name__ == "__main__":` guard.
    bf16: the network's forward under bfloat16 autocast (CUDA or CPU); losses, weights and optimizer in float32.
    With a time budget the run stops before the next step would leave too little of it for the final checkpoint
    (the budget counts from this call's start, plus what a resumed run had already used; see _budget_end_s); a
    budget too short for one step is an InputError. A resumed run already at its steps or budget trains nothing
    and returns an end line with stopped_by 'nothing_to_do'.
    clock: the seconds every time figure and the budget are read from (a test gives its own).
    online: instead of shards, a function start_state -> iterator of (batch on the device, state) (frames
    rendered as training goes: pipelines/online.py); each step's state is kept in state.json under 'online' and
    handed back on resume; no epochs, data_dir and paths unused.
    Raises TrainingInterrupted after the checkpoint when SIGINT or SIGTERM stopped it.
    """
    dist, rank, world = _dist()
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("device 'cuda': no CUDA device is available")
    if workers is not None and workers < 0:
        raise InputError(f"workers = {workers}: expected 0 (in-process) or more worker processes")
    t_start = clock()
    dirs = [data_dir] if isinstance(data_dir, str) else list(data_dir)
    if paths is None and online is None:
        paths = [p for d in dirs for p in shard_paths(d)]
    state = {"step": 0, "epoch": 0, "batch": 0, "workers": 0 if workers is None else workers, "time_s": 0.0}
    saved = None
    if resume:
        saved_state, saved = _check_resume(run_dir, cfg, (provenance or {}).get("data"))
        ran_with = int(saved_state.get("workers", 0))
        if workers is not None and workers != ran_with:
            raise InputError(f"workers = {workers}: {run_dir!r} was trained with {ran_with} (its batches depend "
                             f"on the count); resume it with --workers {ran_with}")
        state = {**state, **saved_state, "workers": ran_with}
    elif os.path.exists(os.path.join(run_dir, "state.json")):
        raise InputError(f"run_dir {run_dir!r} already holds a run: resume it, or give another folder")
    time0 = float(state["time_s"])
    budget_end_s = _budget_end_s(cfg, saved, state)
    state["budget_end_s"] = budget_end_s
    if resume and (state["step"] >= cfg.steps or (budget_end_s is not None and time0 >= budget_end_s)):
        why = "budget_spent" if state["step"] < cfg.steps else "steps_reached"
        return {"kind": "end", "step": state["step"], "epoch": state["epoch"], "steps_run": 0,
                "stopped_by": "nothing_to_do", "why": why, "time_s": time0, "workers": state["workers"]}
    model = init_model(cfg).to(dev)
    if init_weights is not None and not resume:
        tensors, _ = read_weights(init_weights)
        load_state(model, tensors, init_weights)
    if resume:
        tensors, _ = read_weights(os.path.join(run_dir, "checkpoint.safetensors"))
        load_state(model, tensors, os.path.join(run_dir, "checkpoint.safetensors"))
    if dev.type == "cuda":
        model = model.to(memory_format=torch.channels_last)
    opt = make_optimizer(model, cfg, dev)
    if resume:
        opt.load_state_dict(load_tensors(os.path.join(run_dir, "optimizer.pt")))
    ema = make_ema(model, cfg)
    ema_path = os.path.join(run_dir, "ema.safetensors")
    if ema is not None and resume and os.path.exists(ema_path):
        load_state(ema.module, read_weights(ema_path)[0], ema_path)
        ema.n_averaged.fill_(max(1, int(state["step"])))
    net = model
    if dist is not None:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)
    model.train()
    started = {"run": resume}  # the run folder exists (a resumed run's does)

    def elapsed() -> float:
        return time0 + clock() - t_start

    def start_run() -> None:
        """The run folder and its config.json, once the first step is trained (nothing half-made before); a
        resumed run's record takes its new steps or budget and keeps each resuming command under 'resumes'."""
        if started["run"]:
            if saved is not None and not started.get("recorded") and rank == 0:
                started["recorded"] = True
                resumes = saved.get("resumes", []) + [{"command": (provenance or {}).get("command", ""),
                                                       "git": (provenance or {}).get("git"), "step": state["step"]}]
                atomic_write_text(os.path.join(run_dir, "config.json"), json.dumps(
                    {**saved, "train": cfg.to_dict(), "resumes": resumes}, indent=1, sort_keys=True) + "\n")
            return
        started["run"] = True
        if rank == 0:
            os.makedirs(run_dir, exist_ok=True)
            atomic_write_text(os.path.join(run_dir, "config.json"), json.dumps(
                {"train": cfg.to_dict(), **(provenance or {})}, indent=1, sort_keys=True) + "\n")

    bar = _progress(cfg, state, budget_end_s, time0, progress and rank == 0)
    sums: dict[str, torch.Tensor] = {}
    count = 0
    terms_mean: dict[str, float] = {}
    lr = lr_at(cfg, state["step"], time0, budget_end_s)
    run = {"steps": 0, "first_batch_s": None, "data_wait_s": 0.0}  # this call's own figures
    iter_s: list[float] = []  # the last steps' wall times, data wait included
    checkpoint_s = 0.5  # until one is measured

    def checkpoint() -> None:
        if rank != 0 or not started["run"]:
            return
        state["time_s"] = round(elapsed(), 3)
        save_weights(os.path.join(run_dir, "checkpoint.safetensors"), model, {"step": str(state["step"])})
        save_tensors(os.path.join(run_dir, "optimizer.pt"), opt.state_dict())
        if ema is not None:
            save_weights(ema_path, ema.module, {"step": str(state["step"]), "ema_decay": str(cfg.ema_decay)})
        atomic_write_text(os.path.join(run_dir, "state.json"), json.dumps(state, sort_keys=True) + "\n")

    def save_pre_cooldown() -> None:
        """The weights and optimizer before the cooldown's first step: where the next leg starts."""
        state["pre_cooldown_step"] = state["step"]
        if rank == 0:
            save_weights(os.path.join(run_dir, "pre_cooldown.safetensors"), model,
                         {"step": str(state["step"]), "pre_cooldown": "true"})
            save_tensors(os.path.join(run_dir, "pre_cooldown_optimizer.pt"), opt.state_dict())

    def log(kind: str, extra: dict | None = None) -> dict:
        """A metrics line: the loss terms averaged since the last line (an end line right after an epoch line
        repeats that line's terms). The one place the terms are read back from the device."""
        nonlocal sums, count, terms_mean
        if count:
            terms_mean = {k: float(v) / count for k, v in sums.items()}
        line = {"kind": kind, "epoch": state["epoch"], "step": state["step"], "lr": lr, "time_s": round(elapsed(), 3),
                **terms_mean, **(extra or {})}
        if rank == 0 and started["run"]:
            with open(os.path.join(run_dir, "metrics.jsonl"), "a", encoding="utf-8") as fh:
                fh.write(json.dumps(line, sort_keys=True) + "\n")
        sums, count = {}, 0
        return line

    def batches_of(epoch: int):
        return epoch_batches(paths, cfg.data, cfg.seed, epoch, cfg.batch_size, state["workers"], rank, world,
                             pin_memory=dev.type == "cuda")

    def offline_batches():
        """(batch, where the run stands after training it) from the shards, epoch after epoch; an epoch's end
        logged. The next epoch's workers start early (no stall at the boundary)."""
        current = upcoming = None
        try:
            while True:
                skip, n = state["batch"], 0  # a resumed epoch: its first batches were trained on before
                current = upcoming if upcoming is not None else batches_of(state["epoch"])
                upcoming = batches_of(state["epoch"] + 1) if state["workers"] > 0 else None
                for i, cpu_batch in enumerate(loader_batches(current, flag)):
                    if i >= skip:
                        n += 1
                        yield cpu_batch, {"batch": i + 1}
                if flag.get("signal"):
                    return
                if n == 0 and skip == 0:
                    raise InputError(f"data {data_dir!r}: fewer samples than one batch of {cfg.batch_size} per "
                                     f"worker ({state['workers']} workers, {len(paths)} shards, {world} ranks): "
                                     "use fewer workers or a smaller batch")
                close_batches(current)
                log("epoch")
                state["epoch"] += 1
                state["batch"] = 0
        finally:  # the workers of both epochs stop here, on the run's end or an error alike
            for batches in (current, upcoming):
                close_batches(batches)

    def online_batches():
        """(batch on the device, the source's state) from frames rendered as training goes (online(start))."""
        for batch, source_state in online(state.get("online")):
            yield batch, {"online": source_state}

    flag: dict = {}
    stop = None  # why the loop ended early: 'time_budget' or the signal's name
    with _stop_on_signals(flag):
        source = online_batches() if online is not None else offline_batches()
        try:
            t_ask = clock()
            for cpu_batch, position in source:
                if state["step"] >= cfg.steps or flag.get("signal"):
                    break
                t_got = clock()
                run["data_wait_s"] += t_got - t_ask
                if run["first_batch_s"] is None:
                    run["first_batch_s"] = t_got - t_start
                now_s = elapsed()
                if budget_end_s is not None:
                    reserve = 1.5 * max(iter_s[-10:], default=0.0) + checkpoint_s + SHUTDOWN_RESERVE_S
                    now_s, reserve = _shared_clock(dist, dev, now_s, reserve)
                    if now_s + reserve >= budget_end_s:
                        if run["steps"] == 0:
                            raise InputError(
                                f"time_budget_s = {cfg.time_budget_s:g}: too short for one step (the first batch "
                                f"came {now_s - time0:.1f} s into it; a step, the checkpoint and the shutdown need "
                                f"~{reserve:.1f} s more): give a longer budget")
                        stop = "time_budget"
                        if cfg.schedule == "constant_cooldown" and "pre_cooldown_step" not in state:
                            save_pre_cooldown()  # stopped before its cooldown: these weights are the next start
                        break
                if "pre_cooldown_step" not in state and in_cooldown(cfg, state["step"], now_s, budget_end_s):
                    start_run()
                    save_pre_cooldown()
                lr = lr_at(cfg, state["step"], now_s, budget_end_s)
                for g in opt.param_groups:
                    g["lr"] = lr
                terms = _train_step(model, net, opt, to_device(cpu_batch, dev), cfg, state["step"], dev, bf16)
                if ema is not None:
                    ema.update_parameters(model)
                start_run()
                state["step"] += 1
                state.update(position)
                run["steps"] += 1
                for k, v in terms.items():
                    sums[k] = sums[k] + v if k in sums else v
                count += 1
                if budget_end_s is None:
                    bar.update(1)
                else:
                    _advance_budget_bar(bar, elapsed() - time0)
                if state["step"] % POSTFIX_EVERY == 0 or run["steps"] == 1:
                    bar.set_postfix(step=state["step"], loss=f"{float(terms['loss']):.3f}")
                if state["step"] % cfg.checkpoint_every == 0:
                    t_ck = clock()
                    checkpoint()
                    checkpoint_s = clock() - t_ck
                # a step's wall time, its wait for data included, except the run's first (the loaders' start-up,
                # seconds that no later step waits again, would hold back a budget's last steps)
                iter_s.append(clock() - (t_got if run["steps"] == 1 else t_ask))
                t_ask = clock()
            if flag.get("signal") and stop is None:
                stop = flag["signal"]
        finally:
            source.close()  # the loader's or the renderers' workers shut down, on an error too
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
             "stopped_by": "steps" if stop is None else ("time_budget" if stop == "time_budget" else "signal")}
    end = log("end", {**ddp, **speed})
    if stop not in (None, "time_budget"):
        raise TrainingInterrupted(state["step"] if started["run"] else 0, run_dir, stop)
    return end


def _ranks_identical(dist, model: torch.nn.Module, world: int) -> bool:
    """Every rank holds the same parameters and buffers, bit for bit (gathered and compared on all ranks)."""
    flat = torch.cat([t.detach().reshape(-1).double().cpu() for t in model.state_dict().values()])
    gathered = [torch.empty_like(flat) for _ in range(world)]
    dist.all_gather(gathered, flat)
    return all(torch.equal(gathered[0], g) for g in gathered[1:])
