"""The Trainer's hooks one at a time, on a stand-in trainer (no model trained): the budget's stop rule, the
step timing it reads, the signal handlers, the metrics' averages and where they go, the pre-cooldown weights
kept once, the run folder's record of a resume; the hooks' declared order, checked when they are registered."""

import json
import os
import signal
from types import SimpleNamespace

import pytest
import torch

from envisat_pose.config import InputError
from envisat_pose.perception import trainer_hooks as th
from envisat_pose.perception.model import CornerNet, ModelConfig


class Clock:
    """Readings given in advance, one per call."""

    def __init__(self, *readings):
        self.readings = list(readings)

    def __call__(self):
        return self.readings.pop(0)


def stand_in(**kw):
    base = dict(dist=None, dev=torch.device("cpu"), steps_run=0, time0=0.0, rank=0, state={"step": 0, "epoch": 0},
                lr=1e-3, cfg=SimpleNamespace(time_budget_s=10.0, to_dict=lambda: {"steps": 3}), t_start=0.0,
                now_s=0.0, checkpoint_s=0.5, folder_started=False, stop_flag={}, error=None, end_line={})
    return SimpleNamespace(**{**base, **kw})


def test_timing_leaves_the_first_steps_data_wait_out():
    timing = th.LoopTiming(Clock(1.0, 5.0, 6.0, 7.0, 7.5, 8.5, 9.0), t_start=0.5)
    timing.ask()  # 1.0
    timing.got()  # 5.0: the loaders' start-up
    timing.step_done(first=True)  # 6.0 - 5.0, then asks at 7.0
    timing.got()  # 7.5
    timing.step_done(first=False)  # 8.5 - 7.0, then asks at 9.0
    assert timing.iter_s == [1.0, 1.5]
    assert timing.first_batch_s == 4.5 and timing.data_wait_s == 4.0 + 0.5


def test_the_budget_stops_before_a_step_that_would_leave_too_little():
    timing = SimpleNamespace(iter_s=[9.0] + [1.0] * 10)  # only the last 10 steps count
    budget = th.Budget(10.0)
    budget.trainer = stand_in(steps_run=11, timing=timing, checkpoint_s=0.5)
    reserve = 1.5 * 1.0 + 0.5 + th.SHUTDOWN_RESERVE_S
    budget.trainer.now_s = 10.0 - reserve - 1e-9
    assert budget.before_step() is None and budget.reserve == reserve
    assert budget.trainer.now_s == 10.0 - reserve - 1e-9  # one rank: its own clock
    budget.trainer.now_s = 10.0 - reserve
    assert budget.before_step() == "time_budget"
    budget.trainer.steps_run = 0
    with pytest.raises(InputError, match="too short for one step"):
        budget.before_step()
    # a resumed run with less of its budget left than a step needs: spent, not a budget too short (it was the
    # user's whole budget, 90 s, that the message once called too short)
    resumed = th.Budget(10.0, resumed=True)
    resumed.trainer = stand_in(steps_run=0, timing=timing, checkpoint_s=0.5, now_s=10.0 - reserve)
    assert resumed.before_step() == "time_budget"


def test_signals_set_the_trainers_flag_then_a_second_ctrl_c_stops_at_once_and_handlers_come_back():
    before = signal.getsignal(signal.SIGINT)
    hook = th.StopOnSignals()
    hook.trainer = stand_in()
    hook.before_train()
    try:
        signal.raise_signal(signal.SIGTERM)
        assert hook.trainer.stop_flag == {"signal": "SIGTERM"}
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    finally:
        hook.after_train()
    assert signal.getsignal(signal.SIGINT) is before


