"""The training loop's concerns, one small object each, called by the Trainer (perception/train.py) at named points
(detectron2's HookBase): before_step (may ask the loop to stop before the step), after_step, on_stop (the loop
stopped before a step), on_checkpoint (a checkpoint is being written), after_train.

The Trainer calls its hooks in a fixed order, which is part of their contract: before a step the time budget,
then the pre-cooldown weights; after a step the moving average, the run folder, the metrics, the progress bar,
the checkpoint, then the step's timing; after training the progress bar, the DDP agreement, the last checkpoint.
A hook reads the training state through `trainer` (step, model, optimizer, clock), set when the Trainer is built.
Two hooks also have calls of their own at points inside the loop: Timing.ask and Timing.got around each wait for
a batch, and Budget.share_clock, which gives every DDP rank rank 0's clock for the step (its rate and its stop).
"""

from __future__ import annotations

import json
import os
import signal
import threading

import torch

from envisat_pose.config import InputError
from envisat_pose.io import atomic_write_text
from envisat_pose.perception.weights import load_state, read_weights, save_tensors, save_weights

SHUTDOWN_RESERVE_S = 1.0  # a budgeted run keeps this for the final log, checkpoint and the workers' shutdown
POSTFIX_EVERY = 10  # steps between the progress bar's loss readings (each one waits for the device)


class Hook:
    """A piece of the training loop; every method does nothing unless a hook overrides it."""

    trainer = None  # the Trainer (perception/train.py), set by it

    def before_step(self, now_s: float) -> str | None:
        """Before the step at run-clock now_s (seconds): a reason to stop before it, or None."""
        return None

    def after_step(self, terms: dict) -> None:
        """After the step (trainer.state['step'] already counts it); terms: the loss terms, tensors on the device."""

    def on_stop(self, reason: str) -> None:
        """The loop stopped before a step for `reason` (a before_step's answer)."""

    def on_checkpoint(self) -> None:
        """A checkpoint is being written (rank 0, the run folder made): save this hook's own files."""

    def after_train(self) -> None:
        """The loop is over (the steps, the budget or a signal), its batch source closed."""


class StopOnSignals:
    """While training (a context manager): SIGINT and SIGTERM set flag['signal'] (the loop stops after its step,
    with a checkpoint); a second SIGINT raises KeyboardInterrupt at once. Only in the main thread (signals are
    delivered there). flag is the dict perception/stream.py's loader_batches reads."""

    def __init__(self):
        self.flag: dict = {}
        self._old: dict = {}

    @property
    def caught(self) -> str | None:
        """The name of the signal that asked the run to stop ('SIGINT', 'SIGTERM'), or None."""
        return self.flag.get("signal")

    def _handler(self, signum, _frame) -> None:
        if self.flag.get("signal") and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.flag["signal"] = signal.Signals(signum).name

    def __enter__(self) -> StopOnSignals:
        if threading.current_thread() is threading.main_thread():
            self._old = {sig: signal.signal(sig, self._handler) for sig in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc) -> None:
        for sig, h in self._old.items():
            signal.signal(sig, h)
        self._old = {}


class Timing(Hook):
    """This call's own figures, from the trainer's clock: the wait for each batch, the first batch's arrival
    (seconds after the call's start) and the last steps' wall times (data wait included), which the budget reads."""

    def __init__(self):
        self.t_ask = self.t_got = 0.0
        self.first_batch_s: float | None = None
        self.data_wait_s = 0.0
        self.iter_s: list[float] = []

    def ask(self) -> None:
        """The loop asks its source for the next batch."""
        self.t_ask = self.trainer.clock()

    def got(self) -> None:
        """The batch came."""
        self.t_got = self.trainer.clock()
        self.data_wait_s += self.t_got - self.t_ask
        if self.first_batch_s is None:
            self.first_batch_s = self.t_got - self.trainer.t_start

    def after_step(self, terms: dict) -> None:
        # a step's wall time, its wait for data included, except the run's first (the loaders' start-up, seconds
        # that no later step waits again, would hold back a budget's last steps)
        first = self.trainer.steps_run == 1
        self.iter_s.append(self.trainer.clock() - (self.t_got if first else self.t_ask))
        self.ask()

    def figures(self, batch_size: int, world: int) -> dict:
        """The end line's speed figures: this call's steps, samples a second after the first batch came, the
        first batch's wait and the whole data wait (seconds)."""
        tr = self.trainer
        loop_s = tr.clock() - tr.t_start - (self.first_batch_s or 0.0)
        return {"steps_run": tr.steps_run, "samples_s": round(tr.steps_run * batch_size * world / max(loop_s, 1e-9), 2),
                "first_batch_s": round(self.first_batch_s or 0.0, 3), "data_wait_s": round(self.data_wait_s, 3)}


