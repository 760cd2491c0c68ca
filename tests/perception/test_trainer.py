"""The Trainer as an extension point, on a small network and the tiny dataset's batches: a Trainer with only a hook
of its own (no run folder: adapt's fine-tune, a benchmark) trains its steps at the schedule's rates and calls
before_train once before them; after_train runs on every way out, the batches closed before it and the
exception named to it; a hook that stops the run before a step is told why, and so are the others."""

import pytest
import torch

from envisat_pose.perception.data import DataConfig, shard_paths
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.stream import epoch_batches
from envisat_pose.perception.train import TrainConfig, Trainer, init_model, lr_at
from envisat_pose.perception.trainer_hooks import Hook


def config(steps):
    return TrainConfig(steps=steps, batch_size=2, warmup_steps=2, checkpoint_every=10 ** 6,
                       model=ModelConfig(input_px=128, width=16, depth=2, stem_width=8),
                       data=DataConfig(input_px=128, augment=False))


class Record(Hook):
    """Every point it is called at, with the trainer's step and rate."""

    def __init__(self, stop_at=None):
        self.calls, self.stop_at = [], stop_at

    def before_train(self):
        self.calls.append(("before_train", self.trainer.state["step"]))

    def before_step(self):
        if self.trainer.state["step"] == self.stop_at:
            return "enough"
        return None

    def after_step(self, terms):
        self.calls.append(("after_step", self.trainer.state["step"], self.trainer.lr, float(terms["loss"])))

    def on_stop(self, reason):
        self.calls.append(("on_stop", reason))

    def after_train(self):
        self.calls.append(("after_train", type(self.trainer.error).__name__ if self.trainer.error else None))


class Batches:
    """The tiny dataset's batches of epoch 0 as (batch, {}), closable, counting what was taken."""

    def __init__(self, data_dir, cfg):
        self.it = iter(list(epoch_batches(shard_paths(data_dir), cfg.data, cfg.seed, 0, cfg.batch_size, 0)))
        self.closed, self.taken = False, 0

    def __iter__(self):
        return self

    def __next__(self):
        self.taken += 1
        return next(self.it), {}

    def close(self):
        self.closed = True


def trainer(cfg, *hooks):
    torch.set_num_threads(1)
    model = init_model(cfg)
    return Trainer(cfg, model, torch.optim.AdamW(model.parameters(), lr=cfg.lr), dev=torch.device("cpu"),
                   hooks=list(hooks))


def test_a_trainer_with_a_hook_of_its_own_trains_its_steps_at_the_schedules_rates(tiny_dataset):
    cfg, record = config(3), Record()
    tr = trainer(cfg, record)
    batches = Batches(tiny_dataset, cfg)
    assert tr.run(batches) is None and tr.state["step"] == 3 and tr.run_dir is None
    assert record.calls[0] == ("before_train", 0) and record.calls[-1] == ("after_train", None)
    steps = record.calls[1:-1]
    assert [c[:3] for c in steps] == [("after_step", k + 1, lr_at(cfg, k)) for k in range(3)]
    assert batches.closed and tr.end_line == {}  # no Metrics: no end line


def test_after_train_runs_on_an_error_with_the_batches_closed_and_the_error_named(tiny_dataset):
    class Fails(Hook):
        def after_step(self, terms):
            if self.trainer.state["step"] == 2:
                raise RuntimeError("a hook failed")

    cfg, record = config(5), Record()
    tr = trainer(cfg, Fails(), record)
    batches = Batches(tiny_dataset, cfg)
    with pytest.raises(RuntimeError, match="a hook failed"):
        tr.run(batches)
    assert batches.closed and isinstance(tr.error, RuntimeError)
    assert record.calls[-1] == ("after_train", "RuntimeError") and tr.state["step"] == 2


def test_a_hooks_stop_before_a_step_is_told_to_every_hook(tiny_dataset):
    cfg = config(5)
    stopper, other = Record(stop_at=2), type("Other", (Record,), {})()
    tr = trainer(cfg, stopper, other)
    assert tr.run(Batches(tiny_dataset, cfg)) == "enough" and tr.state["step"] == 2
    for hook in (stopper, other):
        assert [c[0] for c in hook.calls] == ["before_train", "after_step", "after_step", "on_stop", "after_train"]
        assert ("on_stop", "enough") in hook.calls