def test_metrics_average_since_the_last_line_and_write_only_once_the_folder_exists(tmp_path):
    metrics = th.Metrics()
    metrics.trainer = stand_in(run_dir=str(tmp_path), elapsed=Clock(2.0, 3.0))
    for loss in (1.0, 2.0, 4.5):
        metrics.after_step({"loss": torch.tensor(loss)})
    metrics.after_epoch()
    assert metrics.terms_mean["loss"] == pytest.approx(2.5)
    assert not (tmp_path / "metrics.jsonl").exists()  # no folder yet
    metrics.trainer.folder_started = True
    again = metrics.log("end", {"steps_run": 3})
    assert again["loss"] == pytest.approx(2.5) and again["steps_run"] == 3 and again["time_s"] == 3.0
    lines = [json.loads(x) for x in open(tmp_path / "metrics.jsonl")]
    assert [x["kind"] for x in lines] == ["end"]


def test_pre_cooldown_weights_are_kept_once_and_at_a_budgets_stop_only(tmp_path):
    model = CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8))
    opt = torch.optim.AdamW(model.parameters())
    hook = th.PreCooldown()
    cooling = {"now": False}
    hook.trainer = stand_in(run_dir=str(tmp_path / "run"), model=model, opt=opt, state={"step": 4},
                            in_cooldown=lambda now_s: cooling["now"])
    assert hook.before_step() is None and "pre_cooldown_step" not in hook.trainer.state
    hook.on_stop("SIGINT")
    assert not (tmp_path / "run").exists()
    cooling["now"] = True
    hook.before_step()
    assert hook.trainer.state["pre_cooldown_step"] == 4
    assert (tmp_path / "run" / "pre_cooldown.safetensors").exists()
    assert (tmp_path / "run" / "pre_cooldown_optimizer.pt").exists()
    hook.trainer.state["step"] = 7
    hook.before_step()
    hook.on_stop("time_budget")
    assert hook.trainer.state["pre_cooldown_step"] == 4  # kept once


def test_a_resumed_run_records_its_command_and_the_step_it_resumed_from_once(tmp_path):
    saved = {"train": {"steps": 2}, "command": "first", "resumes": []}
    folder = th.RunFolder(saved, {"command": "again", "git": "abc"}, resumed_at=2)
    folder.trainer = stand_in(run_dir=str(tmp_path), state={"step": 3})
    folder.before_train()
    assert folder.trainer.folder_started  # a resumed run's folder is there
    folder.after_step({})
    folder.trainer.state["step"] = 4
    folder.after_step({})
    record = json.load(open(os.path.join(tmp_path, "config.json")))
    assert record["train"] == {"steps": 3} and record["command"] == "first"
    assert record["resumes"] == [{"command": "again", "git": "abc", "step": 2}]


def test_checkpoints_wait_for_the_folder_then_write_every_n_steps_with_the_other_hooks_files(tmp_path):
    model = CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8))
    checkpoints = th.Checkpoints(every=2)
    saved = []

    def call(point):  # the trainer's dispatch to the other hooks
        assert point == "on_checkpoint"
        saved.append(json.loads(open(tmp_path / "state.json").read())["step"]
                     if (tmp_path / "state.json").exists() else None)

    checkpoints.trainer = stand_in(run_dir=str(tmp_path), model=model, opt=torch.optim.AdamW(model.parameters()),
                                   state={"step": 2}, clock=Clock(1.0, 1.25), elapsed=lambda: 3.14159, call=call)
    checkpoints.write()
    assert not os.listdir(tmp_path) and saved == []  # no folder yet: nothing
    checkpoints.trainer.folder_started = True
    checkpoints.after_step({})  # step 2: due
    assert saved == [None]  # the other hooks' files before state.json (written last)
    assert json.load(open(tmp_path / "state.json")) == {"step": 2, "time_s": 3.142}
    assert {"checkpoint.safetensors", "optimizer.pt"} <= set(os.listdir(tmp_path))
    assert checkpoints.trainer.checkpoint_s == 0.25
    checkpoints.trainer.state["step"] = 3
    checkpoints.after_step({})  # not due
    assert json.load(open(tmp_path / "state.json"))["step"] == 2
    checkpoints.trainer.state["step"] = 4
    checkpoints.trainer.error = RuntimeError("a step failed")
    checkpoints.after_train()  # no last checkpoint on the way out of an error
    assert json.load(open(tmp_path / "state.json"))["step"] == 2
    checkpoints.trainer.error = None
    checkpoints.after_train()
    assert json.load(open(tmp_path / "state.json"))["step"] == 4