def shared_clock(dist, dev: torch.device, elapsed_s: float, reserve_s: float) -> tuple[float, float]:
    """Rank 0's clock for every rank (a budgeted DDP run must stop at the same step on all ranks)."""
    if dist is None:
        return elapsed_s, reserve_s
    t = torch.tensor([elapsed_s, reserve_s], dtype=torch.float64, device=dev)
    dist.broadcast(t, src=0)
    return float(t[0]), float(t[1])


class Budget(Hook):
    """The time budget: stop before a step that would leave too little of it (1.5 x the slowest of the last 10
    steps, the last checkpoint's seconds and SHUTDOWN_RESERVE_S) for the final checkpoint. Under DDP every rank
    takes rank 0's clock and reserve (share_clock, before each step): the ranks stop at the same step and follow
    the same rate. A budget too short for the first step is an InputError."""

    def __init__(self, budget_end_s: float, timing: Timing, checkpoints: Checkpoints):
        self.budget_end_s, self.timing, self.checkpoints = budget_end_s, timing, checkpoints
        self.reserve = 0.0  # seconds, set by share_clock

    def reserve_s(self) -> float:
        """Seconds kept for one more step, the checkpoint and the shutdown (this rank's figures)."""
        return 1.5 * max(self.timing.iter_s[-10:], default=0.0) + self.checkpoints.checkpoint_s + SHUTDOWN_RESERVE_S

    def share_clock(self, now_s: float) -> float:
        """The run clock for the next step: rank 0's under DDP (one broadcast, the reserve with it; kept)."""
        now_s, self.reserve = shared_clock(self.trainer.dist, self.trainer.dev, now_s, self.reserve_s())
        return now_s

    def before_step(self, now_s: float) -> str | None:
        if now_s + self.reserve < self.budget_end_s:
            return None
        tr = self.trainer
        if tr.steps_run == 0:
            raise InputError(f"time_budget_s = {tr.cfg.time_budget_s:g}: too short for one step (the first batch "
                             f"came {now_s - tr.time0:.1f} s into it; a step, the checkpoint and the shutdown need "
                             f"~{self.reserve:.1f} s more): give a longer budget")
        return "time_budget"


class RunFolder(Hook):
    """The run folder and its config.json, made once the first step is trained (nothing half-made before); a
    resumed run's record takes its new steps or budget and keeps each resuming command under 'resumes', with the
    step it resumed from."""

    def __init__(self, saved: dict | None, provenance: dict | None, resumed_at: int):
        self.saved, self.provenance, self.resumed_at = saved, provenance or {}, resumed_at
        self.started = saved is not None  # a resumed run's folder exists
        self._recorded = False

    def after_step(self, terms: dict) -> None:
        self.start()

    def start(self) -> None:
        """Make the folder (or record the resume) unless done already; only rank 0 writes."""
        tr = self.trainer
        if self.started:
            if self.saved is not None and not self._recorded and tr.rank == 0:
                self._recorded = True
                resumes = self.saved.get("resumes", []) + [{"command": self.provenance.get("command", ""),
                                                            "git": self.provenance.get("git"),
                                                            "step": self.resumed_at}]
                self._write({**self.saved, "train": tr.cfg.to_dict(), "resumes": resumes})
            return
        self.started = True
        if tr.rank == 0:
            os.makedirs(tr.run_dir, exist_ok=True)
            self._write({"train": tr.cfg.to_dict(), **self.provenance})

    def _write(self, record: dict) -> None:
        atomic_write_text(os.path.join(self.trainer.run_dir, "config.json"),
                          json.dumps(record, indent=1, sort_keys=True) + "\n")


