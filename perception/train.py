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
Structure: `train` builds a `Trainer` (the model, the optimizer, the state.json dict and the step); the budget,
the moving average, the pre-cooldown weights, the run folder, checkpoints, metrics, the progress bar, timing,
DDP agreement and signals are hooks of perception/trainer_hooks.py, called at named points in a fixed order.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
import torch

from envisat_pose.config import InputError, check, flatten
from envisat_pose.perception.data import DataConfig, shard_paths
from envisat_pose.perception.losses import LossConfig, corner_losses
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.stream import close_batches, epoch_batches, loader_batches
from envisat_pose.perception.trainer_hooks import (
    Budget,
    Checkpoints,
    DdpAgreement,
    Hook,
    Metrics,
    MovingAverage,
    PreCooldown,
    Progress,
    RunFolder,
    StopOnSignals,
    Timing,
    progress_bar,
)
from envisat_pose.perception.weights import load_state, load_tensors, read_weights


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




@dataclass(frozen=True)
class TrainData:
    """Where a run's batches come from. data_dir: one dataset folder or several (their shards are read
    together); paths: the shard files to read when the caller checked them already (None: every shard of
    data_dir); online: instead of shards, a function start_state -> iterator of (batch on the device, state)
    (frames rendered as training goes: pipelines/detector/online.py), each step's state kept in state.json under 'online'
    and handed back on resume (no epochs; data_dir and paths unused)."""

    data_dir: str | list[str] = ()
    paths: list[str] | None = None
    online: Callable | None = None


@dataclass(frozen=True)
class TrainOptions:
    """How one train() call runs, apart from what it learns (TrainConfig): see train() for each field."""

    resume: bool = False
    device: str = "cpu"
    progress: bool = True
    provenance: dict | None = None
    init_weights: str | None = None
    workers: int | None = None
    bf16: bool = False
    clock: Callable[[], float] = time.perf_counter