def test_a_resume_with_its_target_file_changed_says_so(tmp_path):
    """An online run of another target resumed after its file was edited: refused naming the change (the data
    hash folds the file in, and once the refusal read 'trained on online (...), not on online (...)' with the same
    names on both sides)."""
    import json

    from envisat_pose.config import InputError
    from envisat_pose.perception.train_run import check_resume

    cfg = TrainConfig(steps=4)
    record = {"name": "online (target box, nominal 100 %, K = 4)", "manifest_sha256": "f" * 64, "images": None}
    (tmp_path / "config.json").write_text(json.dumps({"train": cfg.to_dict(),
                                                      "data": [{**record, "target_sha256": "a" * 64}]}))
    (tmp_path / "state.json").write_text(json.dumps({"step": 2}))
    edited = [{**record, "manifest_sha256": "e" * 64, "target_sha256": "b" * 64}]
    with pytest.raises(InputError, match=r"target file that has changed since \(sha256 aaaaaaaaaaaa\.\.\. then, "
                                         r"bbbbbbbbbbbb\.\.\. now\)"):
        check_resume(str(tmp_path), cfg, edited)
    assert check_resume(str(tmp_path), cfg, [{**record, "target_sha256": "a" * 64}])[0] == {"step": 2}


class Raises(Hook):
    """after_train raises `error` (a hook failing on the way out)."""

    def __init__(self, error):
        self.error = error

    def after_train(self):
        raise self.error


class RaisesToo(Raises):
    after = ("Raises",)


class Last(Record):
    after = ("RaisesToo",)


def test_every_after_train_runs_when_one_raises_and_the_first_error_is_raised(tiny_dataset):
    """Two hooks fail in after_train: the hooks after them still run theirs (a progress bar closed, signal
    handlers given back) and see the run as failed (trainer.error: the first failure, so no end line or last
    checkpoint is written after it); that first failure is what run() raises."""
    cfg, last = config(1), Last()
    tr = trainer(cfg, last, RaisesToo(ValueError("second")), Raises(RuntimeError("first")))
    assert [h.name for h in tr.hooks] == ["Raises", "RaisesToo", "Last"]
    with pytest.raises(RuntimeError, match="first"):
        tr.run(Batches(tiny_dataset, cfg))
    assert last.calls[-1] == ("after_train", "RuntimeError") and isinstance(tr.error, RuntimeError)


def test_the_trainer_calls_its_hooks_in_their_declared_order_and_refuses_one_that_cannot_hold():
    """Trainer(hooks=...) and register() sort the hooks by their `after` (the Checkpoints' last write before the
    Metrics' end line, given either way) and refuse a loop or a misspelt name, as hook_order does."""
    from envisat_pose.perception import trainer_hooks as th

    cfg = config(1)
    assert [h.name for h in trainer(cfg, th.Metrics(), th.Checkpoints(1)).hooks] == ["Checkpoints", "Metrics"]
    tr = trainer(cfg, th.Metrics())
    tr.register(th.Checkpoints(1))
    assert [h.name for h in tr.hooks] == ["Checkpoints", "Metrics"]
    with pytest.raises(ValueError, match="twice"):
        tr.register(th.Metrics())
    with pytest.raises(ValueError, match="loops"):
        trainer(cfg, type("Early", (Hook,), {"after": ("Late",)})(), type("Late", (Hook,), {"after": ("Early",)})())


class Signal(Hook):
    """Sets the stop flag as StopOnSignals' handler does, during step 2."""

    def after_step(self, terms):
        if self.trainer.state["step"] == 2:
            self.trainer.stop_flag["signal"] = "SIGTERM"


def test_a_signal_stops_the_run_after_its_step_and_is_why_it_stopped(tiny_dataset):
    """A signal during step 2 of 5: the loop finishes that step and stops; run() returns the signal's name (the
    end line's stopped_by, the CLI's message), not None (the steps all done)."""
    cfg = config(5)
    tr = trainer(cfg, Signal())
    assert tr.run(Batches(tiny_dataset, cfg)) == "SIGTERM" and tr.state["step"] == 2 and tr.stop == "SIGTERM"