class Checkpoints(Hook):
    """checkpoint.safetensors, optimizer.pt, the other hooks' files and state.json (last: where --resume goes on),
    every checkpoint_every steps and at the end; rank 0 only, once the run folder exists. Measures its own
    seconds for the budget's reserve."""

    def __init__(self, folder: RunFolder, every: int):
        self.folder, self.every = folder, every
        self.checkpoint_s = 0.5  # until one is measured

    def after_step(self, terms: dict) -> None:
        if self.trainer.state["step"] % self.every == 0:
            t0 = self.trainer.clock()
            self.write()
            self.checkpoint_s = self.trainer.clock() - t0

    def after_train(self) -> None:
        self.write()

    def write(self) -> None:
        tr = self.trainer
        if tr.rank != 0 or not self.folder.started:
            return
        tr.state["time_s"] = round(tr.elapsed(), 3)
        save_weights(os.path.join(tr.run_dir, "checkpoint.safetensors"), tr.model, {"step": str(tr.state["step"])})
        save_tensors(os.path.join(tr.run_dir, "optimizer.pt"), tr.opt.state_dict())
        for hook in tr.hooks:
            hook.on_checkpoint()
        atomic_write_text(os.path.join(tr.run_dir, "state.json"), json.dumps(tr.state, sort_keys=True) + "\n")


class MovingAverage(Hook):
    """The exponential moving average of the weights (torch's AveragedModel), updated after every step and kept
    as ema.safetensors; a resumed run reads it back and counts its steps as averaged."""

    def __init__(self, ema, decay: float, path: str):
        self.ema, self.decay, self.path = ema, decay, path

    def resume(self, step: int) -> None:
        """Read the average a resumed run kept (when it kept one)."""
        if os.path.exists(self.path):
            load_state(self.ema.module, read_weights(self.path)[0], self.path)
            self.ema.n_averaged.fill_(max(1, int(step)))

    def after_step(self, terms: dict) -> None:
        self.ema.update_parameters(self.trainer.model)

    def on_checkpoint(self) -> None:
        save_weights(self.path, self.ema.module, {"step": str(self.trainer.state["step"]),
                                                  "ema_decay": str(self.decay)})


class PreCooldown(Hook):
    """(schedule 'constant_cooldown') The weights and optimizer before the cooldown's first step, the next leg's
    start: pre_cooldown.safetensors and pre_cooldown_optimizer.pt, and state['pre_cooldown_step']; a budget that
    stops the run before its cooldown keeps its last weights so."""

    def __init__(self, folder: RunFolder):
        self.folder = folder

    def saved(self) -> bool:
        return "pre_cooldown_step" in self.trainer.state

    def before_step(self, now_s: float) -> str | None:
        if not self.saved() and self.trainer.in_cooldown(now_s):
            self.folder.start()
            self.save()
        return None

    def on_stop(self, reason: str) -> None:
        if reason == "time_budget" and not self.saved():
            self.save()  # stopped before its cooldown: these weights are the next start

    def save(self) -> None:
        tr = self.trainer
        tr.state["pre_cooldown_step"] = tr.state["step"]
        if tr.rank == 0:
            save_weights(os.path.join(tr.run_dir, "pre_cooldown.safetensors"), tr.model,
                         {"step": str(tr.state["step"]), "pre_cooldown": "true"})
            save_tensors(os.path.join(tr.run_dir, "pre_cooldown_optimizer.pt"), tr.opt.state_dict())