def test_the_order_is_the_given_one_moved_only_where_a_hook_declares_whom_it_follows():
    given = [th.Checkpoints(1), th.Metrics(), th.RunFolder(None, None, 0), th.MovingAverage(None, 0.9, False),
             th.DdpAgreement(), th.Budget(1.0), th.PreCooldown(), th.StopOnSignals()]
    assert [h.name for h in th.hook_order(given)] == [
        "RunFolder", "MovingAverage", "Checkpoints", "DdpAgreement", "Metrics", "Budget", "PreCooldown",
        "StopOnSignals"]
    # a constraint on a hook that is not registered binds nothing
    assert [h.name for h in th.hook_order([th.Metrics(), th.Checkpoints(1)])] == ["Checkpoints", "Metrics"]
    for ordered in (th.hook_order(given), th.hook_order(given[::-1])):
        place = {h.name: i for i, h in enumerate(ordered)}
        assert all(place[a] < place[h.name] for h in ordered for a in h.after if a in place)


class Early(th.Hook):
    after = ("Late",)


class Late(th.Hook):
    after = ("Early",)


class Misspelt(th.Hook):
    after = ("Checkpoint",)


def test_an_order_that_cannot_hold_is_refused_when_the_hooks_are_registered():
    with pytest.raises(ValueError, match="twice"):
        th.hook_order([th.Metrics(), th.Metrics()])
    with pytest.raises(ValueError, match=r"Misspelt.after names no hook class: \['Checkpoint'\]"):
        th.hook_order([Misspelt()])
    with pytest.raises(ValueError, match="loops"):
        th.hook_order([Early(), Late()])
    assert [h.name for h in th.hook_order([Early()])] == ["Early"]  # alone, its constraint binds nothing


def test_the_budget_bar_shows_every_step_and_the_loss_it_last_read():
    """Under a time budget the bar counts seconds, so its postfix carries the step: the current one at every
    draw, not the last loss reading's (it showed step=1 until the tenth)."""
    import io

    out = io.StringIO()
    bar = th.progress_bar(100, {"step": 0}, budget_end_s=100.0, time0=0.0, enabled=True)
    bar.fp, bar.mininterval = out, 0.0
    hook = th.Progress(bar, by_budget=True)
    hook.trainer = stand_in(elapsed=lambda: 0.0)
    for step in range(1, th.POSTFIX_EVERY + 4):
        hook.trainer.state["step"], hook.trainer.steps_run = step, step
        hook.trainer.elapsed = lambda s=step: float(s)
        hook.after_step({"loss": torch.tensor(1.0 / step)})
        assert f"step={step}," in str(bar), (step, str(bar))
    assert f"loss={1.0 / th.POSTFIX_EVERY:.3f}" in str(bar)  # the last reading, at step POSTFIX_EVERY
    hook.after_train()


def test_a_resume_on_other_online_frames_names_what_changed(tmp_path):
    """Two online runs' records read alike ('online (target t, default 100 %, K = 8)') when a render setting
    differs: the refusal spells out the recorded configs' differences (it named two hashes only)."""
    from envisat_pose.perception.train import TrainConfig
    from envisat_pose.perception.train_run import check_resume

    cfg = TrainConfig()
    name = "online (target t, default 100 %, K = 8)"
    was = {"name": name, "manifest_sha256": "a" * 64, "images": None,
           "configs": {"generate": {"resolution_px": 512, "seed": 0}, "data": {"crop_px": 256}}}
    (tmp_path / "config.json").write_text(json.dumps({"train": cfg.to_dict(), "data": [was]}))
    (tmp_path / "state.json").write_text(json.dumps({"step": 3}))
    now = dict(was, manifest_sha256="b" * 64, configs={"generate": {"resolution_px": 256, "seed": 0},
                                                        "data": {"crop_px": 256}})
    with pytest.raises(InputError, match=r"\(generate\.resolution_px 512 -> 256\): resume with the same data"):
        check_resume(str(tmp_path), cfg, [now])
    assert check_resume(str(tmp_path), cfg, [was])[0] == {"step": 3}