class Trainer:
    """One train() call: the model, its optimizer and the run's state (the dict state.json holds: step, epoch,
    batch, workers, time_s, budget_end_s, pre_cooldown_step, online), trained step by step; every other concern
    is a hook (perception/trainer_hooks.py) called at named points. Trainer(cfg, data, run_dir, opts).run()."""

    def __init__(self, cfg: TrainConfig, data: TrainData, run_dir: str, opts: TrainOptions):
        self.cfg, self.data, self.run_dir, self.opts = cfg, data, run_dir, opts
        self.dist, self.rank, self.world = _dist()
        self.dev = torch.device(opts.device)
        self.clock = opts.clock
        self.signals = StopOnSignals()
        self.steps_run = 0  # this call's own steps
        self.hooks: list[Hook] = []

    def run(self) -> dict:
        """Train; the last metrics line (see train())."""
        self._check_call()
        self.t_start = self.clock()
        self.paths = self._shard_paths()
        self.state, self.saved = self._start_state()
        self.time0 = float(self.state["time_s"])
        self.budget_end_s = _budget_end_s(self.cfg, self.saved, self.state)
        self.state["budget_end_s"] = self.budget_end_s
        if self.saved is not None and self._nothing_to_do():
            why = "budget_spent" if self.state["step"] < self.cfg.steps else "steps_reached"
            return {"kind": "end", "step": self.state["step"], "epoch": self.state["epoch"], "steps_run": 0,
                    "stopped_by": "nothing_to_do", "why": why, "time_s": self.time0, "workers": self.state["workers"]}
        self._build_model()
        self._make_hooks()
        self.lr = lr_at(self.cfg, self.state["step"], self.time0, self.budget_end_s)
        return self._finish(self._train())

    def elapsed(self) -> float:
        """The run's clock, seconds: what it had used before this call (a resumed run's time_s) plus this call's."""
        return self.time0 + self.clock() - self.t_start

    def _now(self) -> float:
        """The run clock for the next step (seconds): under a budget and DDP rank 0's (Budget.share_clock)."""
        now_s = self.elapsed()
        return now_s if self.budget is None else self.budget.share_clock(now_s)

    def in_cooldown(self, now_s: float) -> bool:
        """The next step, at run-clock now_s, is in a constant_cooldown run's cooldown."""
        return in_cooldown(self.cfg, self.state["step"], now_s, self.budget_end_s)

    def _check_call(self) -> None:
        if self.dev.type == "cuda" and not torch.cuda.is_available():
            raise InputError("device 'cuda': no CUDA device is available")
        workers = self.opts.workers
        if workers is not None and workers < 0:
            raise InputError(f"workers = {workers}: expected 0 (in-process) or more worker processes")

    def _shard_paths(self) -> list[str] | None:
        if self.data.paths is not None or self.data.online is not None:
            return self.data.paths
        dirs = [self.data.data_dir] if isinstance(self.data.data_dir, str) else list(self.data.data_dir)
        return [p for d in dirs for p in shard_paths(d)]

    def _start_state(self) -> tuple[dict, dict | None]:
        """The state to start from and, on resume, the run's config.json (None: a new run). InputError when a new
        run's folder holds a run, or when resume's checks fail (perception/train.py _check_resume, the workers)."""
        workers, run_dir = self.opts.workers, self.run_dir
        state = {"step": 0, "epoch": 0, "batch": 0, "workers": 0 if workers is None else workers, "time_s": 0.0}
        if not self.opts.resume:
            if os.path.exists(os.path.join(run_dir, "state.json")):
                raise InputError(f"run_dir {run_dir!r} already holds a run: resume it, or give another folder")
            return state, None
        saved_state, saved = _check_resume(run_dir, self.cfg, (self.opts.provenance or {}).get("data"))
        ran_with = int(saved_state.get("workers", 0))
        if workers is not None and workers != ran_with:
            raise InputError(f"workers = {workers}: {run_dir!r} was trained with {ran_with} (its batches depend "
                             f"on the count); resume it with --workers {ran_with}")
        return {**state, **saved_state, "workers": ran_with}, saved

    def _nothing_to_do(self) -> bool:
        """A resumed run already at its steps or at its budget's end."""
        spent = self.budget_end_s is not None and self.time0 >= self.budget_end_s
        return self.state["step"] >= self.cfg.steps or spent

    def _build_model(self) -> None:
        """The model (seeded, from init_weights, or a resumed run's checkpoint), its optimizer (resumed too), the
        moving average, and `net`: the model itself or its DDP wrapper."""
        cfg, opts, dev = self.cfg, self.opts, self.dev
        self.model = init_model(cfg).to(dev)
        start = os.path.join(self.run_dir, "checkpoint.safetensors") if opts.resume else opts.init_weights
        if start is not None:
            load_state(self.model, read_weights(start)[0], start)
        if dev.type == "cuda":
            self.model = self.model.to(memory_format=torch.channels_last)
        self.opt = make_optimizer(self.model, cfg, dev)
        if opts.resume:
            self.opt.load_state_dict(load_tensors(os.path.join(self.run_dir, "optimizer.pt")))
        ema = make_ema(self.model, cfg)
        self.average = None if ema is None else MovingAverage(ema, cfg.ema_decay,
                                                              os.path.join(self.run_dir, "ema.safetensors"))
        if self.average is not None and opts.resume:
            self.average.resume(self.state["step"])
        self.net = self.model
        if self.dist is not None:
            self.net = torch.nn.parallel.DistributedDataParallel(
                self.model, device_ids=[dev.index] if dev.type == "cuda" else None)
        self.model.train()

    def _make_hooks(self) -> None:
        """The hooks, in the order they are called at each point (perception/trainer_hooks.py)."""
        cfg = self.cfg
        self.folder = RunFolder(self.saved, self.opts.provenance, self.state["step"])
        self.timing, self.metrics = Timing(), Metrics(self.folder)
        self.checkpoints = Checkpoints(self.folder, cfg.checkpoint_every)
        bar = progress_bar(cfg.steps, self.state, self.budget_end_s, self.time0, self.opts.progress and self.rank == 0)
        self.ddp = None if self.dist is None else DdpAgreement(self.dist, self.world)
        self.budget = None if self.budget_end_s is None else Budget(self.budget_end_s, self.timing, self.checkpoints)
        hooks = [
            self.budget, PreCooldown(self.folder) if cfg.schedule == "constant_cooldown" else None,
            self.average, self.folder, self.metrics, Progress(bar, self.budget_end_s is not None), self.ddp,
            self.checkpoints, self.timing,
        ]
        self.hooks = [h for h in hooks if h is not None]
        for hook in self.hooks:
            hook.trainer = self

    def _train(self) -> str | None:
        """The loop under the signal handlers, its batch source closed on every way out, then the hooks'
        after_train (the last checkpoint among them). Why it stopped early: 'time_budget', a signal's name, None."""
        with self.signals:
            source = self._online_batches() if self.data.online is not None else self._shard_batches()
            try:
                stop = self._loop(source)
            finally:
                source.close()  # the loader's or the renderers' workers shut down, on an error too
            for hook in self.hooks:
                hook.after_train()
        return stop

    def _loop(self, source) -> str | None:
        """Steps on the source's batches until the steps are done, a hook stops the run before a step or a
        signal came (the step in progress finishes)."""
        self.timing.ask()
        for cpu_batch, position in source:
            if self.state["step"] >= self.cfg.steps or self.signals.caught:
                break
            self.timing.got()
            now_s = self._now()
            for hook in self.hooks:
                reason = hook.before_step(now_s)
                if reason is not None:
                    for h in self.hooks:
                        h.on_stop(reason)
                    return reason
            terms = self._step(cpu_batch, now_s)
            self.state["step"] += 1
            self.state.update(position)
            self.steps_run += 1
            for hook in self.hooks:
                hook.after_step(terms)
        return self.signals.caught

    def _step(self, cpu_batch: dict, now_s: float) -> dict:
        """One optimizer step at the schedule's rate for this step and run-clock now_s; the loss terms."""
        self.lr = lr_at(self.cfg, self.state["step"], now_s, self.budget_end_s)
        for g in self.opt.param_groups:
            g["lr"] = self.lr
        return _train_step(self.model, self.net, self.opt, to_device(cpu_batch, self.dev), self.cfg,
                           self.state["step"], self.dev, self.opts.bf16)

    def _epoch_batches(self, epoch: int):
        return epoch_batches(self.paths, self.cfg.data, self.cfg.seed, epoch, self.cfg.batch_size,
                             self.state["workers"], self.rank, self.world, pin_memory=self.dev.type == "cuda")

    def _shard_batches(self):
        """(batch, where the run stands after training it) from the shards, epoch after epoch; an epoch's end
        logged. The next epoch's workers start early (no stall at the boundary)."""
        state, current, upcoming = self.state, None, None
        try:
            while True:
                skip, n = state["batch"], 0  # a resumed epoch: its first batches were trained on before
                current = upcoming if upcoming is not None else self._epoch_batches(state["epoch"])
                upcoming = self._epoch_batches(state["epoch"] + 1) if state["workers"] > 0 else None
                for i, cpu_batch in enumerate(loader_batches(current, self.signals.flag)):
                    if i >= skip:
                        n += 1
                        yield cpu_batch, {"batch": i + 1}
                if self.signals.caught:
                    return
                if n == 0 and skip == 0:
                    raise InputError(f"data {self.data.data_dir!r}: fewer samples than one batch of "
                                     f"{self.cfg.batch_size} per worker ({state['workers']} workers, "
                                     f"{len(self.paths)} shards, {self.world} ranks): use fewer workers or a "
                                     "smaller batch")
                close_batches(current)
                self.metrics.log("epoch")
                state["epoch"] += 1
                state["batch"] = 0
        finally:  # the workers of both epochs stop here, on the run's end or an error alike
            for batches in (current, upcoming):
                close_batches(batches)

    def _online_batches(self):
        """(batch on the device, the source's state) from frames rendered as training goes."""
        for batch, source_state in self.data.online(self.state.get("online")):
            yield batch, {"online": source_state}

    def _finish(self, stop: str | None) -> dict:
        """The end line (the last terms, this call's speed, why it stopped, under DDP the ranks' agreement);
        TrainingInterrupted after it when a signal stopped the run."""
        speed = {**self.timing.figures(self.cfg.batch_size, self.world), "workers": self.state["workers"],
                 "bf16": self.opts.bf16,
                 "stopped_by": "steps" if stop is None else ("time_budget" if stop == "time_budget" else "signal")}
        end = self.metrics.log("end", {**(self.ddp.figures if self.ddp else {}), **speed})
        if stop not in (None, "time_budget"):
            raise TrainingInterrupted(self.state["step"] if self.folder.started else 0, self.run_dir, stop)
        return end


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
    rendered as training goes: pipelines/detector/online.py); each step's state is kept in state.json under 'online' and
    handed back on resume; no epochs, data_dir and paths unused.
    Raises TrainingInterrupted after the checkpoint when SIGINT or SIGTERM stopped it.
    """
    opts = TrainOptions(resume=resume, device=device, progress=progress, provenance=provenance,
                        init_weights=init_weights, workers=workers, bf16=bf16, clock=clock)
    return Trainer(cfg, TrainData(data_dir, paths, online), run_dir, opts).run()
