"""The training loop: batches from worker processes (perception/stream.py), the model, the losses, checkpoints in
a run directory.

Run directory (one per run, as L-CNN's):
    config.json         the frozen TrainConfig, the command and the git hash (train.config.toml: the TrainConfig alone)
    metrics.jsonl       one JSON line per epoch (a pass over the data) and one at the end: step, loss terms, time;
                        the end line also this call's speed (samples_s, first_batch_s, data_wait_s, workers)
    checkpoint.safetensors   the model (perception/weights.py: safetensors, the ModelConfig in its metadata)
    optimizer.pt        AdamW state, tensors only (torch.load(weights_only=True) reads it)
    pre_cooldown.safetensors, pre_cooldown_optimizer.pt   (schedule 'constant_cooldown') the same at the
                        cooldown's first step (or at a budget's stop that came before it): the next leg's start
    ema.safetensors     (ema_decay > 0) the moving average of the weights
    state.json          step, epoch, batch within the epoch, workers, time_s: where --resume goes on
Determinism: the model is initialized from a torch.Generator seeded by cfg.seed (no global seeding), each sample's
crop and augmentation from (seed, epoch, shard, index), an epoch's batches from (seed, epoch, worker count); a
resumed run skips its epoch's batches done. A budgeted run's rate follows the clock: not bitwise repeatable.
DDP: when torch.distributed is initialized (torchrun), each rank reads its own shards (perception/stream.py),
gradients are averaged, and only rank 0 writes; a budgeted run stops on rank 0's clock.
The run folder appears with the first step trained (a run refused or failing before it leaves nothing). SIGINT
(Ctrl-C) or SIGTERM stops the run after the step in progress with a checkpoint and raises TrainingInterrupted (a
KeyboardInterrupt) that says how to resume; a second Ctrl-C stops at once.
Structure: a `Trainer` owns the model, the optimizer, the state.json dict and the step (the schedule's rate,
_train_step), and calls the hooks registered on it (perception/trainer_hooks.py) at named points in the order
they declare. `train` registers the run folder's (the budget, the pre-cooldown weights, the moving average, the
run folder, the progress bar, DDP agreement, checkpoints, signals, metrics) over the batches and the start that
perception/train_run.py gives it; adapt's fine-tune registers its own; no training loop steps outside a Trainer.
What it trains is its Task (the model's seeded build, the loss terms of a batch, the online batches): ENVISAT's
corner network (CORNERS) by default, another target's keypoint network (perception/keypoint_train.py).
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

from envisat_pose.config import Config, InputError, check
from envisat_pose.perception.batch_augment import training_batch
from envisat_pose.perception.data import DataConfig, shard_paths
from envisat_pose.perception.losses import LossConfig, corner_losses
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.train_bounds import check_train_config
from envisat_pose.perception.train_run import (
    TrainingInterrupted,
    budget_end,
    end_line,
    nothing_to_do,
    rendered_batches,
    shard_batches,
    start_state,
)
from envisat_pose.perception.trainer_hooks import (
    Budget,
    Checkpoints,
    DdpAgreement,
    Hook,
    LoopTiming,
    Metrics,
    MovingAverage,
    PreCooldown,
    Progress,
    RunFolder,
    StopOnSignals,
    hook_order,
    progress_bar,
)
from envisat_pose.perception.weights import load_backbone, load_state, load_tensors, read_weights


@dataclass(frozen=True)
class TrainConfig(Config):
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
        check_train_config(self, p)  # train_bounds.py: each bound beside its reason
        check(self.model.input_px == self.data.input_px, f"{p}data.input_px", self.data.input_px,
              f"the model's input_px ({self.model.input_px})")
        check(self.data.stride == self.model.stride, f"{p}data.stride", self.data.stride, "the model's stride (4)")

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


def _autocast(dev: torch.device, bf16: bool):
    return torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16)


def make_optimizer(model: torch.nn.Module, cfg: TrainConfig, dev: torch.device) -> torch.optim.Optimizer:
    """AdamW over the model, its update as one fused kernel on CUDA and as multi-tensor (foreach) ops elsewhere:
    the same arithmetic as the per-parameter loop, in a few dozen ops instead of thousands."""
    fast = {"fused": True} if dev.type == "cuda" else {"foreach": True}
    return torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, **fast)


def _corner_terms(model: CornerNet, net: torch.nn.Module, batch: dict, cfg: TrainConfig, step: int,
                  dev: torch.device, bf16: bool) -> dict:
    """The corner network's loss terms on a batch already on dev: the network (bf16 autocast when asked), the line
    verifier on jittered segments, the losses in float32 (perception/losses.corner_losses)."""
    image = batch["image"]
    if dev.type == "cuda":
        image = image.contiguous(memory_format=torch.channels_last)
    with _autocast(dev, bf16):
        out = net(image)
        segs = batch["segments_px"]
        if cfg.line_jitter_px > 0:
            gen = torch.Generator().manual_seed((cfg.seed * 1_000_003 + step) % 2**63)  # resumable: per step
            segs = segs + cfg.line_jitter_px * torch.randn(segs.shape, generator=gen).to(dev, non_blocking=True)
        logits = model.line_logits(out["features"], segs)
    out = {k: v.float() for k, v in out.items()}
    return corner_losses(out, batch, logits.float(), cfg.loss, cfg.model.stride)


@dataclass(frozen=True)
class Task:
    """What a Trainer trains. build(cfg) -> the model, its weights drawn from a generator seeded by cfg.seed;
    terms(model, net, batch, cfg, step, dev, bf16) -> the loss terms of a batch on dev ('loss' their weighted total;
    the forward under bf16 autocast when asked, the losses in float32); online_batch: the batch of frames rendered
    as training goes (batch_augment.training_batch's arguments). CORNERS: ENVISAT's corner network; another
    target's keypoint network: perception/keypoint_train.keypoint_task."""

    build: Callable
    terms: Callable
    online_batch: Callable


CORNERS = Task(init_model, _corner_terms, training_batch)


def _train_step(model: torch.nn.Module, net: torch.nn.Module, opt, batch: dict, cfg: TrainConfig, step: int,
                dev: torch.device, bf16: bool, terms_of: Callable = _corner_terms) -> dict:
    """One optimizer step on a batch already on dev: the loss terms (terms_of, a Task's; the corner network's by
    default), clipped gradients (multi-tensor norm). Returns the loss terms (tensors on dev: nothing here waits
    for the device)."""
    terms = terms_of(model, net, batch, cfg, step, dev, bf16)
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


class Trainer:
    """Trains `model` with `opt` on batches step by step (the schedule's rate, _train_step), calling its hooks
    (perception/trainer_hooks.py) at named points in their declared order. Every training loop of the project
    runs here: `train()` registers the run folder's hooks, adapt's fine-tune its own, a benchmark none.
    Trainer(cfg, model, opt, dev=..., hooks=[...], task=...).run(batches); task: what each step computes (Task;
    CORNERS by default).

    What the hooks share lives here, not in one another: cfg (TrainConfig), model, net (the model or its DDP
    wrapper), opt, dev, bf16, dist, rank, world, run_dir (where hooks write; None: nowhere), clock, t_start (its
    reading at the call's start), time0 (the run clock then: a resumed run's seconds), elapsed(), state (the
    dict state.json holds: step, epoch, batch, workers, time_s, budget_end_s, pre_cooldown_step, online),
    budget_end_s, lr (the last step's rate), now_s (the run clock of the step about to run; Budget makes it
    rank 0's), steps_run (this call's), timing (trainer_hooks.LoopTiming), checkpoint_s (the last checkpoint's
    seconds: Checkpoints measures them, Budget keeps them), folder_started (RunFolder made the run folder),
    stop_flag ({'signal': name} once a signal asked to stop after the step: StopOnSignals), stop (why the loop
    ended early: a hook's reason, a signal's name, None), error (the exception leaving run(), or None) and
    end_line (the end line: hooks add their figures at after_train, Metrics completes and writes it)."""

    def __init__(self, cfg: TrainConfig, model: torch.nn.Module, opt: torch.optim.Optimizer, *, dev: torch.device,
                 net: torch.nn.Module | None = None, bf16: bool = False, clock: Callable[[], float] = time.perf_counter,
                 t_start: float | None = None, state: dict | None = None, budget_end_s: float | None = None,
                 run_dir: str | None = None, hooks: tuple[Hook, ...] | list[Hook] = (), task: Task = CORNERS):
        self.cfg, self.model, self.opt, self.dev, self.bf16, self.task = cfg, model, opt, dev, bf16, task
        self.net = model if net is None else net
        self.dist, self.rank, self.world = _dist()
        self.clock, self.run_dir = clock, run_dir
        self.t_start = clock() if t_start is None else t_start
        self.state = {"step": 0, "epoch": 0, "batch": 0} if state is None else state
        self.time0 = float(self.state.get("time_s", 0.0))
        self.budget_end_s = budget_end_s
        self.lr = self.now_s = 0.0
        self.steps_run = 0
        self.timing = LoopTiming(clock, self.t_start)
        self.checkpoint_s = 0.5  # until Checkpoints measures one
        self.folder_started = False
        self.stop_flag: dict = {}
        self.stop: str | None = None
        self.error: BaseException | None = None
        self.end_line: dict = {}
        self.hooks: list[Hook] = []
        self.register(*hooks)

    def register(self, *hooks: Hook) -> None:
        """Add hooks; all of them are then called in their declared order (trainer_hooks.hook_order)."""
        self.hooks = hook_order([*self.hooks, *hooks])
        for hook in hooks:
            hook.trainer = self

    def call(self, point: str, *args) -> None:
        """Every hook's `point` (before_train, after_step, after_epoch, on_checkpoint, ...), in order."""
        for hook in self.hooks:
            getattr(hook, point)(*args)

    def elapsed(self) -> float:
        """The run's clock, seconds: what it had used before this call (a resumed run's time_s) plus this call's."""
        return self.time0 + self.clock() - self.t_start

    def in_cooldown(self, now_s: float) -> bool:
        """The next step, at run-clock now_s, is in a constant_cooldown run's cooldown."""
        return in_cooldown(self.cfg, self.state["step"], now_s, self.budget_end_s)

    def run(self, batches) -> str | None:
        """Train on `batches`, an iterable of (batch, where the run stands after training it: a dict merged into
        state), until cfg.steps are done, a hook stops the run before a step, a signal came (the step in progress
        finishes) or the batches run out. The hooks' before_train first; on every way out the batches are closed,
        then the hooks' after_train. Returns why it stopped early (a hook's reason such as 'time_budget', a
        signal's name) or None."""
        self.lr = lr_at(self.cfg, self.state["step"], self.time0, self.budget_end_s)
        try:
            self.call("before_train")
            self.stop = self._loop(batches)
        except BaseException as error:
            self.error = error
            raise
        finally:
            if hasattr(batches, "close"):
                batches.close()  # the loader's or the renderers' workers shut down, on an error too
            self._after_train()
        return self.stop

    def _after_train(self) -> None:
        """Every hook's after_train, those after one that raised too; that error is the run's, raised after them."""
        first = None
        for hook in self.hooks:
            try:
                hook.after_train()
            except BaseException as error:
                first = first or error
                self.error = self.error or error
        if first is not None:
            raise first

    def _loop(self, batches) -> str | None:
        self.timing.ask()
        for cpu_batch, position in batches:
            if self.state["step"] >= self.cfg.steps or self.stop_flag.get("signal"):
                break
            self.timing.got()
            self.now_s = self.elapsed()
            reason = next((r for hook in self.hooks if (r := hook.before_step()) is not None), None)
            if reason is not None:
                self.call("on_stop", reason)
                return reason
            terms = self._step(cpu_batch)
            self.state["step"] += 1
            self.state.update(position)
            self.steps_run += 1
            self.call("after_step", terms)
            self.timing.step_done(first=self.steps_run == 1)
        return self.stop_flag.get("signal")

    def _step(self, cpu_batch: dict) -> dict:
        """One optimizer step at the schedule's rate for this step and run-clock now_s; the loss terms."""
        self.lr = lr_at(self.cfg, self.state["step"], self.now_s, self.budget_end_s)
        for g in self.opt.param_groups:
            g["lr"] = self.lr
        return _train_step(self.model, self.net, self.opt, to_device(cpu_batch, self.dev), self.cfg,
                           self.state["step"], self.dev, self.bf16, self.task.terms)


@dataclass(frozen=True)
class TrainOptions:
    """How one train() call runs, apart from what it learns (TrainConfig): see train() for each field."""

    resume: bool = False
    device: str = "cpu"
    progress: bool = False
    provenance: dict | None = None
    init_weights: str | None = None
    backbone_weights: str | None = None
    workers: int | None = None
    bf16: bool = False
    clock: Callable[[], float] = time.perf_counter
    task: Task = CORNERS


def _check_call(opts: TrainOptions) -> None:
    if torch.device(opts.device).type == "cuda" and not torch.cuda.is_available():
        raise InputError("device 'cuda': no CUDA device is available")
    if opts.workers is not None and opts.workers < 0:
        raise InputError(f"workers = {opts.workers}: expected 0 (in-process) or more worker processes")


def _build_model(cfg: TrainConfig, run_dir: str, opts: TrainOptions, dev: torch.device):
    """(model, optimizer, moving average or None): seeded, from init_weights, or a resumed run's checkpoint and
    optimizer."""
    model = opts.task.build(cfg).to(dev)
    start = os.path.join(run_dir, "checkpoint.safetensors") if opts.resume else opts.init_weights
    if start is not None:
        load_state(model, read_weights(start)[0], start)
    elif opts.backbone_weights is not None:
        load_backbone(model, opts.backbone_weights)
    if dev.type == "cuda":
        model = model.to(memory_format=torch.channels_last)
    opt = make_optimizer(model, cfg, dev)
    if opts.resume:
        opt.load_state_dict(load_tensors(os.path.join(run_dir, "optimizer.pt")))
    return model, opt, make_ema(model, cfg)


def _folder_trainer(cfg: TrainConfig, run_dir: str, opts: TrainOptions, state: dict, saved: dict | None,
                 t_start: float) -> Trainer:
    """The Trainer of a train() call with the run folder's hooks, in their order: the budget, the pre-cooldown
    weights, the moving average, the run folder, the progress bar, DDP agreement, checkpoints, signals, metrics."""
    dev = torch.device(opts.device)
    model, opt, ema = _build_model(cfg, run_dir, opts, dev)
    dist, rank, _ = _dist()
    net = model if dist is None else torch.nn.parallel.DistributedDataParallel(
        model, device_ids=[dev.index] if dev.type == "cuda" else None)
    model.train()
    end_s, time0 = state["budget_end_s"], float(state["time_s"])
    bar = progress_bar(cfg.steps, state, end_s, time0, opts.progress and rank == 0)
    continuing = saved is not None and saved["train"].get("time_budget_s") == cfg.time_budget_s  # the same budget
    hooks = [Budget(end_s, resumed=continuing) if end_s is not None else None,
             PreCooldown() if cfg.schedule == "constant_cooldown" else None,
             None if ema is None else MovingAverage(ema, cfg.ema_decay, opts.resume),
             RunFolder(saved, opts.provenance, state["step"]), Progress(bar, end_s is not None),
             None if dist is None else DdpAgreement(), Checkpoints(cfg.checkpoint_every), StopOnSignals(), Metrics()]
    return Trainer(cfg, model, opt, dev=dev, net=net, bf16=opts.bf16, clock=opts.clock, t_start=t_start,
                   state=state, budget_end_s=end_s, run_dir=run_dir, hooks=[h for h in hooks if h is not None],
                   task=opts.task)


def train(cfg: TrainConfig, data_dir: str | list[str], run_dir: str, resume: bool = False, device: str = "cpu",
          progress: bool = False, provenance: dict | None = None, init_weights: str | None = None,
          workers: int | None = None, bf16: bool = False, clock=time.perf_counter,
          paths: list[str] | None = None, online=None, task: Task = CORNERS,
          backbone_weights: str | None = None) -> dict:
    """Train (or go on training, with resume) into run_dir. Returns the last metrics line.

    data_dir: one dataset folder or several (their shards are read together); paths: the shard files to read
    when the caller checked them already (else every shard of data_dir). init_weights: a safetensors file of
    the same architecture to start from instead of the seeded initialization (fine-tuning; a new run only).
    backbone_weights: any detector's weights whose backbone (stem, hourglass, neck) starts a new run's network, its
    heads seeded (weights.load_backbone: transfer from another target's detector, ENVISAT's included).
    workers: DataLoader worker processes feeding the batches (perception/stream.py; 0: in-process); None: the
    run's own count on resume, else 0. The batches depend on the count, so a resumed run keeps it. The workers
    start from a fork server without the calling script (perception/stream.py), so a plain script needs no
    `if __name__ == "__main__":` guard.
    bf16: the network's forward under bfloat16 autocast (CUDA or CPU); losses, weights and optimizer in float32.
    With a time budget the run stops before the next step would leave too little of it for the final checkpoint
    (the budget counts from this call's start, plus what a resumed run had already used; see
    train_run.budget_end); a budget too short for one step is an InputError. A resumed run already at its
    steps or budget trains nothing and returns an end line with stopped_by 'nothing_to_do'.
    clock: the seconds every time figure and the budget are read from (a test gives its own).
    online: instead of shards, a function start_state -> iterator of (batch on the device, state) (frames
    rendered as training goes: pipelines/detector/online.py); each step's state is kept in state.json under 'online' and
    handed back on resume; no epochs, data_dir and paths unused.
    task: what is trained (Task: its model, loss terms and online batches); CORNERS, ENVISAT's corner network,
    the only one that reads shards (another task trains online).
    Raises TrainingInterrupted after the checkpoint when SIGINT or SIGTERM stopped it.
    """
    opts = TrainOptions(resume=resume, device=device, progress=progress, provenance=provenance,
                        init_weights=init_weights, backbone_weights=backbone_weights, workers=workers, bf16=bf16,
                        clock=clock, task=task)
    _check_call(opts)
    if task is not CORNERS and online is None:
        raise InputError("data_dirs: the corner network alone trains on shards; this task trains online")
    t_start = clock()
    if paths is None and online is None:
        paths = [p for d in ([data_dir] if isinstance(data_dir, str) else list(data_dir)) for p in shard_paths(d)]
    state, saved = start_state(run_dir, cfg, resume, workers, (provenance or {}).get("data"), _dist()[2])
    state["budget_end_s"] = budget_end(cfg, saved, state)
    if saved is not None and (end := nothing_to_do(cfg, state, saved)) is not None:
        return end
    trainer = _folder_trainer(cfg, run_dir, opts, state, saved, t_start)
    source = rendered_batches(online, state) if online is not None else shard_batches(trainer, paths, data_dir)
    stop = trainer.run(source)
    if stop not in (None, "time_budget"):
        raise TrainingInterrupted(state["step"] if trainer.folder_started else 0, run_dir, stop)
    return end_line(trainer, stop)
