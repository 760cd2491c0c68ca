"""The training loop's concerns, one small object each, registered on the Trainer (perception/train.py) and called
by it at named points (detectron2's HookBase): before_train, before_step (may ask the loop to stop before the
step), after_step, on_stop (the loop stopped before a step), after_epoch (the batch source finished an epoch),
on_checkpoint (a checkpoint is being written), after_train (on every way out of the loop: a `finally`).

The order is declared, not listed: a hook names in `after` the hooks it must follow at every point, with the
reason beside it, and the Trainer sorts the hooks it is given by those names (hook_order: stable, so hooks
without a constraint between them keep the order they were given in), refusing a name given twice, an `after`
that names no hook and constraints that contradict one another. Hooks never hold one another: what they share
lives on the trainer (its docstring lists it): the run clock of the step (`now_s`, which Budget makes rank 0's
under DDP), the steps' wall times (`timing`), the last checkpoint's seconds (`checkpoint_s`), whether the run
folder exists (`folder_started`), the stop flag a signal sets (`stop_flag`), the exception leaving the loop
(`error`) and the end line (`end_line`). LoopTiming is not a hook: the loop itself reads it around each wait for a
batch.
"""

from __future__ import annotations

import json
import os
import signal
import threading

import torch

from envisat_pose.config import InputError, to_toml
from envisat_pose.io import atomic_write_text
from envisat_pose.perception.weights import load_state, read_weights, save_tensors, save_weights
from envisat_pose.provenance import source_line
from envisat_pose.target import load_target
from envisat_pose.written_target import with_target_sha256

CONFIG_TOML = "train.config.toml"  # the run's TrainConfig as `envisat train --config` reads it (beside config.json)
SHUTDOWN_RESERVE_S = 1.0  # a budgeted run keeps this for the final log, checkpoint and the workers' shutdown
POSTFIX_EVERY = 10  # steps between the progress bar's loss readings (each one waits for the device)


class Hook:
    """A piece of the training loop; every method does nothing unless a hook overrides it. `after`: the names
    (class names) of the hooks this one is called after at every point, when they are registered too."""

    after: tuple[str, ...] = ()
    trainer = None  # the Trainer (perception/train.py), set when the hook is registered

    @property
    def name(self) -> str:
        return type(self).__name__

    def before_train(self) -> None:
        """The trainer is built and its state set; no batch asked for yet."""

    def before_step(self) -> str | None:
        """Before the step at run-clock trainer.now_s (seconds): a reason to stop before it, or None."""
        return None

    def after_step(self, terms: dict) -> None:
        """After the step (trainer.state['step'] already counts it); terms: the loss terms, tensors on the device."""

    def on_stop(self, reason: str) -> None:
        """The loop stopped before a step for `reason` (a before_step's answer)."""

    def after_epoch(self) -> None:
        """The batch source finished an epoch (trainer.state['epoch'] still counts it)."""

    def on_checkpoint(self) -> None:
        """A checkpoint is being written (rank 0, the run folder made): save this hook's own files."""

    def after_train(self) -> None:
        """The loop is over, on every way out, its batch source closed: trainer.error is the exception leaving it
        (None when the steps, a hook's stop, a signal or the end of the batches ended it)."""


def hook_classes(base: type = Hook) -> set[str]:
    """The names of every Hook subclass defined so far (theirs too)."""
    found: set[str] = set()
    for sub in base.__subclasses__():
        found |= {sub.__name__} | hook_classes(sub)
    return found


def hook_order(hooks: list[Hook]) -> list[Hook]:
    """The hooks in the order the trainer calls them: as given, each moved behind the hooks its `after` names
    (stable: a hook is called at its place in the list unless a constraint moves it). ValueError for a hook
    given twice, an `after` naming no hook class, or constraints that loop."""
    names = [h.name for h in hooks]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"hooks registered twice: {twice}")
    known = hook_classes()
    for h in hooks:
        unknown = [a for a in h.after if a not in known]
        if unknown:
            raise ValueError(f"{h.name}.after names no hook class: {unknown}")
    placed: list[Hook] = []
    left = list(hooks)
    while left:
        done = {p.name for p in placed}
        ready = next((h for h in left if all(a in done or a not in names for a in h.after)), None)
        if ready is None:
            raise ValueError("the hooks' order loops: " + "; ".join(f"{h.name} after {', '.join(h.after)}"
                                                                     for h in left))
        placed.append(ready)
        left.remove(ready)
    return placed