class Metrics(Hook):
    """metrics.jsonl: the loss terms summed on the device after each step and averaged into a line by log() (the
    one place they are read back; a line right after another repeats its terms)."""

    def __init__(self, folder: RunFolder):
        self.folder = folder
        self.sums: dict[str, torch.Tensor] = {}
        self.count = 0
        self.terms_mean: dict[str, float] = {}

    def after_step(self, terms: dict) -> None:
        for k, v in terms.items():
            self.sums[k] = self.sums[k] + v if k in self.sums else v
        self.count += 1

    def log(self, kind: str, extra: dict | None = None) -> dict:
        """A metrics line of `kind` ('epoch', 'end'), written by rank 0 once the run folder exists; returned."""
        tr = self.trainer
        if self.count:
            self.terms_mean = {k: float(v) / self.count for k, v in self.sums.items()}
        line = {"kind": kind, "epoch": tr.state["epoch"], "step": tr.state["step"], "lr": tr.lr,
                "time_s": round(tr.elapsed(), 3), **self.terms_mean, **(extra or {})}
        if tr.rank == 0 and self.folder.started:
            with open(os.path.join(tr.run_dir, "metrics.jsonl"), "a", encoding="utf-8") as fh:
                fh.write(json.dumps(line, sort_keys=True) + "\n")
        self.sums, self.count = {}, 0
        return line


def progress_bar(steps: int, state: dict, budget_end_s: float | None, time0: float, enabled: bool):
    """A step bar, or under a budget a bar of the budget's seconds (elapsed / budget)."""
    from tqdm import tqdm

    if budget_end_s is None:
        return tqdm(total=steps, initial=state["step"], disable=not enabled, desc="train", unit="step")
    return tqdm(total=round(budget_end_s - time0, 1), disable=not enabled, desc="train", unit="s",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of the budget{postfix}")


def advance_budget_bar(bar, seconds: float) -> None:
    """Move a budget's bar to `seconds` into it, never past its end: tqdm drops the total of a bar past it, and
    the bar's percentage then fails to format (a last step that ends after the budget's end)."""
    bar.update(max(0.0, min(round(seconds, 1), bar.total) - bar.n))


class Progress(Hook):
    """The progress bar (rank 0, when asked): steps, or a budget's seconds; the loss every POSTFIX_EVERY steps
    and after this call's first."""

    def __init__(self, bar, by_budget: bool):
        self.bar, self.by_budget = bar, by_budget

    def after_step(self, terms: dict) -> None:
        tr = self.trainer
        if self.by_budget:
            advance_budget_bar(self.bar, tr.elapsed() - tr.time0)
        else:
            self.bar.update(1)
        if tr.state["step"] % POSTFIX_EVERY == 0 or tr.steps_run == 1:
            self.bar.set_postfix(step=tr.state["step"], loss=f"{float(terms['loss']):.3f}")

    def after_train(self) -> None:
        self.bar.close()


def ranks_identical(dist, model: torch.nn.Module, world: int) -> bool:
    """Every rank holds the same parameters and buffers, bit for bit (gathered and compared on all ranks)."""
    flat = torch.cat([t.detach().reshape(-1).double().cpu() for t in model.state_dict().values()])
    gathered = [torch.empty_like(flat) for _ in range(world)]
    dist.all_gather(gathered, flat)
    return all(torch.equal(gathered[0], g) for g in gathered[1:])


class DdpAgreement(Hook):
    """(DDP) After training: rank 0's BatchNorm statistics on every rank (those of the last forward are each rank's
    own), then whether the ranks agree bit for bit; the end line's 'ranks_identical' and 'world'."""

    def __init__(self, dist, world: int):
        self.dist, self.world = dist, world
        self.figures: dict = {}

    def after_train(self) -> None:
        model = self.trainer.model
        for b in model.buffers():
            self.dist.broadcast(b, src=0)
        self.figures = {"ranks_identical": float(ranks_identical(self.dist, model, self.world)),
                        "world": float(self.world)}