def test_metrics_write_the_end_line_of_a_run_that_ended_well_only(tmp_path):
    """A run the loop left with an error writes no 'end' line (a reader would take it for a finished run) and
    keeps no end_line; the same hook on a run that ended writes one, stopped by its steps."""
    for error in (RuntimeError("a step failed"), None):
        metrics = th.Metrics()
        metrics.trainer = stand_in(run_dir=str(tmp_path), folder_started=True, error=error, stop=None, world=1,
                                   timing=th.LoopTiming(lambda: 1.0, 0.0), bf16=False, elapsed=lambda: 1.0,
                                   cfg=SimpleNamespace(batch_size=2), state={"step": 3, "epoch": 0, "workers": 0})
        metrics.after_step({"loss": torch.tensor(1.0)})
        metrics.after_train()
        ended = (tmp_path / "metrics.jsonl").exists()
        assert ended == (error is None) and bool(metrics.trainer.end_line) == (error is None)
    assert json.loads(open(tmp_path / "metrics.jsonl").read())["stopped_by"] == "steps"


def test_a_resumed_moving_average_goes_on_from_the_one_it_kept(tmp_path):
    """A resumed run reads ema.safetensors back and its next step averages into it: decay x the kept average +
    (1 - decay) x the weights (torch's EMA rule, computed here), not the weights alone (an average counted as
    empty restarts from the model)."""
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

    decay = 0.9

    def ema_of():  # two calls: two random initialisations
        model = CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8))
        return model, AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)

    kept_model, kept = ema_of()
    saver = th.MovingAverage(kept, decay, resume=False)
    saver.trainer = stand_in(run_dir=str(tmp_path), state={"step": 5})
    saver.on_checkpoint()
    model, ema = ema_of()
    hook = th.MovingAverage(ema, decay, resume=True)
    hook.trainer = stand_in(run_dir=str(tmp_path), state={"step": 5}, model=model)
    hook.before_train()
    hook.after_step({})
    for name, value in ema.module.state_dict().items():
        if value.is_floating_point():
            want = decay * kept_model.state_dict()[name] + (1 - decay) * model.state_dict()[name]
            torch.testing.assert_close(value, want, rtol=1e-5, atol=1e-6, msg=name)


# the order the hooks must keep at every point (design: trainer_hooks' docstrings), stated here apart from the
# hooks' own `after`: (called first, called after)
REQUIRED_BEFORE = [("RunFolder", "Checkpoints"), ("MovingAverage", "Checkpoints"), ("Checkpoints", "Metrics"),
                   ("DdpAgreement", "Metrics"), ("Checkpoints", "StopOnSignals"), ("DdpAgreement", "StopOnSignals"),
                   ("Budget", "PreCooldown")]


def test_the_hooks_keep_the_required_order_whatever_order_they_are_given_in():
    """The last checkpoint and the ranks' agreement run under the signal handlers (a Ctrl-C there does not cut
    the final write); the pre-cooldown weights are saved on rank 0's clock after the budget's refusal; the end
    line after the last checkpoint. Given in either order, forwards and backwards."""
    given = [th.Checkpoints(1), th.Metrics(), th.RunFolder(None, None, 0), th.MovingAverage(None, 0.9, False),
             th.DdpAgreement(), th.Budget(1.0), th.PreCooldown(), th.StopOnSignals()]
    for hooks in (given, given[::-1]):
        place = {h.name: i for i, h in enumerate(th.hook_order(hooks))}
        for first, then in REQUIRED_BEFORE:
            assert place[first] < place[then], (first, then)