class LoopTiming:
    """The loop's own figures (not a hook: the loop reads them around each wait for a batch), from the trainer's
    clock: the wait for each batch, the first batch's arrival (seconds after t_start) and the last steps' wall
    times (data wait included), which the budget reads."""

    def __init__(self, clock, t_start: float):
        self.clock, self.t_start = clock, t_start
        self.t_ask = self.t_got = 0.0
        self.first_batch_s: float | None = None
        self.data_wait_s = 0.0
        self.iter_s: list[float] = []

    def ask(self) -> None:
        """The loop asks its source for the next batch."""
        self.t_ask = self.clock()

    def got(self) -> None:
        """The batch came."""
        self.t_got = self.clock()
        self.data_wait_s += self.t_got - self.t_ask
        if self.first_batch_s is None:
            self.first_batch_s = self.t_got - self.t_start

    def step_done(self, first: bool) -> None:
        """A step and its hooks are done; the loop goes back to its source. A step's wall time counts its wait
        for data, except the run's first (the loaders' start-up, seconds that no later step waits again, would
        hold back a budget's last steps)."""
        self.iter_s.append(self.clock() - (self.t_got if first else self.t_ask))
        self.ask()

    def figures(self, steps_run: int, batch_size: int, world: int) -> dict:
        """The end line's speed figures: this call's steps, samples a second after the first batch came, the
        first batch's wait and the whole data wait (seconds)."""
        loop_s = self.clock() - self.t_start - (self.first_batch_s or 0.0)
        return {"steps_run": steps_run, "samples_s": round(steps_run * batch_size * world / max(loop_s, 1e-9), 2),
                "first_batch_s": round(self.first_batch_s or 0.0, 3), "data_wait_s": round(self.data_wait_s, 3)}


class StopOnSignals(Hook):
    """While training: SIGINT and SIGTERM set trainer.stop_flag['signal'] (the loop stops after its step, with a
    checkpoint); a second SIGINT raises KeyboardInterrupt at once. Only in the main thread (signals are
    delivered there). The old handlers come back at after_train, so the last checkpoint and the ranks' agreement
    run under these (a first Ctrl-C there does not cut them)."""

    after = ("Checkpoints", "DdpAgreement")  # their after_train still under the handlers

    def __init__(self):
        self._old: dict = {}

    def _handler(self, signum, _frame) -> None:
        flag = self.trainer.stop_flag
        if flag.get("signal") and signum == signal.SIGINT:
            raise KeyboardInterrupt
        flag["signal"] = signal.Signals(signum).name

    def before_train(self) -> None:
        if threading.current_thread() is threading.main_thread():
            self._old = {sig: signal.signal(sig, self._handler) for sig in (signal.SIGINT, signal.SIGTERM)}

    def after_train(self) -> None:
        for sig, h in self._old.items():
            signal.signal(sig, h)
        self._old = {}


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
    takes rank 0's clock and reserve (trainer.now_s, before each step): the ranks stop at the same step and
    follow the same rate. A budget too short for the first step is an InputError, but for a run resumed under its
    own budget (resumed), whose budget is then spent: it stops with nothing trained."""

    def __init__(self, budget_end_s: float, resumed: bool = False):
        self.budget_end_s, self.resumed = budget_end_s, resumed
        self.reserve = 0.0  # seconds, set before each step

    def reserve_s(self) -> float:
        """Seconds kept for one more step, the checkpoint and the shutdown (this rank's figures)."""
        tr = self.trainer
        return 1.5 * max(tr.timing.iter_s[-10:], default=0.0) + tr.checkpoint_s + SHUTDOWN_RESERVE_S

    def before_step(self) -> str | None:
        tr = self.trainer
        tr.now_s, self.reserve = shared_clock(tr.dist, tr.dev, tr.now_s, self.reserve_s())
        if tr.now_s + self.reserve < self.budget_end_s:
            return None
        if tr.steps_run == 0 and not self.resumed:
            raise InputError(f"time_budget_s = {tr.cfg.time_budget_s:g}: too short for one step (the first batch "
                             f"came {tr.now_s - tr.time0:.1f} s into it; a step, the checkpoint and the shutdown "
                             f"need ~{self.reserve:.1f} s more): give a longer budget")
        return "time_budget"

    def on_checkpoint(self) -> None:
        """state.json's min_leg_s: the least of the budget in which a resume of this run trains a step (this
        call's wait for its first batch, the batch sources' start-up, and the reserve before a step), which
        train_run.nothing_to_do reads (with its margin: leg_need_s) before it starts anything."""
        tr = self.trainer
        tr.state["min_leg_s"] = round((tr.timing.first_batch_s or 0.0) + self.reserve_s(), 3)


class RunFolder(Hook):
    """The run folder, its config.json and its TrainConfig as train.config.toml (CONFIG_TOML), made once the first
    step is trained (nothing half-made before); a resumed run's record takes its new steps or budget and its
    threads (what a later resume takes) and keeps each resuming command under 'resumes', with the step it resumed
    from and its threads. Sets trainer.folder_started (a resumed run's folder exists from the start)."""

    def __init__(self, saved: dict | None, provenance: dict | None, resumed_at: int):
        self.saved, self.provenance, self.resumed_at = saved, provenance or {}, resumed_at
        self._recorded = False

    def before_train(self) -> None:
        self.trainer.folder_started = self.saved is not None

    def after_step(self, terms: dict) -> None:
        """Make the folder (or record the resume) unless done already; only rank 0 writes."""
        tr = self.trainer
        if tr.folder_started:
            if self.saved is not None and not self._recorded and tr.rank == 0:
                self._recorded = True
                threads = self.provenance.get("threads")  # this leg's, where known: what the next resume takes
                leg = {} if threads is None else {"threads": threads}
                resumes = self.saved.get("resumes", []) + [{"command": self.provenance.get("command", ""),
                                                            "git": self.provenance.get("git"),
                                                            "step": self.resumed_at, **leg}]
                self._write({**self.saved, "train": tr.cfg.to_dict(), **leg, "resumes": resumes})
            return
        tr.folder_started = True
        if tr.rank == 0:
            os.makedirs(tr.run_dir, exist_ok=True)
            self._write({"train": tr.cfg.to_dict(), **self.provenance})

    def _write(self, record: dict) -> None:
        """config.json (what a resume reads), then its TrainConfig as CONFIG_TOML (what `--config` reads back),
        with the sha256 of the target file it names (another target's run; written_target.with_target_sha256),
        which `envisat train --config` checks the file against."""
        atomic_write_text(os.path.join(self.trainer.run_dir, "config.json"),
                          json.dumps(record, indent=1, sort_keys=True) + "\n")
        target = record["train"].get("target")
        sha256 = load_target(target).sha256 if isinstance(target, str) else None
        atomic_write_text(os.path.join(self.trainer.run_dir, CONFIG_TOML),
                          "# envisat train: the full validated config of this run\n" + source_line()
                          + "# `envisat train --config THIS_FILE` on the same data trains it again (its shards by "
                          "name and manifest sha256, or its online looks: config.json beside it)\n"
                          + to_toml(with_target_sha256(record["train"], "train", sha256)))


class Checkpoints(Hook):
    """checkpoint.safetensors, optimizer.pt, the other hooks' files (on_checkpoint) and state.json (last: where
    --resume goes on), every `every` steps and at the end of a run the loop left without an error; rank 0 only,
    once the run folder exists. Measures its own seconds into trainer.checkpoint_s (the budget's reserve)."""

    after = ("RunFolder", "MovingAverage")  # the folder exists and the average holds the step it checkpoints

    def __init__(self, every: int):
        self.every = every

    def after_step(self, terms: dict) -> None:
        tr = self.trainer
        if tr.state["step"] % self.every == 0:
            t0 = tr.clock()
            self.write()
            tr.checkpoint_s = tr.clock() - t0

    def after_train(self) -> None:
        if self.trainer.error is None:
            self.write()

    def write(self) -> None:
        tr = self.trainer
        if not tr.folder_started:
            return
        check_finite(tr.model, tr.state["step"], tr.lr)  # on every rank: DDP's replicas are equal, all stop at once
        if tr.rank != 0:
            return
        tr.state["time_s"] = round(tr.elapsed(), 3)
        save_weights(os.path.join(tr.run_dir, "checkpoint.safetensors"), tr.model, {"step": str(tr.state["step"])})
        save_tensors(os.path.join(tr.run_dir, "optimizer.pt"), tr.opt.state_dict())
        tr.call("on_checkpoint")
        atomic_write_text(os.path.join(tr.run_dir, "state.json"), json.dumps(tr.state, sort_keys=True) + "\n")


class TrainingDiverged(InputError):
    """The weights went non-finite: the run stops before it would write them over the last checkpoint."""


def check_finite(model: torch.nn.Module, step: int, lr: float) -> None:
    """TrainingDiverged naming the step, the learning rate and how many weight tensors are not finite, where any
    is not (one check at each checkpoint: no host sync in the steps between)."""
    tensors = [t for t in model.state_dict().values() if t.is_floating_point()]
    bad = sum(not bool(torch.isfinite(t).all()) for t in tensors)
    if bad:
        raise TrainingDiverged(f"training diverged by step {step}: {bad} of {len(tensors)} weight tensors are not "
                               f"finite (learning rate {lr:g}: try a lower `lr`); the last checkpoint and state.json "
                               "are kept as they were")


class MovingAverage(Hook):
    """The exponential moving average of the weights (torch's AveragedModel), updated after every step and kept
    as ema.safetensors; a resumed run reads it back (before_train) and counts its steps as averaged."""

    def __init__(self, ema, decay: float, resume: bool):
        self.ema, self.decay, self.resume = ema, decay, resume

    def path(self) -> str:
        return os.path.join(self.trainer.run_dir, "ema.safetensors")

    def before_train(self) -> None:
        """Read the average a resumed run kept (when it kept one)."""
        if self.resume and os.path.exists(self.path()):
            load_state(self.ema.module, read_weights(self.path())[0], self.path())
            self.ema.n_averaged.fill_(max(1, int(self.trainer.state["step"])))

    def after_step(self, terms: dict) -> None:
        self.ema.update_parameters(self.trainer.model)

    def on_checkpoint(self) -> None:
        save_weights(self.path(), self.ema.module, {"step": str(self.trainer.state["step"]),
                                                    "ema_decay": str(self.decay)})


class PreCooldown(Hook):
    """(schedule 'constant_cooldown') The weights and optimizer before the cooldown's first step, the next leg's
    start: pre_cooldown.safetensors and pre_cooldown_optimizer.pt, and state['pre_cooldown_step']; a budget that
    stops the run before its cooldown keeps its last weights so."""

    after = ("Budget",)  # the step's clock is rank 0's, and a budget's refusal of the first step writes nothing

    def saved(self) -> bool:
        return "pre_cooldown_step" in self.trainer.state

    def before_step(self) -> str | None:
        if not self.saved() and self.trainer.in_cooldown(self.trainer.now_s):
            self.save()
        return None

    def on_stop(self, reason: str) -> None:
        if reason == "time_budget" and not self.saved():
            self.save()  # stopped before its cooldown: these weights are the next start

    def save(self) -> None:
        tr = self.trainer
        tr.state["pre_cooldown_step"] = tr.state["step"]
        if tr.rank == 0:
            os.makedirs(tr.run_dir, exist_ok=True)  # a cooldown from the first step: before the folder's record
            save_weights(os.path.join(tr.run_dir, "pre_cooldown.safetensors"), tr.model,
                         {"step": str(tr.state["step"]), "pre_cooldown": "true"})
            save_tensors(os.path.join(tr.run_dir, "pre_cooldown_optimizer.pt"), tr.opt.state_dict())


class Metrics(Hook):
    """metrics.jsonl: the loss terms summed on the device after each step and averaged into a line (the one place
    they are read back; a line right after another repeats its terms): one at each epoch's end, and the end line
    of a run the loop left without an error (the figures other hooks put in trainer.end_line, this call's speed,
    why it stopped), kept as trainer.end_line."""

    after = ("Checkpoints", "DdpAgreement")  # the end line comes after the last checkpoint and the ranks' figures

    def __init__(self):
        self.sums: dict[str, torch.Tensor] = {}
        self.count = 0
        self.terms_mean: dict[str, float] = {}

    def after_step(self, terms: dict) -> None:
        for k, v in terms.items():
            self.sums[k] = self.sums[k] + v if k in self.sums else v
        self.count += 1

    def after_epoch(self) -> None:
        self.log("epoch")

    def after_train(self) -> None:
        tr = self.trainer
        if tr.error is not None:
            return
        stop = tr.stop
        speed = {**tr.timing.figures(tr.steps_run, tr.cfg.batch_size, tr.world), "workers": tr.state["workers"],
                 "bf16": tr.bf16,
                 "stopped_by": "steps" if stop is None else ("time_budget" if stop == "time_budget" else "signal")}
        tr.end_line = self.log("end", {**tr.end_line, **speed})

    def log(self, kind: str, extra: dict | None = None) -> dict:
        """A metrics line of `kind` ('epoch', 'end'), written by rank 0 once the run folder exists; returned."""
        tr = self.trainer
        if self.count:
            self.terms_mean = {k: float(v) / self.count for k, v in self.sums.items()}
        line = {"kind": kind, "epoch": tr.state["epoch"], "step": tr.state["step"], "lr": tr.lr,
                "time_s": round(tr.elapsed(), 3), **self.terms_mean, **(extra or {})}
        if tr.rank == 0 and tr.folder_started:
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
    and after this call's first; closed on every way out."""

    def __init__(self, bar, by_budget: bool):
        self.bar, self.by_budget, self.loss_text = bar, by_budget, "?"

    def after_step(self, terms: dict) -> None:
        tr = self.trainer
        if tr.state["step"] % POSTFIX_EVERY == 0 or tr.steps_run == 1:  # the loss read back (a device sync)
            self.loss_text = f"{float(terms['loss']):.3f}"
        # the step every step (a budget's bar counts seconds), set before the update that may draw it
        self.bar.set_postfix_str(f"step={tr.state['step']}, loss={self.loss_text}", refresh=False)
        if self.by_budget:
            advance_budget_bar(self.bar, tr.elapsed() - tr.time0)
        else:
            self.bar.update(1)

    def after_train(self) -> None:
        self.bar.close()


def ranks_identical(dist, model: torch.nn.Module, world: int) -> bool:
    """Every rank holds the same parameters and buffers, bit for bit (gathered and compared on all ranks)."""
    flat = torch.cat([t.detach().reshape(-1).double().cpu() for t in model.state_dict().values()])
    gathered = [torch.empty_like(flat) for _ in range(world)]
    dist.all_gather(gathered, flat)
    return all(torch.equal(gathered[0], g) for g in gathered[1:])


class DdpAgreement(Hook):
    """(DDP) After a run the loop left without an error (an error on one rank must not wait for the others):
    rank 0's BatchNorm statistics on every rank (those of the last forward are each rank's own), then whether
    the ranks agree bit for bit: the end line's 'ranks_identical' and 'world'."""

    def after_train(self) -> None:
        tr = self.trainer
        if tr.error is not None:
            return
        for b in tr.model.buffers():
            tr.dist.broadcast(b, src=0)
        tr.end_line.update({"ranks_identical": float(ranks_identical(tr.dist, tr.model, tr.world)),
                            "world": float(tr.world)})
